// Test support: the real mll_server as a child process on a free loopback
// port, and running a command line (mll_cli) to completion.
#ifndef MLL_TESTS_CLIENT_CPP_SERVER_PROCESS_H_
#define MLL_TESTS_CLIENT_CPP_SERVER_PROCESS_H_

#include <sys/types.h>

#include <memory>
#include <string>
#include <vector>

#include "absl/status/statusor.h"

namespace mll {

class ServerProcess {
 public:
  // Starts `server_path --address=127.0.0.1:0 --port_file=F <extra_args>` and
  // waits (at most 60 s) until it has written its port to F.
  static absl::StatusOr<std::unique_ptr<ServerProcess>> Start(
      const std::string& server_path,
      const std::vector<std::string>& extra_args = {});

  // Stops the server (SIGTERM, then SIGKILL after 10 s).
  ~ServerProcess();

  // "127.0.0.1:<port>".
  const std::string& address() const { return address_; }

  // SIGKILL and reap: the server is gone at once, as after a crash.
  void Kill();
  // SIGTERM and reap; the exit status as waitpid reports it.
  int Terminate();

 private:
  ServerProcess(pid_t pid, std::string address, std::string port_file);
  int Signal(int signal_number, int grace_seconds);

  pid_t pid_;
  std::string address_;
  std::string port_file_;
};

struct CommandResult {
  int exit_code = -1;  // The exit status, or -1 if killed by a signal.
  std::string out;
  std::string err;
};

// Runs `argv` to completion (killed after `timeout_seconds`), capturing both
// output streams.
absl::StatusOr<CommandResult> RunCommand(const std::vector<std::string>& argv,
                                         int timeout_seconds = 120);

}  // namespace mll

#endif  // MLL_TESTS_CLIENT_CPP_SERVER_PROCESS_H_
