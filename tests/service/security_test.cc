// TLS with a self-signed certificate made at test time (openssl CLI), and the
// mll_server binary with TLS, tokens and metrics together, over loopback.
#include <signal.h>
#include <unistd.h>

#include <chrono>
#include <cstdlib>
#include <fstream>
#include <sstream>
#include <string>
#include <thread>
#include <tuple>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "httplib.h"
#include "server_process.h"
#include "test_util.h"

namespace mll::service::testing {
namespace {

using ::testing::AllOf;
using ::testing::HasSubstr;
using ::testing::Not;

struct KeyPair {
  std::string cert_file;
  std::string key_file;
  std::string cert_pem;
};

std::string ReadAll(const std::string& path) {
  std::ifstream in(path);
  std::stringstream contents;
  contents << in.rdbuf();
  return contents.str();
}

// A fresh self-signed P-256 certificate for localhost and 127.0.0.1.
// The files are per process: ctest runs this file's tests as concurrent
// processes, which must not overwrite each other's certificate.
KeyPair MakeKeyPair(const std::string& stem) {
  const std::string prefix =
      ::testing::TempDir() + stem + "_" + std::to_string(getpid());
  KeyPair pair{prefix + "_cert.pem", prefix + "_key.pem", ""};
  const std::string command =
      "openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 "
      "-nodes -days 2 -subj /CN=localhost "
      "-addext subjectAltName=DNS:localhost,IP:127.0.0.1 -keyout " +
      pair.key_file + " -out " + pair.cert_file + " 2>/dev/null";
  EXPECT_EQ(std::system(command.c_str()), 0) << command;
  pair.cert_pem = ReadAll(pair.cert_file);
  EXPECT_THAT(pair.cert_pem, HasSubstr("-----BEGIN CERTIFICATE-----"));
  return pair;
}

std::shared_ptr<grpc::Channel> TlsChannel(const std::string& target,
                                          const std::string& root_pem) {
  grpc::SslCredentialsOptions ssl;
  ssl.pem_root_certs = root_pem;
  return grpc::CreateChannel(target, grpc::SslCredentials(ssl));
}

// CreateEnv over `channel` with a 5 s deadline; `token` if not empty.
grpc::Status TryCreate(const std::shared_ptr<grpc::Channel>& channel,
                       const std::string& token = "") {
  auto stub = v1::MultiLunarLander::NewStub(channel);
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() +
                       std::chrono::seconds(5));
  if (!token.empty()) AddToken(token, &context);
  v1::Env env;
  return stub->CreateEnv(&context, CreateRequest(1), &env);
}

class TlsTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    server_pair_ = new KeyPair(MakeKeyPair("mll_tls_server"));
    other_pair_ = new KeyPair(MakeKeyPair("mll_tls_other"));
  }
  static void TearDownTestSuite() {
    delete server_pair_;
    delete other_pair_;
  }

  static ServerOptions TlsOptions(const KeyPair& pair) {
    ServerOptions options;
    options.address = "127.0.0.1:0";
    options.tls_cert_file = pair.cert_file;
    options.tls_key_file = pair.key_file;
    return options;
  }

  static KeyPair* server_pair_;
  static KeyPair* other_pair_;
};

KeyPair* TlsTest::server_pair_ = nullptr;
KeyPair* TlsTest::other_pair_ = nullptr;

TEST_F(TlsTest, ClientTrustingTheCertificateConnects) {
  absl::StatusOr<std::unique_ptr<Server>> server =
      Server::Start(TlsOptions(*server_pair_));
  ASSERT_TRUE(server.ok()) << server.status();
  EXPECT_TRUE((*server)->tls());
  const std::string port = std::to_string((*server)->port());
  // The certificate names both: either works as the target.
  for (const std::string host : {"localhost", "127.0.0.1"}) {
    const grpc::Status status =
        TryCreate(TlsChannel(host + ":" + port, server_pair_->cert_pem));
    EXPECT_TRUE(status.ok()) << host << ": " << status.error_message();
  }
  EXPECT_EQ((*server)->service().registry().size(), 2);
}

TEST_F(TlsTest, PlaintextAndUntrustingClientsCannotConnect) {
  absl::StatusOr<std::unique_ptr<Server>> server =
      Server::Start(TlsOptions(*server_pair_));
  ASSERT_TRUE(server.ok()) << server.status();
  const std::string target = "127.0.0.1:" + std::to_string((*server)->port());
  EXPECT_EQ(
      TryCreate(grpc::CreateChannel(target, grpc::InsecureChannelCredentials()))
          .error_code(),
      grpc::StatusCode::UNAVAILABLE);
  // A client that trusts another certificate rejects the server's.
  EXPECT_EQ(TryCreate(TlsChannel(target, other_pair_->cert_pem)).error_code(),
            grpc::StatusCode::UNAVAILABLE);
  EXPECT_EQ((*server)->service().registry().size(), 0);
}

TEST_F(TlsTest, BadTlsOptionsAreInvalidArgumentNamingTheFlag) {
  ServerOptions options = TlsOptions(*server_pair_);
  options.tls_key_file = "";
  absl::StatusOr<std::unique_ptr<Server>> server = Server::Start(options);
  EXPECT_EQ(server.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(server.status().message(),
              HasSubstr("--tls_cert is set without --tls_key"));

  options = TlsOptions(*server_pair_);
  options.tls_cert_file = ::testing::TempDir() + "no_such_cert.pem";
  server = Server::Start(options);
  EXPECT_EQ(server.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(server.status().message(),
              HasSubstr("--tls_cert: cannot read " + options.tls_cert_file));

  options = TlsOptions(*server_pair_);
  options.tls_key_file = ::testing::TempDir() + "not_pem.txt";
  std::ofstream(options.tls_key_file) << "just text\n";
  server = Server::Start(options);
  EXPECT_EQ(server.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(server.status().message(),
              HasSubstr("--tls_key: " + options.tls_key_file + " is not PEM"));
}

// The line of `log` starting with `prefix`, polled for while the server
// starts (at most 20 s).
std::string WaitForLogLine(const std::string& log, const std::string& prefix) {
  const auto end = std::chrono::steady_clock::now() + std::chrono::seconds(20);
  while (std::chrono::steady_clock::now() < end) {
    std::istringstream lines(ReadAll(log));
    for (std::string line; std::getline(lines, line);) {
      if (line.rfind(prefix, 0) == 0) return line;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  return "";
}

TEST_F(TlsTest, BinaryWithTlsTokensAndMetrics) {
  const std::string tokens = ::testing::TempDir() + "mll_binary_tokens.txt";
  std::ofstream(tokens) << "# two trainers\nsecret-one\n\nsecret-two\n";
  const std::string log = ::testing::TempDir() + "mll_binary_security.log";
  ServerProcess process(
      {"--tls_cert=" + server_pair_->cert_file,
       "--tls_key=" + server_pair_->key_file, "--auth_token_file=" + tokens,
       "--metrics_address=127.0.0.1:0", "--threads=1"},
      log);
  const int port = process.WaitForPort();
  ASSERT_GT(port, 0);
  const std::string line = WaitForLogLine(log, "mll_server: TLS ");
  EXPECT_THAT(line, AllOf(HasSubstr("TLS on"),
                          HasSubstr("auth on (2 tokens from " + tokens + ")"),
                          HasSubstr("metrics on http://127.0.0.1:")));
  EXPECT_THAT(ReadAll(log), AllOf(Not(HasSubstr("secret-one")),
                                  Not(HasSubstr("secret-two"))));

  auto channel =
      TlsChannel("localhost:" + std::to_string(port), server_pair_->cert_pem);
  EXPECT_TRUE(TryCreate(channel, "secret-two").ok());
  const grpc::Status no_token = TryCreate(channel);
  EXPECT_EQ(no_token.error_code(), grpc::StatusCode::UNAUTHENTICATED);
  EXPECT_THAT(no_token.error_message(),
              HasSubstr("authorization: Bearer <token>"));
  grpc::Status health;
  EXPECT_EQ(HealthCheck(channel, &health), std::string("\x08\x01", 2))
      << "probes need no token";

  // The metrics endpoint from the log line: plain HTTP on loopback.
  const size_t at = line.find("http://127.0.0.1:");
  ASSERT_NE(at, std::string::npos);
  const int metrics_port =
      std::atoi(line.c_str() + at + std::string("http://127.0.0.1:").size());
  httplib::Client http("127.0.0.1", metrics_port);
  http.set_connection_timeout(5);
  http.set_read_timeout(5);
  httplib::Result scrape = http.Get("/metrics");
  ASSERT_TRUE(scrape) << httplib::to_string(scrape.error());
  EXPECT_EQ(scrape->status, 200);
  EXPECT_THAT(scrape->body,
              AllOf(HasSubstr("\nmll_envs_live 1\n"),
                    HasSubstr("mll_rpc_errors_total{method=\"CreateEnv\","
                              "code=\"UNAUTHENTICATED\"} 1\n")));

  channel.reset();
  EXPECT_EQ(process.SignalAndWait(SIGTERM), 0);
}

TEST(SecurityFlagsTest, BinaryRejectsBadSecurityFlags) {
  auto [code, output] =
      RunServer("--address=127.0.0.1:0 --tls_cert=/nonexistent.pem");
  EXPECT_EQ(code, 1);
  EXPECT_THAT(output, HasSubstr("--tls_cert is set without --tls_key"));
  std::tie(code, output) = RunServer(
      "--address=127.0.0.1:0 --auth_token_file=/nonexistent_tokens.txt");
  EXPECT_EQ(code, 1);
  EXPECT_THAT(output,
              HasSubstr("--auth_token_file: cannot read /nonexistent_tokens"));
  std::tie(code, output) =
      RunServer("--address=127.0.0.1:0 --metrics_address=nowhere");
  EXPECT_EQ(code, 1);
  EXPECT_THAT(output, HasSubstr("--metrics_address: \"nowhere\" is not "
                                "host:port"));
}

}  // namespace
}  // namespace mll::service::testing
