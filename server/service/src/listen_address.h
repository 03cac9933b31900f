// The host:port of a listening flag (--address, --metrics_address), checked
// before anything binds: gRPC would otherwise listen on a random port for
// an out-of-range one, and cpp-httplib would wrap it around. --address also
// takes unix:PATH, a Unix-domain socket (what an embedded server listens on:
// a round trip skips the TCP stack).
#ifndef MLL_SERVICE_SRC_LISTEN_ADDRESS_H_
#define MLL_SERVICE_SRC_LISTEN_ADDRESS_H_

#include <string>

#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"

namespace mll::service {

struct ListenAddress {
  // As written, IPv6 brackets included ("[::1]"); empty for a unix: address.
  std::string host;
  // 0..65535; 0 picks a free port.
  int port = 0;
  // The socket's path of unix:PATH; empty for host:port.
  std::string unix_path;
};

// The longest socket path Linux takes (sockaddr_un.sun_path, its NUL
// excluded); gRPC would fail to bind a longer one without saying why.
inline constexpr size_t kMaxUnixPathBytes = 107;

// INVALID_ARGUMENT naming `flag` ("--address") and the value unless
// `address` is host:port with a non-empty host and a decimal port in
// 0..65535, or (with `allow_unix`) unix:PATH with a non-empty PATH of at
// most kMaxUnixPathBytes bytes; `example_port` is the port the message's
// examples show.
absl::StatusOr<ListenAddress> ParseListenAddress(absl::string_view flag,
                                                 absl::string_view address,
                                                 int example_port,
                                                 bool allow_unix = false);

}  // namespace mll::service

#endif  // MLL_SERVICE_SRC_LISTEN_ADDRESS_H_
