// Bearer-token authentication. A server started with tokens (--auth_token_file)
// accepts a call only with the metadata `authorization: Bearer <token>` for
// one of them; each token is an owner, and environments belong to the owner
// that created them (Registry). Without tokens every caller is the one
// anonymous owner. Tokens are compared as SHA-256 digests in constant time,
// so neither their bytes nor their lengths show in the time a check takes.
#ifndef MLL_SERVICE_AUTH_H_
#define MLL_SERVICE_AUTH_H_

#include <array>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"

namespace mll::service {

// The owner of every env on a server without tokens.
inline constexpr absl::string_view kAnonymousOwner = "";

// The metadata key carrying the token (gRPC keys are lower case).
inline constexpr absl::string_view kAuthorizationKey = "authorization";

// The tokens of a token file: one per line, surrounding whitespace ignored,
// blank lines and lines starting with '#' skipped, duplicates merged.
// INVALID_ARGUMENT naming `flag` when the file cannot be read, holds no
// token, or a token has characters outside printable ASCII or whitespace
// inside (the line number is given; the token never is).
absl::StatusOr<std::vector<std::string>> ReadTokenFile(
    const std::string& path, absl::string_view flag = "--auth_token_file");

class Authenticator {
 public:
  // No tokens: authentication is off and everyone is kAnonymousOwner.
  // Tokens must be distinct (ReadTokenFile merges duplicates).
  explicit Authenticator(const std::vector<std::string>& tokens);

  bool enabled() const { return !digests_.empty(); }

  // The owner that the `authorization` metadata value (nullopt: absent)
  // authenticates, valid as long as this object. UNAUTHENTICATED, saying
  // what is expected and never repeating the presented value, when auth is
  // on and the value is missing, malformed or not a known token.
  absl::StatusOr<absl::string_view> Authenticate(
      std::optional<absl::string_view> authorization) const;

 private:
  using Digest = std::array<unsigned char, 32>;
  static Digest Sha256(absl::string_view bytes);

  std::vector<Digest> digests_;
  // owners_[i] is the owner of digests_[i]: "token#<i+1>", so that the
  // registry never holds a secret.
  std::vector<std::string> owners_;
};

}  // namespace mll::service

#endif  // MLL_SERVICE_AUTH_H_
