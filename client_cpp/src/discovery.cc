#include "discovery.h"

#include <arpa/inet.h>
#include <netdb.h>
#include <netinet/in.h>
#include <sys/socket.h>

#include <algorithm>
#include <string>
#include <utility>
#include <vector>

#include "absl/container/flat_hash_set.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "channel.h"

namespace mll::client {
namespace internal {
namespace {

bool IsIpLiteral(const std::string& host) {
  in6_addr v6;
  in_addr v4;
  return inet_pton(AF_INET, host.c_str(), &v4) == 1 ||
         inet_pton(AF_INET6, host.c_str(), &v6) == 1;
}

}  // namespace

absl::StatusOr<AddressEntry> ParseAddressEntry(absl::string_view entry) {
  if (absl::Status valid = CheckAddress(entry); !valid.ok()) return valid;
  AddressEntry parsed;
  parsed.text = std::string(entry);
  const size_t colon = entry.rfind(':');
  absl::string_view host = entry.substr(0, colon);
  const bool bracketed =
      absl::StartsWith(host, "[") && absl::EndsWith(host, "]");
  // A gRPC target with a scheme ("unix:/path" has no numeric port, but
  // "dns:host:50051" has): CheckAddress accepted it by its scheme.
  absl::string_view port = entry.substr(colon + 1);
  const bool numeric_port =
      !port.empty() && std::all_of(port.begin(), port.end(),
                                   [](char c) { return c >= '0' && c <= '9'; });
  if (!numeric_port || (!bracketed && absl::StrContains(host, ':'))) {
    return parsed;
  }
  if (bracketed) host = host.substr(1, host.size() - 2);
  parsed.host = std::string(host);
  parsed.port = std::string(port);
  parsed.is_name = !IsIpLiteral(parsed.host);
  return parsed;
}

absl::StatusOr<std::vector<std::string>> ResolveEntry(
    const AddressEntry& entry) {
  if (!entry.is_name) return std::vector<std::string>{entry.text};
  addrinfo hints = {};
  hints.ai_family = AF_UNSPEC;
  hints.ai_socktype = SOCK_STREAM;
  hints.ai_flags = AI_NUMERICSERV;
  addrinfo* found = nullptr;
  const int error =
      getaddrinfo(entry.host.c_str(), entry.port.c_str(), &hints, &found);
  if (error != 0) {
    return absl::UnavailableError(absl::StrCat(
        "the name in address \"", entry.text,
        "\" resolves to no address (getaddrinfo: ", gai_strerror(error), ")"));
  }
  std::vector<std::string> addresses;
  for (const addrinfo* info = found; info != nullptr; info = info->ai_next) {
    char text[INET6_ADDRSTRLEN] = {};
    if (info->ai_family == AF_INET) {
      const auto* ip = reinterpret_cast<const sockaddr_in*>(info->ai_addr);
      inet_ntop(AF_INET, &ip->sin_addr, text, sizeof(text));
      addresses.push_back(absl::StrCat(text, ":", entry.port));
    } else if (info->ai_family == AF_INET6) {
      const auto* ip = reinterpret_cast<const sockaddr_in6*>(info->ai_addr);
      inet_ntop(AF_INET6, &ip->sin6_addr, text, sizeof(text));
      addresses.push_back(absl::StrCat("[", text, "]:", entry.port));
    }
  }
  freeaddrinfo(found);
  std::sort(addresses.begin(), addresses.end());
  addresses.erase(std::unique(addresses.begin(), addresses.end()),
                  addresses.end());
  if (addresses.empty()) {
    return absl::UnavailableError(
        absl::StrCat("the name in address \"", entry.text,
                     "\" resolves to no IPv4 or IPv6 address (getaddrinfo)"));
  }
  return addresses;
}

absl::StatusOr<std::vector<Endpoint>> ResolveEntries(
    const std::vector<AddressEntry>& entries,
    std::vector<absl::Status>* failures) {
  std::vector<Endpoint> endpoints;
  absl::flat_hash_set<std::string> seen;
  if (failures != nullptr) failures->assign(entries.size(), absl::OkStatus());
  for (size_t i = 0; i < entries.size(); ++i) {
    absl::StatusOr<std::vector<std::string>> addresses =
        ResolveEntry(entries[i]);
    if (!addresses.ok()) {
      if (failures == nullptr) return addresses.status();
      (*failures)[i] = addresses.status();
      continue;
    }
    for (std::string& address : *addresses) {
      if (!seen.insert(address).second) continue;
      endpoints.push_back({std::move(address), static_cast<int>(i)});
    }
  }
  return endpoints;
}

ClientOptions EndpointOptions(const AddressEntry& entry,
                              const ClientOptions& options) {
  ClientOptions out = options;
  if (entry.is_name && out.use_tls && out.tls_target_name_override.empty()) {
    out.tls_target_name_override = entry.host;
  }
  return out;
}

std::string DescribeResolution(const AddressEntry& entry,
                               const std::vector<std::string>& addresses,
                               const absl::Status& failure) {
  if (!entry.is_name) return "";
  // The failure names the entry and says why.
  if (!failure.ok()) return std::string(failure.message());
  if (addresses.empty()) {
    return absl::StrCat(entry.text, " resolves to no address");
  }
  return absl::StrCat(entry.text, " resolves to ",
                      absl::StrJoin(addresses, ", "));
}

}  // namespace internal
}  // namespace mll::client
