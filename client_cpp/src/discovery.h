// Discovery: an address entry "host:port" whose host is a name (a Kubernetes
// headless Service's, say) stands for every address the name resolves to,
// each one server with its own channel. The client resolves names itself
// (getaddrinfo), not through gRPC's resolver, which would make one channel
// of them all, balanced by gRPC, and hide which server holds an env.
#ifndef MLL_CLIENT_SRC_DISCOVERY_H_
#define MLL_CLIENT_SRC_DISCOVERY_H_

#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "mll/client_types.h"

namespace mll::client {
namespace internal {

// One entry of a client's address list, parsed.
struct AddressEntry {
  // As given, e.g. "mll.default.svc:50051".
  std::string text;
  // The host without brackets, and the port; empty for a gRPC target with a
  // scheme ("unix:PATH", "dns:...", "ipv4:...").
  std::string host;
  std::string port;
  // Whether `host` is a name to resolve (not an IP literal, not a target).
  bool is_name = false;
};

// Parses `entry` (checked as OpenChannel checks addresses: INVALID_ARGUMENT
// for a malformed one).
absl::StatusOr<AddressEntry> ParseAddressEntry(absl::string_view entry);

// The addresses `entry` stands for: an IP literal or a gRPC target itself; a
// name, every address it resolves to (getaddrinfo, SOCK_STREAM, IPv4 and
// IPv6), as "a.b.c.d:port" or "[v6]:port", sorted and without duplicates.
// UNAVAILABLE naming the entry when a name resolves to no address.
absl::StatusOr<std::vector<std::string>> ResolveEntry(
    const AddressEntry& entry);

// One server an address list stands for.
struct Endpoint {
  // What the client connects to: an IP address and port, or the entry
  // itself when it is no name.
  std::string address;
  // The index of the entry it came from.
  int entry = 0;
};

// The servers of `entries` (each resolved by ResolveEntry), in entry order,
// each address once (the first entry that yields it keeps it). With
// `failures`, a name that resolves to nothing is recorded there (its
// UNAVAILABLE) and the others go on; without, the first such failure is
// returned.
absl::StatusOr<std::vector<Endpoint>> ResolveEntries(
    const std::vector<AddressEntry>& entries,
    std::vector<absl::Status>* failures = nullptr);

// `options` for the servers of `entry`: with TLS, the server's certificate
// is checked against the name (unless tls_target_name_override says
// otherwise), not against the address it resolved to.
ClientOptions EndpointOptions(const AddressEntry& entry,
                              const ClientOptions& options);

// "NAME:PORT resolves to A, B", or the failure's message (which names the
// entry and says why it resolves to no address), for messages; "" for an
// entry that is no name.
std::string DescribeResolution(const AddressEntry& entry,
                               const std::vector<std::string>& addresses,
                               const absl::Status& failure);

}  // namespace internal
}  // namespace mll::client

#endif  // MLL_CLIENT_SRC_DISCOVERY_H_
