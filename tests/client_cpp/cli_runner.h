// mll_cli as the tests run it. Header-only because the path is a compile
// definition of the test programs (MLL_CLI_PATH), not of the support library,
// which bench/client_cpp also builds.
#ifndef MLL_TESTS_CLIENT_CPP_CLI_RUNNER_H_
#define MLL_TESTS_CLIENT_CPP_CLI_RUNNER_H_

#include <string>
#include <utility>
#include <vector>

#include "server_process.h"

namespace mll::client {

// The build's mll_cli with `args`, to completion; when it cannot be run,
// exit_code is -1 and err says why.
inline CommandResult RunCli(std::vector<std::string> args) {
  args.insert(args.begin(), MLL_CLI_PATH);
  absl::StatusOr<CommandResult> result = RunCommand(args);
  if (result.ok()) return *std::move(result);
  CommandResult failed;
  failed.err = result.status().ToString();
  return failed;
}

}  // namespace mll::client

#endif  // MLL_TESTS_CLIENT_CPP_CLI_RUNNER_H_
