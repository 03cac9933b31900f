// The host:port of a listening flag (--address, --metrics_address), checked
// before anything binds: gRPC would otherwise listen on a random port for
// an out-of-range one, and cpp-httplib would wrap it around.
#ifndef MLL_SERVICE_SRC_LISTEN_ADDRESS_H_
#define MLL_SERVICE_SRC_LISTEN_ADDRESS_H_

#include <string>

#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"

namespace mll::service {

struct ListenAddress {
  // As written, IPv6 brackets included ("[::1]"); never empty.
  std::string host;
  // 0..65535; 0 picks a free port.
  int port = 0;
};

// INVALID_ARGUMENT naming `flag` ("--address") and the value unless
// `address` is host:port with a non-empty host and a decimal port in
// 0..65535; `example_port` is the port the message's examples show.
absl::StatusOr<ListenAddress> ParseListenAddress(absl::string_view flag,
                                                 absl::string_view address,
                                                 int example_port);

}  // namespace mll::service

#endif  // MLL_SERVICE_SRC_LISTEN_ADDRESS_H_
