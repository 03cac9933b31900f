#include "channel.h"

#include <memory>
#include <string>

#include "absl/status/status.h"
#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "grpc/grpc.h"
#include "grpcpp/create_channel.h"
#include "grpcpp/security/credentials.h"
#include "grpcpp/support/channel_arguments.h"
#include "mll/http2_flow_control.h"
#include "mll/http2_keepalive.h"

namespace mll::client {
namespace internal {
namespace {

// gRPC accepts only printable ASCII in metadata values; a token with a space
// or a newline (a token file read whole) would fail every call obscurely.
// The message never repeats the token.
absl::Status CheckToken(const std::string& token) {
  for (size_t i = 0; i < token.size(); ++i) {
    const unsigned char c = static_cast<unsigned char>(token[i]);
    if (c <= ' ' || c > '~') {
      return absl::InvalidArgumentError(absl::StrCat(
          "token has character code ", static_cast<int>(c), " at position ", i,
          " (of ", token.size(), "); allowed: printable ASCII without spaces"));
    }
  }
  return absl::OkStatus();
}

}  // namespace

// A host:port target needs a port in 1..65535 (gRPC would wrap 99999 around
// to another port) and brackets around an IPv6 host. Targets with a gRPC
// scheme ("dns:", "unix:", "ipv4:", ...) are gRPC's to check.
absl::Status CheckAddress(absl::string_view address) {
  const std::string expected =
      "expected host:port with a port in 1..65535, e.g. 127.0.0.1:50051 or "
      "[::1]:50051";
  if (address.empty()) {
    return absl::InvalidArgumentError(
        absl::StrCat("address is empty; ", expected));
  }
  for (absl::string_view scheme :
       {"dns:", "unix:", "unix-abstract:", "ipv4:", "ipv6:", "vsock:"}) {
    if (absl::StartsWith(address, scheme)) return absl::OkStatus();
  }
  const size_t colon = address.rfind(':');
  absl::string_view host = address.substr(0, colon);
  const bool bracketed =
      absl::StartsWith(host, "[") && absl::EndsWith(host, "]");
  int port = 0;
  if (colon == absl::string_view::npos || host.empty() ||
      (!bracketed && absl::StrContains(host, ':')) ||
      (absl::StrContains(host, '[') && !bracketed) ||
      !absl::SimpleAtoi(address.substr(colon + 1), &port) || port < 1 ||
      port > 65535) {
    return absl::InvalidArgumentError(
        absl::StrCat("address \"", address, "\" is not valid; ", expected));
  }
  return absl::OkStatus();
}

absl::StatusOr<std::shared_ptr<grpc::Channel>> OpenChannel(
    absl::string_view address, const ClientOptions& options) {
  if (absl::Status valid = CheckAddress(address); !valid.ok()) return valid;
  if (options.max_receive_message_bytes <= 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("max_receive_message_bytes is ",
                     options.max_receive_message_bytes, "; must be > 0"));
  }
  absl::Status token = CheckToken(options.token);
  if (!token.ok()) return token;
  if (!options.use_tls && (!options.tls_root_certificates.empty() ||
                           !options.tls_target_name_override.empty())) {
    // Silently speaking plaintext when TLS settings were given would send
    // the token in the clear.
    return absl::InvalidArgumentError(
        "tls_root_certificates or tls_target_name_override is set but "
        "use_tls is false; set use_tls for TLS");
  }
  std::shared_ptr<grpc::ChannelCredentials> credentials;
  grpc::ChannelArguments arguments;
  if (options.use_tls) {
    grpc::SslCredentialsOptions ssl;
    ssl.pem_root_certs = options.tls_root_certificates;
    credentials = grpc::SslCredentials(ssl);
    if (!options.tls_target_name_override.empty()) {
      arguments.SetSslTargetNameOverride(options.tls_target_name_override);
    }
  } else {
    credentials = grpc::InsecureChannelCredentials();
  }
  arguments.SetMaxReceiveMessageSize(options.max_receive_message_bytes);
  const auto set = [&arguments](const char* name, int value) {
    arguments.SetInt(name, value);
  };
  SetHttp2FlowControl(set);
  SetClientKeepalive(set);
  // Each channel its own subchannels (connections): a new channel to a server
  // found down (VectorEnv failover's probe) must not inherit the reconnect
  // backoff of an older channel's subchannel to the same address.
  arguments.SetInt(GRPC_ARG_USE_LOCAL_SUBCHANNEL_POOL, 1);
  return grpc::CreateCustomChannel(std::string(address), credentials,
                                   arguments);
}

void AddToken(grpc::ClientContext* context, const std::string& token) {
  if (!token.empty()) {
    context->AddMetadata("authorization", absl::StrCat("Bearer ", token));
  }
}

}  // namespace internal
}  // namespace mll::client
