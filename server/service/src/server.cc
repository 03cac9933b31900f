#include "mll/service/server.h"

#include <sys/socket.h>
#include <sys/un.h>
#include <unistd.h>

#include <algorithm>
#include <fstream>
#include <sstream>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/time/clock.h"
#include "grpcpp/ext/proto_server_reflection_plugin.h"
#include "grpcpp/health_check_service_interface.h"
#include "listen_address.h"
#include "metrics_http.h"
#include "mll/http2_flow_control.h"
#include "mll/http2_keepalive.h"

namespace mll::service {
namespace {

constexpr int kMaxMessageMb = 2047;  // gRPC sizes messages in an int.
constexpr absl::Duration kDestructorGrace = absl::Seconds(1);
constexpr int kExamplePort = 50051;
// How long Shutdown refuses new calls with UNAVAILABLE before gRPC's own
// shutdown, which fails calls that reach it before the client has seen its
// GOAWAY with CANCELLED, a code clients do not retry elsewhere.
constexpr absl::Duration kRefusalPeriod = absl::Milliseconds(100);
// How often Drain looks whether envs are left.
constexpr absl::Duration kDrainPoll = absl::Milliseconds(20);

// Whether a server accepts connections on the Unix-domain socket `path`.
// gRPC removes a socket file before binding its path, which would take the
// path from a server still listening there; that one is refused instead, as
// a port in use is.
bool UnixSocketAnswers(const std::string& path) {
  sockaddr_un address{};
  address.sun_family = AF_UNIX;
  path.copy(address.sun_path, sizeof(address.sun_path) - 1);
  const int fd = socket(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC, 0);
  if (fd < 0) return false;
  const bool answers =
      connect(fd, reinterpret_cast<sockaddr*>(&address), sizeof(address)) == 0;
  close(fd);
  return answers;
}

absl::Status OutOfRange(absl::string_view flag, double value,
                        absl::string_view allowed) {
  return absl::InvalidArgumentError(absl::StrCat(
      "--", flag, ": ", value, " is out of range (allowed: ", allowed, ")"));
}

absl::StatusOr<std::string> ReadPemFile(absl::string_view flag,
                                        const std::string& path) {
  std::ifstream in(path);
  std::stringstream contents;
  contents << in.rdbuf();
  if (!in.is_open() || in.bad()) {
    return absl::InvalidArgumentError(
        absl::StrCat("--", flag, ": cannot read ", path));
  }
  if (contents.str().find("-----BEGIN ") == std::string::npos) {
    return absl::InvalidArgumentError(absl::StrCat(
        "--", flag, ": ", path, " is not PEM (no -----BEGIN line)"));
  }
  return contents.str();
}

// Plaintext, or TLS with the options' certificate and key.
absl::StatusOr<std::shared_ptr<grpc::ServerCredentials>> Credentials(
    const ServerOptions& options) {
  if (options.tls_cert_file.empty()) return grpc::InsecureServerCredentials();
  absl::StatusOr<std::string> cert =
      ReadPemFile("tls_cert", options.tls_cert_file);
  if (!cert.ok()) return cert.status();
  absl::StatusOr<std::string> key =
      ReadPemFile("tls_key", options.tls_key_file);
  if (!key.ok()) return key.status();
  grpc::SslServerCredentialsOptions ssl;
  ssl.pem_key_cert_pairs.push_back({*std::move(key), *std::move(cert)});
  return grpc::SslServerCredentials(ssl);
}

gpr_timespec ToGprDeadline(absl::Duration from_now) {
  return gpr_time_add(
      gpr_now(GPR_CLOCK_MONOTONIC),
      gpr_time_from_nanos(absl::ToInt64Nanoseconds(from_now), GPR_TIMESPAN));
}

}  // namespace

absl::Status ValidateServerOptions(const ServerOptions& options) {
  if (options.service.threads < 1) {
    return OutOfRange("threads", options.service.threads, ">= 1");
  }
  if (options.service.max_envs < 1) {
    return OutOfRange("max_envs", options.service.max_envs, ">= 1");
  }
  if (options.service.max_envs_per_token < 0) {
    return OutOfRange("max_envs_per_token", options.service.max_envs_per_token,
                      ">= 1, or 0 for the default");
  }
  if (options.service.shared_memory_sessions < 0) {
    return OutOfRange("shared_memory_sessions",
                      options.service.shared_memory_sessions,
                      ">= 0 (0: no session attaches shared memory)");
  }
  if (!(options.service.idle_timeout > absl::ZeroDuration())) {
    return OutOfRange("idle_timeout_s",
                      absl::ToDoubleSeconds(options.service.idle_timeout),
                      "> 0 seconds");
  }
  if (options.max_message_mb < 1 || options.max_message_mb > kMaxMessageMb) {
    return OutOfRange("max_message_mb", options.max_message_mb,
                      absl::StrCat("1..", kMaxMessageMb));
  }
  if (!options.address.empty()) {
    absl::Status address =
        ParseListenAddress("--address", options.address, kExamplePort,
                           /*allow_unix=*/true)
            .status();
    if (!address.ok()) return address;
  }
  if (options.tls_cert_file.empty() != options.tls_key_file.empty()) {
    return absl::InvalidArgumentError(
        absl::StrCat(options.tls_cert_file.empty() ? "--tls_key" : "--tls_cert",
                     " is set without ",
                     options.tls_cert_file.empty() ? "--tls_cert" : "--tls_key",
                     " (allowed: both, for TLS, or neither, for plaintext)"));
  }
  return absl::OkStatus();
}

absl::StatusOr<std::unique_ptr<Server>> Server::Start(
    const ServerOptions& options) {
  absl::Status status = ValidateServerOptions(options);
  if (!status.ok()) return status;
  absl::StatusOr<std::shared_ptr<grpc::ServerCredentials>> credentials =
      Credentials(options);
  if (!credentials.ok()) return credentials.status();
  // Both are process-wide switches that apply to servers built after them.
  grpc::EnableDefaultHealthCheckService(true);
  grpc::reflection::InitProtoReflectionServerBuilderPlugin();

  std::unique_ptr<Server> server(new Server());
  const int max_bytes = options.max_message_mb * 1024 * 1024;
  ServiceOptions service_options = options.service;
  service_options.max_message_bytes = max_bytes;
  server->service_ = std::make_unique<MultiLunarLanderService>(service_options);
  grpc::ServerBuilder builder;
  builder.SetMaxReceiveMessageSize(max_bytes);
  builder.SetMaxSendMessageSize(max_bytes);
  builder.RegisterService(server->service_.get());
  // gRPC sets SO_REUSEPORT by default, with which a second server on a port
  // in use would share it (and its clients' envs) instead of failing.
  builder.AddChannelArgument(GRPC_ARG_ALLOW_REUSEPORT, 0);
  const auto set = [&builder](const char* name, int value) {
    builder.AddChannelArgument(name, value);
  };
  SetHttp2FlowControl(set);
  SetServerKeepalivePolicy(set);
  ListenAddress asked;
  if (!options.address.empty()) {
    asked = *ParseListenAddress("--address", options.address, kExamplePort,
                                /*allow_unix=*/true);
    if (!asked.unix_path.empty() && UnixSocketAnswers(asked.unix_path)) {
      return absl::UnavailableError(
          absl::StrCat("--address: cannot listen on ", options.address,
                       " (in use: a server answers on that socket)"));
    }
    builder.AddListeningPort(options.address, *credentials, &server->port_);
  }
  server->tls_ = !options.tls_cert_file.empty();
  server->server_ = builder.BuildAndStart();
  const bool unix_socket = !asked.unix_path.empty();
  // A unix socket has no port (gRPC reports a placeholder).
  if (unix_socket) server->port_ = 0;
  if (server->server_ == nullptr ||
      (!options.address.empty() && !unix_socket && server->port_ == 0) ||
      (asked.port != 0 && server->port_ != asked.port)) {
    return absl::UnavailableError(absl::StrCat(
        "--address: cannot listen on ", options.address,
        unix_socket ? " (its directory is missing or not writable"
                    : " (in use, or not host:port of a local interface",
        server->tls_ ? "; or --tls_cert and --tls_key do not match" : "", ")"));
  }
  if (!options.metrics_address.empty()) {
    MultiLunarLanderService* service = server->service_.get();
    absl::StatusOr<std::unique_ptr<MetricsHttpServer>> metrics =
        MetricsHttpServer::Start(options.metrics_address,
                                 [service] { return service->MetricsText(); });
    if (!metrics.ok()) return metrics.status();
    server->metrics_http_ = *std::move(metrics);
  }
  if (!options.http_address.empty()) {
    absl::StatusOr<std::unique_ptr<DashboardServer>> dashboard =
        DashboardServer::Start(options.http_address,
                               &server->service_->registry(),
                               &server->service_->authenticator());
    if (!dashboard.ok()) return dashboard.status();
    server->dashboard_ = *std::move(dashboard);
  }
  return server;
}

Server::~Server() {
  if (!shut_down_) Shutdown(kDestructorGrace);
}

int Server::metrics_port() const {
  return metrics_http_ == nullptr ? 0 : metrics_http_->port();
}

int Server::http_port() const {
  return dashboard_ == nullptr ? 0 : dashboard_->port();
}

std::shared_ptr<grpc::Channel> Server::InProcessChannel() {
  grpc::ChannelArguments arguments;
  arguments.SetMaxReceiveMessageSize(-1);
  arguments.SetMaxSendMessageSize(-1);
  return server_->InProcessChannel(arguments);
}

int Server::Drain(absl::Duration period) {
  if (shut_down_ || server_ == nullptr) return 0;
  if (grpc::HealthCheckServiceInterface* health =
          server_->GetHealthCheckService()) {
    health->Shutdown();  // NOT_SERVING from now on.
  }
  service_->StartDraining();
  const absl::Time deadline = absl::Now() + period;
  Registry& registry = service_->registry();
  for (absl::Time now = absl::Now(); registry.size() > 0 && now < deadline;
       now = absl::Now()) {
    absl::SleepFor(std::min(kDrainPoll, deadline - now));
  }
  return registry.size();
}

void Server::Shutdown(absl::Duration grace) {
  if (shut_down_ || server_ == nullptr) return;
  shut_down_ = true;
  service_->RefuseNewCalls();
  if (grpc::HealthCheckServiceInterface* health =
          server_->GetHealthCheckService()) {
    health->Shutdown();  // NOT_SERVING from now on.
  }
  const absl::Duration refusal = std::min(grace / 2, kRefusalPeriod);
  absl::SleepFor(refusal);
  server_->Shutdown(ToGprDeadline(grace - refusal));
  server_->Wait();
  dashboard_.reset();
  // Scrapes keep working while calls drain, so the last counts are seen.
  metrics_http_.reset();
}

}  // namespace mll::service
