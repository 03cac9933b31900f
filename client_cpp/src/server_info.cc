// GetServerInfo on the client side: asking once per transport, decoding,
// and deciding whether this client can use a server (docs/server.md,
// "Versions and compatibility").
#include <string>
#include <utility>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/synchronization/mutex.h"
#include "mll/client.h"
#include "transport.h"
#include "wire.h"

#ifndef MLL_PROJECT_VERSION
#error "MLL_PROJECT_VERSION must be defined (client_cpp/CMakeLists.txt)"
#endif

namespace mll::client {
namespace internal {

absl::StatusOr<v1::ServerInfo> Transport::ServerInfo(bool fresh) {
  // Held across the call: threads asking at once make one call.
  absl::MutexLock lock(&server_info_mu_);
  if (server_info_.has_value() && !fresh) return *server_info_;
  grpc::ClientContext context;
  const absl::Duration timeout = Prepare(&context, /*unary=*/true);
  v1::ServerInfo info;
  const grpc::Status status =
      stub_->GetServerInfo(&context, v1::GetServerInfoRequest(), &info);
  if (status.error_code() == grpc::StatusCode::UNIMPLEMENTED) {
    // A release from before GetServerInfo: protocol 1.0, nothing known.
    info.Clear();
    info.set_protocol_major(1);
    info.set_protocol_minor(0);
  } else if (!status.ok()) {
    return FromCall(status, timeout);
  }
  server_info_ = info;
  return info;
}

ServerInfo DecodeServerInfo(const v1::ServerInfo& proto) {
  ServerInfo info;
  info.server_version = proto.server_version();
  info.protocol_major = proto.protocol_major();
  info.protocol_minor = proto.protocol_minor();
  info.capabilities.assign(proto.capabilities().begin(),
                           proto.capabilities().end());
  const v1::ServerLimits& limits = proto.limits();
  info.max_envs = limits.max_envs();
  info.max_envs_per_token = limits.max_envs_per_token();
  info.max_message_bytes = limits.max_message_bytes();
  info.idle_timeout_s = limits.idle_timeout_s();
  info.max_landers = limits.max_landers();
  info.threads = limits.threads();
  info.shared_memory_sessions = limits.shared_memory_sessions();
  // A server without load figures (before protocol 1.3) leaves them zero.
  const v1::ServerLoad& load = proto.load();
  info.load.envs_hosted = load.envs_hosted();
  info.load.cpu_cores = load.cpu_cores();
  info.load.cores_available = load.cores_available();
  info.load.agent_steps_per_s = load.agent_steps_per_s();
  info.json = JsonOf(proto);
  return info;
}

}  // namespace internal

namespace {

std::string ProtocolText(int major, int minor) {
  return absl::StrCat("v", major, ".", minor);
}

// "mll_server 0.1.0 at ADDRESS (protocol v1.1)".
std::string ServerText(const ServerInfo& info, absl::string_view address) {
  return absl::StrCat(
      "mll_server ",
      info.server_version.empty() ? "(a release without GetServerInfo)"
                                  : info.server_version,
      " at ", address, " (protocol ",
      ProtocolText(info.protocol_major, info.protocol_minor), ")");
}

// "this client (mll::client 0.1.0, protocol v1.1)".
std::string ClientText() {
  return absl::StrCat(
      "this client (mll::client ", Client::Version(), ", protocol ",
      ProtocolText(Client::kProtocolMajor, Client::kProtocolMinor), ")");
}

}  // namespace

bool ServerInfo::has_capability(absl::string_view name) const {
  for (const std::string& capability : capabilities) {
    if (capability == name) return true;
  }
  return false;
}

absl::string_view Client::Version() { return MLL_PROJECT_VERSION; }

absl::StatusOr<ServerInfo> Client::GetServerInfo(int server) const {
  if (server < 0 || server >= server_count()) {
    return absl::InvalidArgumentError(
        absl::StrCat("server is ", server, "; allowed: 0..", server_count() - 1,
                     " (one per address)"));
  }
  absl::StatusOr<v1::ServerInfo> proto = transports_[server]->ServerInfo();
  if (!proto.ok()) return proto.status();
  return internal::DecodeServerInfo(*proto);
}

absl::Status Client::CheckCompatible(
    const ServerInfo& info, absl::string_view address,
    absl::Span<const absl::string_view> capabilities) {
  if (info.protocol_major != kProtocolMajor) {
    const bool server_newer = info.protocol_major > kProtocolMajor;
    const int upgrade_to = server_newer ? info.protocol_major : kProtocolMajor;
    const int or_use = server_newer ? kProtocolMajor : info.protocol_major;
    return absl::FailedPreconditionError(absl::StrCat(
        ServerText(info, address), " speaks ",
        server_newer ? "a newer" : "an older", " wire protocol than ",
        ClientText(), ": upgrade the ", server_newer ? "client" : "server",
        " to a release of protocol v", upgrade_to, ", or use a ",
        server_newer ? "server" : "client", " of protocol v", or_use));
  }
  // A 1.0 server lists nothing: what it lacks shows when it is used.
  if (info.protocol_minor < 1) return absl::OkStatus();
  std::vector<std::string> missing;
  for (absl::string_view capability : capabilities) {
    if (!info.has_capability(capability)) missing.emplace_back(capability);
  }
  if (missing.empty()) return absl::OkStatus();
  return absl::FailedPreconditionError(absl::StrCat(
      ServerText(info, address), " lacks capability \"",
      absl::StrJoin(missing, "\", \""), "\", which ", ClientText(),
      " needs here (the server offers: \"",
      absl::StrJoin(info.capabilities, "\", \""),
      "\"); upgrade the server, or enable the capability if its flags "
      "turned it off"));
}

}  // namespace mll::client
