// run_with_server SERVER COMMAND [ARGS...]: starts SERVER on a free loopback
// port, runs COMMAND ARGS... 127.0.0.1:PORT, stops the server, and exits with
// the command's exit code. For tests that drive programs from CMake scripts.
#include <iostream>
#include <string>
#include <vector>

#include "server_process.h"

int main(int argc, char** argv) {
  if (argc < 3) {
    std::cerr << "usage: run_with_server SERVER COMMAND [ARGS...]" << std::endl;
    return 2;
  }
  absl::StatusOr<std::unique_ptr<mll::client::ServerProcess>> server =
      mll::client::ServerProcess::Start(argv[1]);
  if (!server.ok()) {
    std::cerr << "run_with_server: " << server.status() << std::endl;
    return 1;
  }
  std::vector<std::string> command(argv + 2, argv + argc);
  command.push_back((*server)->address());
  absl::StatusOr<mll::client::CommandResult> result =
      mll::client::RunCommand(command);
  if (!result.ok()) {
    std::cerr << "run_with_server: " << result.status() << std::endl;
    return 1;
  }
  std::cout << result->out;
  std::cerr << result->err;
  return result->exit_code;
}
