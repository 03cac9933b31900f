#include "listen_address.h"

#include "absl/status/status.h"
#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"

namespace mll::service {
namespace {

constexpr int kMaxPort = 65535;
constexpr size_t kMaxPortDigits = 5;
constexpr absl::string_view kUnixScheme = "unix:";

}  // namespace

absl::StatusOr<ListenAddress> ParseListenAddress(absl::string_view flag,
                                                 absl::string_view address,
                                                 int example_port,
                                                 bool allow_unix) {
  if (allow_unix && absl::StartsWith(address, kUnixScheme)) {
    ListenAddress parsed;
    parsed.unix_path = std::string(address.substr(kUnixScheme.size()));
    if (parsed.unix_path.empty() ||
        parsed.unix_path.size() > kMaxUnixPathBytes) {
      return absl::InvalidArgumentError(absl::StrCat(
          flag, ": \"", address, "\" has a socket path of ",
          parsed.unix_path.size(), " bytes (allowed: unix:PATH with 1..",
          kMaxUnixPathBytes, " bytes, e.g. unix:/tmp/mll.sock)"));
    }
    return parsed;
  }
  const size_t colon = address.rfind(':');
  ListenAddress parsed;
  bool ok = colon != absl::string_view::npos && colon > 0;
  if (ok) {
    const absl::string_view port = address.substr(colon + 1);
    ok = !port.empty() && port.size() <= kMaxPortDigits;
    for (char c : port) ok = ok && absl::ascii_isdigit(c);
    if (ok) {
      for (char c : port) parsed.port = parsed.port * 10 + (c - '0');
      ok = parsed.port <= kMaxPort;
    }
    parsed.host = std::string(address.substr(0, colon));
    // An IPv6 host needs brackets, or its last group would be the port.
    ok = ok && (parsed.host.find(':') == std::string::npos ||
                (parsed.host.front() == '[' && parsed.host.back() == ']'));
  }
  if (!ok) {
    return absl::InvalidArgumentError(absl::StrCat(
        flag, ": \"", address, "\" is not host:port (allowed: e.g. 127.0.0.1:",
        example_port, ", 0.0.0.0:", example_port, ", [::1]:", example_port,
        "; port 0..", kMaxPort, ", 0 picks a free port",
        allow_unix ? "; or unix:PATH, a Unix-domain socket" : "", ")"));
  }
  return parsed;
}

}  // namespace mll::service
