// Test support for the fault scenarios: child processes (the real mll_server,
// the fault client) whose stdout the test reads line by line, and which it
// signals and reaps.
#ifndef MLL_TESTS_RELIABILITY_SUBPROCESS_H_
#define MLL_TESTS_RELIABILITY_SUBPROCESS_H_

#include <sys/types.h>

#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/time/time.h"

namespace mll::service::testing {

class Subprocess {
 public:
  // Starts argv[0] (a path) with `argv`; stdout goes to a pipe read by
  // ReadLine, stderr is inherited (it shows in the test's log).
  static absl::StatusOr<std::unique_ptr<Subprocess>> Start(
      const std::vector<std::string>& argv);
  // SIGKILL and reap if still running.
  ~Subprocess();
  Subprocess(const Subprocess&) = delete;
  Subprocess& operator=(const Subprocess&) = delete;

  pid_t pid() const { return pid_; }
  // Resident memory (VmRSS of /proc/<pid>/status) in KiB; -1 if unreadable.
  int64_t ResidentKib() const;
  // The next line of stdout without its newline, or nullopt at end of file
  // or when `timeout` passes first.
  std::optional<std::string> ReadLine(absl::Duration timeout);
  void Signal(int signal_number);
  // The waitpid status once the process exits, or nullopt if it is still
  // running after `timeout`.
  std::optional<int> Wait(absl::Duration timeout);

 private:
  Subprocess(pid_t pid, int stdout_fd) : pid_(pid), stdout_fd_(stdout_fd) {}

  pid_t pid_;
  int stdout_fd_;
  bool reaped_ = false;
  std::string buffered_;
};

// The real mll_server on 127.0.0.1:0 with `flags`, once it has written its
// port (--port_file).
struct ServerUnderTest {
  std::unique_ptr<Subprocess> process;
  std::string address;  // "127.0.0.1:<port>"
};
absl::StatusOr<ServerUnderTest> StartServer(
    const std::vector<std::string>& flags);

// `duration`, stretched when the tests run under a sanitizer
// (scripts/sanitize.sh sets MLL_SANITIZER), where everything is several
// times slower. Only waits are scaled, never what a test asserts.
absl::Duration Scaled(absl::Duration duration);

}  // namespace mll::service::testing

#endif  // MLL_TESTS_RELIABILITY_SUBPROCESS_H_
