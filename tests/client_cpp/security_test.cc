// mll::client and mll_cli against real mll_server processes with TLS (a
// self-signed certificate made at test time with the openssl CLI) and bearer
// tokens (--auth_token_file), over loopback.
#include <stdlib.h>

#include <chrono>
#include <memory>
#include <string>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/strings/strip.h"
#include "cli_runner.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "mll/client.h"
#include "server_process.h"

namespace mll::client {
namespace {

using ::testing::HasSubstr;
using ::testing::Not;

constexpr char kTokenA[] = "token-a-7f3e9c";
constexpr char kTokenB[] = "token-b-41d0aa";

// Servers and certificates shared by the suite:
//  - secure: TLS with a certificate for localhost/127.0.0.1, tokens A and B;
//  - renamed: TLS with a certificate for mll.test only, no tokens.
// `stranger` is a certificate no server uses.
class SecureServers : public ::testing::Environment {
 public:
  void SetUp() override {
    absl::StatusOr<Certificate> local =
        MakeSelfSignedCertificate("mll_local", "DNS:localhost,IP:127.0.0.1");
    ASSERT_TRUE(local.ok()) << local.status();
    absl::StatusOr<Certificate> renamed =
        MakeSelfSignedCertificate("mll_renamed", "DNS:mll.test");
    ASSERT_TRUE(renamed.ok()) << renamed.status();
    absl::StatusOr<Certificate> stranger =
        MakeSelfSignedCertificate("mll_stranger", "DNS:localhost,IP:127.0.0.1");
    ASSERT_TRUE(stranger.ok()) << stranger.status();
    local_ = *local;
    renamed_ = *renamed;
    stranger_ = *stranger;
    absl::StatusOr<std::string> tokens = WriteTempFile(
        "mll_tokens",
        absl::StrCat("# test tokens\n", kTokenA, "\n", kTokenB, "\n"));
    ASSERT_TRUE(tokens.ok()) << tokens.status();
    token_file_ = *tokens;

    absl::StatusOr<std::unique_ptr<ServerProcess>> secure =
        ServerProcess::Start(
            MLL_SERVER_PATH,
            {"--tls_cert=" + local_.cert_file, "--tls_key=" + local_.key_file,
             "--auth_token_file=" + token_file_});
    ASSERT_TRUE(secure.ok()) << secure.status();
    secure_ = *std::move(secure);
    absl::StatusOr<std::unique_ptr<ServerProcess>> named = ServerProcess::Start(
        MLL_SERVER_PATH,
        {"--tls_cert=" + renamed_.cert_file, "--tls_key=" + renamed_.key_file});
    ASSERT_TRUE(named.ok()) << named.status();
    renamed_server_ = *std::move(named);
  }
  void TearDown() override {
    secure_.reset();
    renamed_server_.reset();
  }

  static const std::string& secure_address() { return secure_->address(); }
  static const std::string& renamed_address() {
    return renamed_server_->address();
  }
  static const Certificate& local() { return local_; }
  static const Certificate& renamed() { return renamed_; }
  static const Certificate& stranger() { return stranger_; }
  static const std::string& token_file() { return token_file_; }

 private:
  static inline std::unique_ptr<ServerProcess> secure_;
  static inline std::unique_ptr<ServerProcess> renamed_server_;
  static inline Certificate local_;
  static inline Certificate renamed_;
  static inline Certificate stranger_;
  static inline std::string token_file_;
};

// Options trusting `root` (TLS) or plaintext when `root` is null.
ClientOptions Options(const Certificate* root, const std::string& token) {
  ClientOptions options;
  options.use_tls = root != nullptr;
  if (root != nullptr) options.tls_root_certificates = root->cert_pem;
  options.token = token;
  // Failing handshakes must not hang a test.
  options.call_timeout = std::chrono::seconds(10);
  return options;
}

Client Connect(const std::string& address, const ClientOptions& options) {
  absl::StatusOr<Client> client = Client::Create(address, options);
  EXPECT_TRUE(client.ok()) << client.status();
  return *std::move(client);
}

Client Secure(const std::string& token) {
  return Connect(SecureServers::secure_address(),
                 Options(&SecureServers::local(), token));
}

RemoteEnvConfig OneLander() {
  RemoteEnvConfig config;
  config.n_landers = 1;
  return config;
}

// Reset, parallel step and a one-item StepBatch through `client`.
void ExpectFlies(const Client& client) {
  absl::StatusOr<RemoteEnv> env = client.CreateEnv(OneLander());
  ASSERT_TRUE(env.ok()) << env.status();
  ASSERT_TRUE(env->Reset(5).ok());
  const std::vector<int32_t> action = {2};
  absl::StatusOr<StepData> step = env->Step(Actions::Discrete(action));
  ASSERT_TRUE(step.ok()) << step.status();
  EXPECT_EQ(step->cycles, 1);
  const BatchStep item{&*env, Actions::Discrete(action)};
  absl::StatusOr<std::vector<absl::StatusOr<StepData>>> batch =
      client.StepBatch({&item, 1});
  ASSERT_TRUE(batch.ok()) << batch.status();
  ASSERT_TRUE((*batch)[0].ok()) << (*batch)[0].status();
  EXPECT_EQ((*batch)[0]->cycles, 2);
  EXPECT_TRUE(env->Delete().ok());
}

// ---------------------------------------------------------------------- TLS

TEST(TlsTest, ClientTrustingTheCertificateWorksUnaryAndSession) {
  const std::string port = std::string(
      absl::StripPrefix(SecureServers::secure_address(), "127.0.0.1:"));
  // The certificate names both the IP and localhost.
  for (const std::string host : {"127.0.0.1", "localhost"}) {
    SCOPED_TRACE(host);
    const Client client = Connect(absl::StrCat(host, ":", port),
                                  Options(&SecureServers::local(), kTokenA));
    EXPECT_TRUE(client.CheckHealth().ok()) << client.CheckHealth();
    ASSERT_NO_FATAL_FAILURE(ExpectFlies(client));
    absl::StatusOr<Client> session = client.OpenSession();
    ASSERT_TRUE(session.ok()) << session.status();
    ASSERT_NO_FATAL_FAILURE(ExpectFlies(*session));
  }
}

TEST(TlsTest, PlaintextAndUntrustingClientsCannotTalk) {
  const Client plaintext =
      Connect(SecureServers::secure_address(), Options(nullptr, kTokenA));
  EXPECT_EQ(plaintext.CreateEnv().status().code(),
            absl::StatusCode::kUnavailable);
  EXPECT_EQ(plaintext.CheckHealth().code(), absl::StatusCode::kUnavailable);
  const Client untrusting =
      Connect(SecureServers::secure_address(),
              Options(&SecureServers::stranger(), kTokenA));
  EXPECT_EQ(untrusting.CreateEnv().status().code(),
            absl::StatusCode::kUnavailable);
  EXPECT_EQ(untrusting.CheckHealth().code(), absl::StatusCode::kUnavailable);
}

TEST(TlsTest, TargetNameOverrideChecksTheCertificateForThatName) {
  // The certificate names mll.test only, not the 127.0.0.1 dialled.
  ClientOptions options = Options(&SecureServers::renamed(), "");
  const Client by_address = Connect(SecureServers::renamed_address(), options);
  EXPECT_EQ(by_address.CheckHealth().code(), absl::StatusCode::kUnavailable);
  options.tls_target_name_override = "mll.test";
  const Client by_name = Connect(SecureServers::renamed_address(), options);
  EXPECT_TRUE(by_name.CheckHealth().ok()) << by_name.CheckHealth();
  ASSERT_NO_FATAL_FAILURE(ExpectFlies(by_name));
  options.tls_target_name_override = "other.test";
  const Client wrong_name = Connect(SecureServers::renamed_address(), options);
  EXPECT_EQ(wrong_name.CheckHealth().code(), absl::StatusCode::kUnavailable);
}

TEST(TlsTest, TlsSettingsWithoutTlsAreRejected) {
  ClientOptions options = Options(&SecureServers::local(), "");
  options.use_tls = false;
  absl::StatusOr<Client> client =
      Client::Create(SecureServers::secure_address(), options);
  EXPECT_EQ(client.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(client.status().message(), HasSubstr("use_tls is false"));
}

// ------------------------------------------------------------------- tokens

TEST(TokenTest, RightTokenWorksMissingOrWrongIsUnauthenticated) {
  ASSERT_NO_FATAL_FAILURE(ExpectFlies(Secure(kTokenA)));
  ASSERT_NO_FATAL_FAILURE(ExpectFlies(Secure(kTokenB)));
  for (const std::string token : {"", "token-c-wrong"}) {
    SCOPED_TRACE("token \"" + token + "\"");
    const Client client = Secure(token);
    // Health needs no token.
    EXPECT_TRUE(client.CheckHealth().ok()) << client.CheckHealth();
    const absl::Status created = client.CreateEnv().status();
    EXPECT_EQ(created.code(), absl::StatusCode::kUnauthenticated) << created;
    EXPECT_EQ(client.ListEnvs().status().code(),
              absl::StatusCode::kUnauthenticated);
    EXPECT_EQ(client.GetEnv("envs/x").status().code(),
              absl::StatusCode::kUnauthenticated);
    // The Session stream carries the token too: without it the stream fails.
    absl::StatusOr<Client> session = client.OpenSession();
    ASSERT_TRUE(session.ok()) << session.status();
    EXPECT_EQ(session->CreateEnv().status().code(),
              absl::StatusCode::kUnauthenticated);
  }
}

TEST(TokenTest, EnvsOfOneTokenAreNotFoundForAnother) {
  const Client a = Secure(kTokenA);
  const Client b = Secure(kTokenB);
  absl::StatusOr<RemoteEnv> env = a.CreateEnv(OneLander());
  ASSERT_TRUE(env.ok()) << env.status();
  ASSERT_TRUE(env->Reset(1).ok());
  const std::string& name = env->name();

  EXPECT_EQ(b.GetEnv(name).status().code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(b.Attach(name).status().code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(b.DeleteEnv(name).code(), absl::StatusCode::kNotFound);
  // A's handle stepped through B's client goes out with B's token.
  const std::vector<int32_t> action = {0};
  const BatchStep item{&*env, Actions::Discrete(action)};
  absl::StatusOr<std::vector<absl::StatusOr<StepData>>> batch =
      b.StepBatch({&item, 1});
  ASSERT_TRUE(batch.ok()) << batch.status();
  EXPECT_EQ((*batch)[0].status().code(), absl::StatusCode::kNotFound);
  absl::StatusOr<std::vector<EnvInfo>> listed_b = b.ListEnvs();
  ASSERT_TRUE(listed_b.ok()) << listed_b.status();
  for (const EnvInfo& info : *listed_b) EXPECT_NE(info.name, name);
  absl::StatusOr<std::vector<EnvInfo>> listed_a = a.ListEnvs();
  ASSERT_TRUE(listed_a.ok()) << listed_a.status();
  bool found = false;
  for (const EnvInfo& info : *listed_a) found |= info.name == name;
  EXPECT_TRUE(found);
  // Still A's and untouched.
  absl::StatusOr<StepData> step = env->Step(Actions::Discrete(action));
  ASSERT_TRUE(step.ok()) << step.status();
  EXPECT_EQ(step->cycles, 1);
}

TEST(TokenTest, TokenThatCannotTravelIsRejectedWithoutEchoingIt) {
  for (const std::string token : {"two words", "line\n", "caf\xc3\xa9"}) {
    absl::StatusOr<Client> client =
        Client::Create(SecureServers::secure_address(),
                       Options(&SecureServers::local(), token));
    EXPECT_EQ(client.status().code(), absl::StatusCode::kInvalidArgument);
    EXPECT_THAT(client.status().message(), HasSubstr("token has character"));
    EXPECT_THAT(client.status().message(), Not(HasSubstr(token)));
  }
}

// ------------------------------------------------------------------ mll_cli

std::string SecureFlag() {
  return "--address=" + SecureServers::secure_address();
}
std::string RootFlag() {
  return "--tls_root_cert=" + SecureServers::local().cert_file;
}

// MLL_TOKEN set for one scope (inherited by the commands run in it).
class ScopedTokenVariable {
 public:
  explicit ScopedTokenVariable(const std::string& value) {
    setenv("MLL_TOKEN", value.c_str(), 1);
  }
  ~ScopedTokenVariable() { unsetenv("MLL_TOKEN"); }
};

TEST(SecureCliTest, TlsRootCertAndTokenFlags) {
  const CommandResult health = RunCli({"health", SecureFlag(), RootFlag()});
  EXPECT_EQ(health.exit_code, 0) << health.err;
  const CommandResult play = RunCli({"play", SecureFlag(), RootFlag(),
                                     std::string("--token=") + kTokenA,
                                     "--n_landers=2", "--max_cycles=30"});
  EXPECT_EQ(play.exit_code, 0) << play.err;
  EXPECT_THAT(play.out, HasSubstr("\"summary\":true"));

  const CommandResult no_token = RunCli({"list", SecureFlag(), RootFlag()});
  EXPECT_EQ(no_token.exit_code, 1);
  EXPECT_THAT(no_token.err, HasSubstr("UNAUTHENTICATED"));
  const CommandResult plaintext =
      RunCli({"list", SecureFlag(), std::string("--token=") + kTokenA});
  EXPECT_EQ(plaintext.exit_code, 1);
  EXPECT_THAT(plaintext.err, HasSubstr("UNAVAILABLE"));
  const CommandResult untrusting =
      RunCli({"list", SecureFlag(), std::string("--token=") + kTokenA,
              "--tls_root_cert=" + SecureServers::stranger().cert_file});
  EXPECT_EQ(untrusting.exit_code, 1);
  const CommandResult renamed =
      RunCli({"health", "--address=" + SecureServers::renamed_address(),
              "--tls_root_cert=" + SecureServers::renamed().cert_file,
              "--tls_server_name=mll.test"});
  EXPECT_EQ(renamed.exit_code, 0) << renamed.err;
}

TEST(SecureCliTest, TokenFromFlagFileOrEnvironmentInThatOrder) {
  // A file with one token (and a comment).
  absl::StatusOr<std::string> file_b =
      WriteTempFile("mll_token_b", absl::StrCat("# B\n  ", kTokenB, "  \n"));
  ASSERT_TRUE(file_b.ok()) << file_b.status();
  const CommandResult created =
      RunCli({"create", SecureFlag(), RootFlag(), "--token_file=" + *file_b,
              "--n_landers=1"});
  ASSERT_EQ(created.exit_code, 0) << created.err;
  const std::string name = EnvNameIn(created.out);
  ASSERT_FALSE(name.empty()) << created.out;
  // B's env: found with B's token, from whichever source; not with A's.
  {
    ScopedTokenVariable variable(kTokenB);
    const CommandResult get = RunCli({"get", name, SecureFlag(), RootFlag()});
    EXPECT_EQ(get.exit_code, 0) << get.err;
    // --token beats MLL_TOKEN.
    const CommandResult as_a = RunCli({"get", name, SecureFlag(), RootFlag(),
                                       std::string("--token=") + kTokenA});
    EXPECT_EQ(as_a.exit_code, 1);
    EXPECT_THAT(as_a.err, HasSubstr("NOT_FOUND"));
  }
  {
    ScopedTokenVariable variable(kTokenA);
    // --token_file beats MLL_TOKEN.
    const CommandResult get = RunCli(
        {"get", name, SecureFlag(), RootFlag(), "--token_file=" + *file_b});
    EXPECT_EQ(get.exit_code, 0) << get.err;
    const CommandResult as_a = RunCli({"get", name, SecureFlag(), RootFlag()});
    EXPECT_EQ(as_a.exit_code, 1);
    EXPECT_THAT(as_a.err, HasSubstr("NOT_FOUND"));
  }
  const CommandResult deleted = RunCli(
      {"delete", name, SecureFlag(), RootFlag(), "--token_file=" + *file_b});
  EXPECT_EQ(deleted.exit_code, 0) << deleted.err;

  // Bad token sources are command-line errors that never print the token.
  const CommandResult both =
      RunCli({"list", SecureFlag(), RootFlag(),
              std::string("--token=") + kTokenA, "--token_file=" + *file_b});
  EXPECT_EQ(both.exit_code, 2);
  EXPECT_THAT(both.err, HasSubstr("both set"));
  absl::StatusOr<std::string> two = WriteTempFile(
      "mll_token_two", absl::StrCat(kTokenA, "\n", kTokenB, "\n"));
  ASSERT_TRUE(two.ok());
  const CommandResult many =
      RunCli({"list", SecureFlag(), RootFlag(), "--token_file=" + *two});
  EXPECT_EQ(many.exit_code, 2);
  EXPECT_THAT(many.err, HasSubstr("has 2 tokens"));
  EXPECT_THAT(many.err, Not(HasSubstr(kTokenA)));
  const CommandResult missing = RunCli(
      {"list", SecureFlag(), RootFlag(), "--token_file=/nonexistent/token"});
  EXPECT_EQ(missing.exit_code, 2);
  EXPECT_THAT(missing.err, HasSubstr("cannot be read"));
}

}  // namespace
}  // namespace mll::client

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  ::testing::AddGlobalTestEnvironment(new mll::client::SecureServers());
  return RUN_ALL_TESTS();
}
