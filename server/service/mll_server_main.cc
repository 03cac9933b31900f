// mll_server: hosts Multi Lunar Lander environments over gRPC.
//
//   mll_server --address=127.0.0.1:0 --port_file=/tmp/port
//   mll_server --address=0.0.0.0:50051 --tls_cert=cert.pem --tls_key=key.pem
//       --auth_token_file=tokens.txt --metrics_address=0.0.0.0:9464
//       (one command line)
//
// SIGTERM with --drain_s > 0: drain first (health NOT_SERVING, new envs and
// Sessions refused, open Sessions ended with UNAVAILABLE "draining: ...", the
// envs left served until they are gone or --drain_s has passed). Then, as on
// SIGINT: stop accepting calls, let in-flight calls finish (up to a grace
// period), exit 0.
#include <pthread.h>
#include <signal.h>
#include <unistd.h>

#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <string>
#include <thread>
#include <vector>

#include "absl/flags/flag.h"
#include "absl/strings/str_cat.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/time.h"
#include "grpc/support/log.h"
#include "mll/service/auth.h"
#include "mll/service/server.h"
#include "program_usage.h"

ABSL_FLAG(std::string, address, "127.0.0.1:50051",
          "host:port to listen on; port 0 picks a free port; or unix:PATH, a "
          "Unix-domain socket");
ABSL_FLAG(std::string, port_file, "",
          "if set, the bound TCP port is written to this file once listening "
          "(not written for a unix: --address)");
ABSL_FLAG(int32_t, threads,
          static_cast<int32_t>(std::thread::hardware_concurrency()),
          "threads stepping a StepBatch's environments: the call's own and "
          "threads - 1 workers (default: cores)");
ABSL_FLAG(int32_t, max_envs, 10000, "most environments hosted at once");
ABSL_FLAG(int32_t, max_envs_per_token, 0,
          "most environments one token (tenant) hosts at once; 0: the "
          "default, unlimited without --auth_token_file, else "
          "max(1, max_envs / number of tokens)");
ABSL_FLAG(int32_t, shared_memory_sessions, 64,
          "most Sessions attached to shared memory at once (clients on this "
          "host; one thread each); 0: none, every session stays on its "
          "stream");
ABSL_FLAG(double, idle_timeout_s, 300,
          "an environment untouched this many seconds is destroyed");
ABSL_FLAG(double, shutdown_grace_s, 5,
          "after SIGTERM, in-flight calls get this many seconds to finish "
          "before they are cancelled (0 < S <= 3600)");
ABSL_FLAG(double, drain_s, 0,
          "on SIGTERM, drain first for up to this many seconds: health "
          "NOT_SERVING, CreateEnv and new Sessions refused (UNAVAILABLE "
          "\"draining: ...\"), open Sessions ended with that status so their "
          "clients move their envs, the envs left served until they are gone "
          "(0 <= S <= 3600; 0: no drain)");
ABSL_FLAG(int32_t, max_message_mb, 64,
          "largest message received or sent, in MiB");
ABSL_FLAG(std::string, tls_cert, "",
          "PEM certificate chain; with --tls_key the server speaks TLS only "
          "(default: plaintext)");
ABSL_FLAG(std::string, tls_key, "", "PEM private key of --tls_cert");
ABSL_FLAG(std::string, auth_token_file, "",
          "file of bearer tokens, one per line ('#' comments); when set, every "
          "call but grpc.health.v1 needs metadata `authorization: Bearer "
          "<token>` and sees only the envs created with its token");
ABSL_FLAG(std::string, metrics_address, "",
          "host:port serving Prometheus metrics at GET /metrics, e.g. "
          "127.0.0.1:9464 (empty: off)");
ABSL_FLAG(std::string, http_address, "",
          "host:port serving the web dashboard (the hosted envs and live "
          "views of them), e.g. 127.0.0.1:8080 (empty: off)");
ABSL_FLAG(int64_t, parent_pid, 0,
          "stop (as on SIGTERM) when the process with this pid, which must be "
          "the one that started mll_server, exits (Linux; 0: off); the "
          "Python client's embedded server uses it");

namespace {

// Bounds of --shutdown_grace_s (a positive time) and --drain_s: an hour.
constexpr double kMaxShutdownGraceS = 3600;

// Writes through a temporary file and a rename, so that a reader polling
// for the file never sees it half written.
bool WritePortFile(const std::string& path, int port) {
  const std::string temporary = path + ".tmp";
  {
    std::ofstream out(temporary, std::ios::trunc);
    out << port << "\n";
    if (!out.good()) return false;
  }
  return std::rename(temporary.c_str(), path.c_str()) == 0;
}

// gRPC's own log lines (e.g. "E1125 ... Failed to add port") repeat what the
// server reports itself in one line; GRPC_VERBOSITY (DEBUG, INFO, ERROR) turns
// them back on.
void QuietGrpcLogsUnlessAsked() {
  if (std::getenv("GRPC_VERBOSITY") == nullptr) {
    gpr_set_log_function([](gpr_log_func_args*) {});
  }
}

// The host part of host:port.
std::string HostOf(const std::string& address) {
  return address.substr(0, address.rfind(':'));
}

// SIGTERM and SIGINT, blocked in every thread (gRPC's threads inherit the
// mask), so that they reach only main's sigwait, outside any signal handler.
sigset_t BlockStopSignals() {
  sigset_t signals;
  sigemptyset(&signals);
  sigaddset(&signals, SIGTERM);
  sigaddset(&signals, SIGINT);
  pthread_sigmask(SIG_BLOCK, &signals, nullptr);
  return signals;
}

// The server's options from the flags, with the auth tokens read.
absl::StatusOr<mll::service::ServerOptions> ServerOptionsFromFlags() {
  mll::service::ServerOptions options;
  options.address = absl::GetFlag(FLAGS_address);
  options.max_message_mb = absl::GetFlag(FLAGS_max_message_mb);
  options.service.threads = absl::GetFlag(FLAGS_threads);
  options.service.max_envs = absl::GetFlag(FLAGS_max_envs);
  options.service.max_envs_per_token = absl::GetFlag(FLAGS_max_envs_per_token);
  options.service.shared_memory_sessions =
      absl::GetFlag(FLAGS_shared_memory_sessions);
  options.service.idle_timeout =
      absl::Seconds(absl::GetFlag(FLAGS_idle_timeout_s));
  options.tls_cert_file = absl::GetFlag(FLAGS_tls_cert);
  options.tls_key_file = absl::GetFlag(FLAGS_tls_key);
  options.metrics_address = absl::GetFlag(FLAGS_metrics_address);
  options.http_address = absl::GetFlag(FLAGS_http_address);
  const std::string token_file = absl::GetFlag(FLAGS_auth_token_file);
  if (!token_file.empty()) {
    absl::StatusOr<std::vector<std::string>> tokens =
        mll::service::ReadTokenFile(token_file);
    if (!tokens.ok()) return tokens.status();
    options.service.auth_tokens = *std::move(tokens);
  }
  return options;
}

// What the server listens on and what protects it, in two lines on stderr;
// never the tokens themselves.
void PrintBanner(const mll::service::Server& server,
                 const mll::service::ServerOptions& options,
                 double shutdown_grace_s) {
  const std::string listening =
      server.port() == 0
          ? options.address
          : absl::StrCat(HostOf(options.address), ":", server.port());
  const std::string port_file = absl::GetFlag(FLAGS_port_file);
  std::fprintf(stderr,
               "mll_server: listening on %s (--address=%s --port_file=%s "
               "--threads=%d --max_envs=%d --max_envs_per_token=%d "
               "--shared_memory_sessions=%d --idle_timeout_s=%g "
               "--max_message_mb=%d --shutdown_grace_s=%g --drain_s=%g)\n",
               listening.c_str(), options.address.c_str(), port_file.c_str(),
               options.service.threads, options.service.max_envs,
               mll::service::EffectiveMaxEnvsPerToken(options.service),
               options.service.shared_memory_sessions,
               absl::ToDoubleSeconds(options.service.idle_timeout),
               options.max_message_mb, shutdown_grace_s,
               absl::GetFlag(FLAGS_drain_s));
  const int n_tokens = static_cast<int>(options.service.auth_tokens.size());
  std::fprintf(
      stderr, "mll_server: TLS %s, auth %s, metrics %s\n",
      server.tls() ? "on" : "off (plaintext)",
      n_tokens == 0
          ? "off (anonymous)"
          : absl::StrCat("on (", n_tokens, n_tokens == 1 ? " token" : " tokens",
                         " from ", absl::GetFlag(FLAGS_auth_token_file), ")")
                .c_str(),
      server.metrics_port() == 0
          ? "off"
          : absl::StrCat("on http://", HostOf(options.metrics_address), ":",
                         server.metrics_port(), "/metrics")
                .c_str());
  if (server.http_port() != 0) {
    std::fprintf(stderr, "mll_server: dashboard on http://%s:%d/\n",
                 HostOf(options.http_address).c_str(), server.http_port());
  }
}

// Prints "mll_server: <message>" and returns main's failure code.
int Fail(const absl::Status& status) {
  std::fprintf(stderr, "mll_server: %s\n",
               std::string(status.message()).c_str());
  return 1;
}

}  // namespace

int main(int argc, char** argv) {
  mll::core::tools::ParseFlagsOnly(argc, argv, "mll_server", [] {
    return absl::StrCat(
        "mll_server: hosts Multi Lunar Lander environments over gRPC "
        "(mll.v1).\nUsage: mll_server [--flags]\n\nFlags:\n",
        mll::core::tools::DescribeFlags(
            mll::core::tools::FlagsDefinedIn("mll_server_main.cc")));
  });
  QuietGrpcLogsUnlessAsked();
  // Debian's abseil is built with Mutex deadlock detection on, which puts a
  // global graph lock on every Lock (seen in StepBatch profiles). The
  // server's lock order is fixed (the registry's, then one env's, never two
  // envs'); the tests run with detection on.
  absl::SetMutexDeadlockDetectionMode(absl::OnDeadlockCycle::kIgnore);
  sigset_t signals = BlockStopSignals();
  if (absl::Status status = mll::core::tools::FollowParent(
          absl::GetFlag(FLAGS_parent_pid), "mll_server");
      !status.ok()) {
    return Fail(status);
  }

  const double shutdown_grace_s = absl::GetFlag(FLAGS_shutdown_grace_s);
  if (!(shutdown_grace_s > 0 && shutdown_grace_s <= kMaxShutdownGraceS)) {
    return Fail(absl::InvalidArgumentError(
        absl::StrCat("--shutdown_grace_s: ", shutdown_grace_s,
                     " is out of range: allowed 0 < S <= ", kMaxShutdownGraceS,
                     " seconds")));
  }
  const double drain_s = absl::GetFlag(FLAGS_drain_s);
  if (!(drain_s >= 0 && drain_s <= kMaxShutdownGraceS)) {
    return Fail(absl::InvalidArgumentError(absl::StrCat(
        "--drain_s: ", drain_s, " is out of range: allowed 0 <= S <= ",
        kMaxShutdownGraceS, " seconds (0: no drain)")));
  }
  absl::StatusOr<mll::service::ServerOptions> options =
      ServerOptionsFromFlags();
  if (!options.ok()) return Fail(options.status());
  absl::StatusOr<std::unique_ptr<mll::service::Server>> server =
      mll::service::Server::Start(*options);
  if (!server.ok()) return Fail(server.status());
  const std::string port_file = absl::GetFlag(FLAGS_port_file);
  if (!port_file.empty() && (*server)->port() != 0 &&
      !WritePortFile(port_file, (*server)->port())) {
    return Fail(absl::InternalError(
        absl::StrCat("--port_file: cannot write ", port_file)));
  }
  PrintBanner(**server, *options, shutdown_grace_s);

  int signal_number = 0;
  sigwait(&signals, &signal_number);
  if (signal_number == SIGTERM && drain_s > 0) {
    std::fprintf(stderr,
                 "mll_server: draining on signal %d (up to --drain_s=%g)\n",
                 signal_number, drain_s);
    const absl::Time began = absl::Now();
    const int left = (*server)->Drain(absl::Seconds(drain_s));
    std::fprintf(stderr, "mll_server: drained in %.3f s, %d envs left\n",
                 absl::ToDoubleSeconds(absl::Now() - began), left);
  }
  (*server)->Shutdown(absl::Seconds(shutdown_grace_s));
  std::fprintf(stderr, "mll_server: stopped on signal %d after shutdown\n",
               signal_number);
  return 0;
}
