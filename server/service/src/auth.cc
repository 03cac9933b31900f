#include "mll/service/auth.h"

#include <openssl/crypto.h>
#include <openssl/evp.h>

#include <fstream>
#include <utility>

#include "absl/status/status.h"
#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"

namespace mll::service {
namespace {

constexpr absl::string_view kScheme = "Bearer ";

absl::Status Unauthenticated(absl::string_view problem) {
  return absl::UnauthenticatedError(absl::StrCat(
      "metadata ", kAuthorizationKey, ": ", problem, "; this server expects `",
      kAuthorizationKey,
      ": Bearer <token>` with a token from its --auth_token_file"));
}

bool IsTokenChar(char c) { return c > ' ' && c <= '~'; }

}  // namespace

absl::StatusOr<std::vector<std::string>> ReadTokenFile(const std::string& path,
                                                       absl::string_view flag) {
  std::ifstream in(path);
  if (!in.is_open()) {
    return absl::InvalidArgumentError(
        absl::StrCat(flag, ": cannot read ", path));
  }
  std::vector<std::string> tokens;
  std::string line;
  for (int number = 1; std::getline(in, line); ++number) {
    const absl::string_view token = absl::StripAsciiWhitespace(line);
    if (token.empty() || absl::StartsWith(token, "#")) continue;
    for (char c : token) {
      if (!IsTokenChar(c)) {
        return absl::InvalidArgumentError(absl::StrCat(
            flag, ": ", path, " line ", number,
            " has a character outside printable ASCII or a space inside the "
            "token (allowed: one token of '!'..'~' per line, '#' comments)"));
      }
    }
    bool seen = false;
    for (const std::string& other : tokens) seen = seen || other == token;
    if (!seen) tokens.emplace_back(token);
  }
  if (in.bad()) {
    return absl::InvalidArgumentError(
        absl::StrCat(flag, ": error reading ", path));
  }
  if (tokens.empty()) {
    return absl::InvalidArgumentError(absl::StrCat(
        flag, ": ", path,
        " holds no token (allowed: one or more lines with a token; blank "
        "lines and '#' comments are skipped)"));
  }
  return tokens;
}

Authenticator::Authenticator(const std::vector<std::string>& tokens) {
  for (const std::string& token : tokens) {
    digests_.push_back(Sha256(token));
    owners_.push_back(absl::StrCat("token#", owners_.size() + 1));
  }
}

Authenticator::Digest Authenticator::Sha256(absl::string_view bytes) {
  Digest digest;
  unsigned int size = 0;
  // SHA-256 cannot fail on in-memory input with the default provider.
  EVP_Digest(bytes.data(), bytes.size(), digest.data(), &size, EVP_sha256(),
             nullptr);
  return digest;
}

absl::StatusOr<absl::string_view> Authenticator::Authenticate(
    std::optional<absl::string_view> authorization) const {
  if (!enabled()) return kAnonymousOwner;
  if (!authorization.has_value()) return Unauthenticated("missing");
  if (authorization->size() <= kScheme.size() ||
      !absl::EqualsIgnoreCase(authorization->substr(0, kScheme.size()),
                              kScheme)) {
    return Unauthenticated("not of the form `Bearer <token>`");
  }
  const Digest presented =
      Sha256(absl::StripAsciiWhitespace(authorization->substr(kScheme.size())));
  // Every digest is compared, so the time does not tell which one matched.
  int match = -1;
  for (int i = 0; i < static_cast<int>(digests_.size()); ++i) {
    const bool equal = CRYPTO_memcmp(presented.data(), digests_[i].data(),
                                     presented.size()) == 0;
    match = equal ? i : match;
  }
  if (match < 0) return Unauthenticated("the token is not accepted");
  return absl::string_view(owners_[match]);
}

}  // namespace mll::service
