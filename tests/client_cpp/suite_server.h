// Test support: one mll_server shared by every test of a suite.
#ifndef MLL_TESTS_CLIENT_CPP_SUITE_SERVER_H_
#define MLL_TESTS_CLIENT_CPP_SUITE_SERVER_H_

#include <memory>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "gtest/gtest.h"
#include "server_process.h"

namespace mll::client {

// For a suite's SetUpTestSuite: starts MLL_SERVER_PATH with `flags`; the
// suite's TearDownTestSuite deletes what it returns. When the server does not
// start, the suite fails with the reason and this returns nullptr.
inline ServerProcess* StartSuiteServer(
    const std::vector<std::string>& flags = {}) {
  absl::StatusOr<std::unique_ptr<ServerProcess>> server =
      ServerProcess::Start(MLL_SERVER_PATH, flags);
  if (!server.ok()) {
    ADD_FAILURE() << "mll_server did not start: " << server.status();
    return nullptr;
  }
  return server->release();
}

}  // namespace mll::client

#endif  // MLL_TESTS_CLIENT_CPP_SUITE_SERVER_H_
