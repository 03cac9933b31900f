// The gRPC channel to one server from the client's options (address checks,
// TLS or plaintext, message size), and the bearer token of every call. Shared
// by the C++ client and the native stream library of the Python client.
#ifndef MLL_CLIENT_SRC_CHANNEL_H_
#define MLL_CLIENT_SRC_CHANNEL_H_

#include <memory>
#include <string>

#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "grpcpp/channel.h"
#include "grpcpp/client_context.h"
#include "mll/client.h"

namespace mll::client {
namespace internal {

// OK for "host:port" with a port in 1..65535 (an IPv6 host in brackets) or a
// gRPC target with a scheme ("unix:PATH", ...); else INVALID_ARGUMENT saying
// what is expected.
absl::Status CheckAddress(absl::string_view address);

// A channel to `address` (host:port, or a gRPC target such as unix:PATH) with
// `options`' TLS settings and largest received message; INVALID_ARGUMENT for
// a malformed address, token or option.
absl::StatusOr<std::shared_ptr<grpc::Channel>> OpenChannel(
    absl::string_view address, const ClientOptions& options);

// Adds `authorization: Bearer <token>` to the call, unless `token` is empty.
void AddToken(grpc::ClientContext* context, const std::string& token);

}  // namespace internal
}  // namespace mll::client

#endif  // MLL_CLIENT_SRC_CHANNEL_H_
