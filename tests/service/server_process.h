// The mll_server binary as a child process of a test, and gRPC's health
// check as raw bytes: shared by the tests that run the real binary.
#ifndef MLL_TESTS_SERVICE_SERVER_PROCESS_H_
#define MLL_TESTS_SERVICE_SERVER_PROCESS_H_

#include <sys/types.h>

#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "grpcpp/grpcpp.h"

namespace mll::service::testing {

// mll_server on 127.0.0.1:0 with --port_file and `flags`; killed (SIGKILL)
// on destruction unless it has exited. With `log_file`, its stderr goes
// there.
class ServerProcess {
 public:
  explicit ServerProcess(std::vector<std::string> flags,
                         const std::string& log_file = "");
  ~ServerProcess();
  ServerProcess(const ServerProcess&) = delete;
  ServerProcess& operator=(const ServerProcess&) = delete;

  // The port from --port_file, polled for at most 20 s; 0 on timeout.
  int WaitForPort();

  // Sends `signal` and returns the exit status, or -1 if the process did not
  // exit within 15 s.
  int SignalAndWait(int signal);

 private:
  pid_t pid_ = -1;
  std::string port_file_;
};

// Runs the binary with `flags` (shell words) to completion; its exit code
// and output (stdout and stderr).
std::pair<int, std::string> RunServer(const std::string& flags);

// grpc.health.v1.Health/Check for the whole server, as the response's raw
// protobuf bytes (the health proto's C++ stubs are not part of Debian's
// gRPC); "\x08\x01" is SERVING.
std::string HealthCheck(const std::shared_ptr<grpc::Channel>& channel,
                        grpc::Status* status);

}  // namespace mll::service::testing

#endif  // MLL_TESTS_SERVICE_SERVER_PROCESS_H_
