#include "server_process.h"

#include <fcntl.h>
#include <signal.h>
#include <sys/prctl.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <regex>
#include <sstream>
#include <thread>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/strip.h"

namespace mll::client {
namespace {

using Clock = std::chrono::steady_clock;

// A fresh, empty file in the test's temporary directory.
absl::StatusOr<std::string> MakeTempFile(const std::string& stem) {
  const char* dir = std::getenv("TMPDIR");
  std::string path =
      absl::StrCat(dir != nullptr ? dir : "/tmp", "/", stem, "_XXXXXX");
  const int fd = mkstemp(path.data());
  if (fd < 0) {
    return absl::InternalError(absl::StrCat("mkstemp ", path, " failed"));
  }
  close(fd);
  return path;
}

std::string ReadFile(const std::string& path) {
  std::ifstream file(path, std::ios::binary);
  std::stringstream contents;
  contents << file.rdbuf();
  return contents.str();
}

// fork + exec of `argv`, stdout/stderr to the given files when not empty.
absl::StatusOr<pid_t> Spawn(const std::vector<std::string>& argv,
                            const std::string& out_path,
                            const std::string& err_path) {
  std::vector<char*> args;
  for (const std::string& arg : argv)
    args.push_back(const_cast<char*>(arg.c_str()));
  args.push_back(nullptr);
  const pid_t pid = fork();
  if (pid < 0) return absl::InternalError("fork failed");
  if (pid == 0) {
    // A child outlives a crashed test otherwise, holding its output pipes
    // open (ctest would wait for them) and its port.
    prctl(PR_SET_PDEATHSIG, SIGTERM);
    if (!out_path.empty()) {
      const int out = open(out_path.c_str(), O_WRONLY | O_TRUNC);
      dup2(out, STDOUT_FILENO);
    }
    if (!err_path.empty()) {
      const int err = open(err_path.c_str(), O_WRONLY | O_TRUNC);
      dup2(err, STDERR_FILENO);
    }
    execvp(args[0], args.data());
    _exit(127);
  }
  return pid;
}

// waitpid with a deadline; true when the child was reaped.
bool WaitFor(pid_t pid, int seconds, int* status) {
  const auto deadline = Clock::now() + std::chrono::seconds(seconds);
  while (Clock::now() < deadline) {
    const pid_t done = waitpid(pid, status, WNOHANG);
    if (done == pid) return true;
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  return false;
}

}  // namespace

absl::StatusOr<std::unique_ptr<ServerProcess>> ServerProcess::Start(
    const std::string& server_path,
    const std::vector<std::string>& extra_args) {
  std::vector<std::string> argv = {server_path, "--address=127.0.0.1:0"};
  argv.insert(argv.end(), extra_args.begin(), extra_args.end());
  return StartProgram(std::move(argv));
}

absl::StatusOr<std::unique_ptr<ServerProcess>> ServerProcess::StartProgram(
    std::vector<std::string> argv) {
  const std::string server_path = argv[0];
  absl::StatusOr<std::string> port_file = MakeTempFile("mll_port");
  if (!port_file.ok()) return port_file.status();
  argv.push_back(absl::StrCat("--port_file=", *port_file));
  absl::StatusOr<pid_t> pid = Spawn(argv, "", "");
  if (!pid.ok()) return pid.status();

  const auto deadline = Clock::now() + std::chrono::seconds(60);
  std::string previous;
  while (Clock::now() < deadline) {
    int status = 0;
    if (waitpid(*pid, &status, WNOHANG) == *pid) {
      return absl::InternalError(absl::StrCat(server_path, " exited (status ",
                                              status, ") before serving"));
    }
    // Accepted once two reads a moment apart agree, so a half-written file
    // is never taken for the port.
    const std::string text(absl::StripAsciiWhitespace(ReadFile(*port_file)));
    int port = 0;
    if (!text.empty() && text == previous && absl::SimpleAtoi(text, &port) &&
        port > 0) {
      return std::unique_ptr<ServerProcess>(new ServerProcess(
          *pid, absl::StrCat("127.0.0.1:", port), *port_file));
    }
    previous = text;
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  kill(*pid, SIGKILL);
  waitpid(*pid, nullptr, 0);
  return absl::DeadlineExceededError(
      absl::StrCat(server_path, " wrote no port to ", *port_file, " in 60 s"));
}

ServerProcess::ServerProcess(pid_t pid, std::string address,
                             std::string port_file)
    : pid_(pid),
      address_(std::move(address)),
      port_file_(std::move(port_file)) {}

ServerProcess::~ServerProcess() {
  if (pid_ > 0) Terminate();
  unlink(port_file_.c_str());
}

int ServerProcess::Signal(int signal_number, int grace_seconds) {
  if (pid_ <= 0) return -1;
  int status = 0;
  kill(pid_, signal_number);
  kill(pid_, SIGCONT);  // A paused process handles the signal once resumed.
  if (!WaitFor(pid_, grace_seconds, &status)) {
    kill(pid_, SIGKILL);
    waitpid(pid_, &status, 0);
  }
  pid_ = -1;
  return status;
}

void ServerProcess::Kill() { Signal(SIGKILL, 10); }

void ServerProcess::Pause() {
  kill(pid_, SIGSTOP);
  // SIGSTOP stops each thread when it next runs kernel code: wait (at most
  // 10 s) until every thread of the server reads as stopped, so that nothing
  // sent from now on is answered.
  const std::string tasks = absl::StrCat("/proc/", pid_, "/task");
  const auto deadline =
      std::chrono::steady_clock::now() + std::chrono::seconds(10);
  while (std::chrono::steady_clock::now() < deadline) {
    bool all_stopped = true;
    for (const auto& task : std::filesystem::directory_iterator(tasks)) {
      std::ifstream stat(task.path() / "stat");
      std::string line;
      std::getline(stat, line);
      const size_t end_of_name = line.rfind(')');
      const char state =
          end_of_name + 2 < line.size() ? line[end_of_name + 2] : '?';
      if (state != 'T' && state != 't') all_stopped = false;
    }
    if (all_stopped) return;
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
  }
}

void ServerProcess::Resume() {
  if (pid_ > 0) kill(pid_, SIGCONT);
}

int ServerProcess::Terminate() { return Signal(SIGTERM, 10); }

absl::StatusOr<CommandResult> RunCommand(const std::vector<std::string>& argv,
                                         int timeout_seconds) {
  absl::StatusOr<std::string> out_path = MakeTempFile("mll_out");
  if (!out_path.ok()) return out_path.status();
  absl::StatusOr<std::string> err_path = MakeTempFile("mll_err");
  if (!err_path.ok()) return err_path.status();
  absl::StatusOr<pid_t> pid = Spawn(argv, *out_path, *err_path);
  if (!pid.ok()) return pid.status();
  int status = 0;
  if (!WaitFor(*pid, timeout_seconds, &status)) {
    kill(*pid, SIGKILL);
    waitpid(*pid, &status, 0);
    return absl::DeadlineExceededError(
        absl::StrCat(argv[0], " did not finish in ", timeout_seconds, " s"));
  }
  CommandResult result;
  result.exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  result.out = ReadFile(*out_path);
  result.err = ReadFile(*err_path);
  unlink(out_path->c_str());
  unlink(err_path->c_str());
  return result;
}

bool Eventually(const std::function<bool()>& condition, int seconds) {
  const auto deadline = Clock::now() + std::chrono::seconds(seconds);
  while (!condition()) {
    if (Clock::now() >= deadline) return false;
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  return true;
}

std::string EnvNameIn(const std::string& json) {
  static const std::regex kName("\"name\":\"(envs/[^\"]+)\"");
  std::smatch match;
  return std::regex_search(json, match, kName) ? match[1].str() : "";
}

absl::StatusOr<std::string> WriteTempFile(const std::string& stem,
                                          const std::string& contents) {
  absl::StatusOr<std::string> path = MakeTempFile(stem);
  if (!path.ok()) return path.status();
  std::ofstream file(*path, std::ios::binary | std::ios::trunc);
  file << contents;
  file.close();
  if (!file) return absl::InternalError(absl::StrCat("cannot write ", *path));
  return path;
}

absl::StatusOr<Certificate> MakeSelfSignedCertificate(
    const std::string& stem, const std::string& subject_alt_names) {
  Certificate certificate;
  absl::StatusOr<std::string> cert_file = MakeTempFile(stem + "_cert");
  if (!cert_file.ok()) return cert_file.status();
  absl::StatusOr<std::string> key_file = MakeTempFile(stem + "_key");
  if (!key_file.ok()) return key_file.status();
  certificate.cert_file = *cert_file;
  certificate.key_file = *key_file;
  absl::StatusOr<CommandResult> openssl =
      RunCommand({"openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt",
                  "ec_paramgen_curve:prime256v1", "-nodes", "-days", "2",
                  "-subj", "/CN=mll-test", "-addext",
                  absl::StrCat("subjectAltName=", subject_alt_names), "-keyout",
                  certificate.key_file, "-out", certificate.cert_file},
                 60);
  if (!openssl.ok()) return openssl.status();
  if (openssl->exit_code != 0) {
    return absl::InternalError(absl::StrCat(
        "openssl req exited ", openssl->exit_code, ": ", openssl->err));
  }
  certificate.cert_pem = ReadFile(certificate.cert_file);
  if (certificate.cert_pem.find("-----BEGIN CERTIFICATE-----") ==
      std::string::npos) {
    return absl::InternalError(absl::StrCat(
        "openssl wrote no PEM certificate to ", certificate.cert_file));
  }
  return certificate;
}

}  // namespace mll::client
