#include "mll/service/server.h"

#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/time/clock.h"
#include "grpcpp/ext/proto_server_reflection_plugin.h"
#include "grpcpp/health_check_service_interface.h"

namespace mll {
namespace {

constexpr int kMaxMessageMb = 2047;  // gRPC sizes messages in an int.
constexpr absl::Duration kDestructorGrace = absl::Seconds(1);

absl::Status OutOfRange(absl::string_view flag, double value,
                        absl::string_view allowed) {
  return absl::InvalidArgumentError(
      absl::StrCat("--", flag, ": ", value, " is out of range (allowed: ",
                   allowed, ")"));
}

gpr_timespec ToGprDeadline(absl::Duration from_now) {
  return gpr_time_add(gpr_now(GPR_CLOCK_MONOTONIC),
                      gpr_time_from_nanos(absl::ToInt64Nanoseconds(from_now),
                                          GPR_TIMESPAN));
}

}  // namespace

absl::Status ValidateServerOptions(const ServerOptions& options) {
  if (options.service.threads < 1) {
    return OutOfRange("threads", options.service.threads, ">= 1");
  }
  if (options.service.max_envs < 1) {
    return OutOfRange("max_envs", options.service.max_envs, ">= 1");
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
  return absl::OkStatus();
}

absl::StatusOr<std::unique_ptr<Server>> Server::Start(
    const ServerOptions& options) {
  absl::Status status = ValidateServerOptions(options);
  if (!status.ok()) return status;
  // Both are process-wide switches that apply to servers built after them.
  grpc::EnableDefaultHealthCheckService(true);
  grpc::reflection::InitProtoReflectionServerBuilderPlugin();

  std::unique_ptr<Server> server(new Server());
  server->service_ = std::make_unique<MultiLunarLanderService>(options.service);
  grpc::ServerBuilder builder;
  const int max_bytes = options.max_message_mb * 1024 * 1024;
  builder.SetMaxReceiveMessageSize(max_bytes);
  builder.SetMaxSendMessageSize(max_bytes);
  builder.RegisterService(server->service_.get());
  if (!options.address.empty()) {
    builder.AddListeningPort(options.address,
                             grpc::InsecureServerCredentials(),
                             &server->port_);
  }
  server->server_ = builder.BuildAndStart();
  if (server->server_ == nullptr ||
      (!options.address.empty() && server->port_ == 0)) {
    return absl::UnavailableError(absl::StrCat(
        "--address: cannot listen on ", options.address,
        " (in use, or not host:port of a local interface)"));
  }
  return server;
}

Server::~Server() {
  if (!shut_down_) Shutdown(kDestructorGrace);
}

std::shared_ptr<grpc::Channel> Server::InProcessChannel() {
  grpc::ChannelArguments arguments;
  arguments.SetMaxReceiveMessageSize(-1);
  arguments.SetMaxSendMessageSize(-1);
  return server_->InProcessChannel(arguments);
}

void Server::Shutdown(absl::Duration grace) {
  if (shut_down_ || server_ == nullptr) return;
  shut_down_ = true;
  server_->Shutdown(ToGprDeadline(grace));
  server_->Wait();
}

}  // namespace mll
