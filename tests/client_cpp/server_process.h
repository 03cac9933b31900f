// Test support: the real mll_server as a child process on a free loopback
// port, and running a command line (mll_cli) to completion.
#ifndef MLL_TESTS_CLIENT_CPP_SERVER_PROCESS_H_
#define MLL_TESTS_CLIENT_CPP_SERVER_PROCESS_H_

#include <sys/types.h>

#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/statusor.h"

namespace mll::client {

class ServerProcess {
 public:
  // Starts `server_path --address=127.0.0.1:0 --port_file=F <extra_args>` and
  // waits (at most 60 s) until it has written its port to F.
  static absl::StatusOr<std::unique_ptr<ServerProcess>> Start(
      const std::string& server_path,
      const std::vector<std::string>& extra_args = {});
  // Any program that writes its port to the file of a --port_file flag:
  // `argv --port_file=F`, waited for as Start does (e.g. a delay_proxy).
  static absl::StatusOr<std::unique_ptr<ServerProcess>> StartProgram(
      std::vector<std::string> argv);

  // Stops the server (SIGTERM, then SIGKILL after 10 s).
  ~ServerProcess();

  // "127.0.0.1:<port>".
  const std::string& address() const { return address_; }

  // SIGKILL and reap: the server is gone at once, as after a crash.
  void Kill();
  // SIGSTOP: the server answers nothing until killed or resumed (requests
  // sent meanwhile stay in flight).
  void Pause();
  // SIGCONT: a paused server runs again.
  void Resume();
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
// output streams. argv[0] without a slash is looked up in PATH.
absl::StatusOr<CommandResult> RunCommand(const std::vector<std::string>& argv,
                                         int timeout_seconds = 120);

// The env name in mll_cli's JSON output (`"name":"envs/..."`); empty if none.
std::string EnvNameIn(const std::string& json);

// Polls `condition` every 10 ms until it holds or `seconds` pass; whether it
// held. For what a server does just after answering: it deletes a session's
// envs once the stream has ended, after the client has its final status.
bool Eventually(const std::function<bool()>& condition, int seconds = 10);

// A new file in the temporary directory holding `contents`; its path.
absl::StatusOr<std::string> WriteTempFile(const std::string& stem,
                                          const std::string& contents);

// A fresh self-signed P-256 certificate and its key, made with the openssl
// CLI for `subject_alt_names` (e.g. "DNS:localhost,IP:127.0.0.1"), in files
// of the temporary directory.
struct Certificate {
  std::string cert_file;
  std::string key_file;
  // The certificate's PEM text: a client's root for this server.
  std::string cert_pem;
};
absl::StatusOr<Certificate> MakeSelfSignedCertificate(
    const std::string& stem, const std::string& subject_alt_names);

}  // namespace mll::client

#endif  // MLL_TESTS_CLIENT_CPP_SERVER_PROCESS_H_
