// Client::GetServerInfo and the compatibility check: against the real
// mll_server, against fake servers (one from before GetServerInfo, one of a
// newer protocol), with synthetic ServerInfo values; and `mll_cli info`.
#include <atomic>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "cli_runner.h"
#include "gmock/gmock.h"
#include "grpcpp/grpcpp.h"
#include "gtest/gtest.h"
#include "mll/client.h"
#include "mll/v1/multi_lunar_lander.grpc.pb.h"
#include "server_process.h"

namespace mll::client {
namespace {

using ::testing::AllOf;
using ::testing::HasSubstr;
using ::testing::SizeIs;
using ::testing::StartsWith;

// A server of mll.v1 that answers GetServerInfo with `info` (UNIMPLEMENTED
// when unset, as a release from before GetServerInfo does) and CreateEnv
// with a made-up env; every other method is UNIMPLEMENTED.
class FakeService final : public v1::MultiLunarLander::CallbackService {
 public:
  explicit FakeService(std::optional<v1::ServerInfo> info)
      : info_(std::move(info)) {}

  grpc::ServerUnaryReactor* GetServerInfo(
      grpc::CallbackServerContext* context,
      const v1::GetServerInfoRequest* request,
      v1::ServerInfo* response) override {
    ++info_calls;
    if (!info_.has_value()) {
      return v1::MultiLunarLander::CallbackService::GetServerInfo(
          context, request, response);
    }
    *response = *info_;
    grpc::ServerUnaryReactor* reactor = context->DefaultReactor();
    reactor->Finish(grpc::Status::OK);
    return reactor;
  }

  grpc::ServerUnaryReactor* CreateEnv(grpc::CallbackServerContext* context,
                                      const v1::CreateEnvRequest* /*request*/,
                                      v1::Env* response) override {
    ++create_calls;
    response->set_name("envs/fake");
    grpc::ServerUnaryReactor* reactor = context->DefaultReactor();
    reactor->Finish(grpc::Status::OK);
    return reactor;
  }

  std::atomic<int> info_calls{0};
  std::atomic<int> create_calls{0};

 private:
  const std::optional<v1::ServerInfo> info_;
};

class FakeServer {
 public:
  explicit FakeServer(std::optional<v1::ServerInfo> info) : service_(info) {
    grpc::ServerBuilder builder;
    builder.AddListeningPort("127.0.0.1:0", grpc::InsecureServerCredentials(),
                             &port_);
    builder.RegisterService(&service_);
    server_ = builder.BuildAndStart();
  }
  ~FakeServer() { server_->Shutdown(); }
  std::string address() const { return absl::StrCat("127.0.0.1:", port_); }
  FakeService& service() { return service_; }

 private:
  FakeService service_;
  int port_ = 0;
  std::unique_ptr<grpc::Server> server_;
};

class ServerInfoTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    absl::StatusOr<std::unique_ptr<ServerProcess>> server =
        ServerProcess::Start(MLL_SERVER_PATH, {"--threads=2", "--max_envs=50",
                                               "--idle_timeout_s=77"});
    ASSERT_TRUE(server.ok()) << server.status();
    server_ = server->release();
  }
  static void TearDownTestSuite() {
    delete server_;
    server_ = nullptr;
  }

  static Client Connect(const std::string& address) {
    absl::StatusOr<Client> client = Client::Create(address);
    EXPECT_TRUE(client.ok()) << client.status();
    return *std::move(client);
  }

  static inline ServerProcess* server_ = nullptr;
};

ServerInfo Synthetic(int major, int minor,
                     std::vector<std::string> capabilities = {}) {
  ServerInfo info;
  info.server_version = "9.8.7";
  info.protocol_major = major;
  info.protocol_minor = minor;
  info.capabilities = std::move(capabilities);
  return info;
}

TEST_F(ServerInfoTest, RealServerReportsItsReleaseProtocolAndLimits) {
  const Client client = Connect(server_->address());
  absl::StatusOr<ServerInfo> info = client.GetServerInfo();
  ASSERT_TRUE(info.ok()) << info.status();
  // Client and server are built from the same project version.
  EXPECT_EQ(info->server_version, Client::Version());
  EXPECT_EQ(info->protocol_major, Client::kProtocolMajor);
  EXPECT_EQ(info->protocol_minor, Client::kProtocolMinor);
  EXPECT_TRUE(info->has_capability("packed_step_batch"));
  EXPECT_TRUE(info->has_capability("keep_alive"));
  EXPECT_TRUE(info->has_capability("shared_memory_sessions"));
  EXPECT_FALSE(info->has_capability("no_such_thing"));
  EXPECT_EQ(info->threads, 2);
  EXPECT_EQ(info->max_envs, 50);
  EXPECT_EQ(info->idle_timeout_s, 77);
  EXPECT_EQ(info->max_landers, 32);
  EXPECT_EQ(info->max_message_bytes, int64_t{64} << 20);
  EXPECT_THAT(info->json,
              AllOf(StartsWith("{"), HasSubstr("\"protocol_major\":1"),
                    HasSubstr(absl::StrCat("\"server_version\":\"",
                                           Client::Version(), "\""))));
  EXPECT_TRUE(Client::CheckCompatible(*info, server_->address(),
                                      {"packed_step_batch", "auto_reset"})
                  .ok());

  absl::StatusOr<ServerInfo> out_of_range = client.GetServerInfo(1);
  EXPECT_EQ(out_of_range.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(out_of_range.status().message(),
              HasSubstr("server is 1; allowed: 0..0"));
}

TEST(ServerInfoCheckTest, RefusesAnotherProtocolMajorNamingBothVersions) {
  absl::Status newer = Client::CheckCompatible(Synthetic(2, 3), "host:1");
  EXPECT_EQ(newer.code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(newer.message(),
              AllOf(HasSubstr("mll_server 9.8.7 at host:1 (protocol v2.3)"),
                    HasSubstr(absl::StrCat("mll::client ", Client::Version(),
                                           ", protocol v1.")),
                    HasSubstr("upgrade the client to a release of protocol "
                              "v2")));
  absl::Status older = Client::CheckCompatible(Synthetic(0, 4), "host:1");
  EXPECT_EQ(older.code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(older.message(),
              AllOf(HasSubstr("(protocol v0.4)"),
                    HasSubstr("upgrade the server to a release of protocol "
                              "v1")));
}

TEST(ServerInfoCheckTest, RefusesAMissingCapabilityUnlessTheServerIsV1_0) {
  absl::Status missing =
      Client::CheckCompatible(Synthetic(1, 1, {"keep_alive"}), "host:1",
                              {"keep_alive", "packed_step_batch"});
  EXPECT_EQ(missing.code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(
      missing.message(),
      AllOf(HasSubstr("lacks capability \"packed_step_batch\""),
            HasSubstr("(protocol v1.1)"), HasSubstr("upgrade the server")));
  // A newer minor with more capabilities is fine.
  EXPECT_TRUE(Client::CheckCompatible(
                  Synthetic(1, 7, {"packed_step_batch", "future_thing"}),
                  "host:1", {"packed_step_batch"})
                  .ok());
  // A 1.0 server (before GetServerInfo) lists nothing: not refused.
  EXPECT_TRUE(
      Client::CheckCompatible(Synthetic(1, 0), "host:1", {"packed_step_batch"})
          .ok());
}

TEST_F(ServerInfoTest, ServerWithoutGetServerInfoIsProtocol1_0AndUsable) {
  FakeServer old(std::nullopt);
  const Client client = Connect(old.address());
  absl::StatusOr<ServerInfo> info = client.GetServerInfo();
  ASSERT_TRUE(info.ok()) << info.status();
  EXPECT_EQ(info->server_version, "");
  EXPECT_EQ(info->protocol_major, 1);
  EXPECT_EQ(info->protocol_minor, 0);
  EXPECT_TRUE(info->capabilities.empty());
  absl::StatusOr<RemoteEnv> env = client.CreateEnv();
  ASSERT_TRUE(env.ok()) << env.status();
  EXPECT_EQ(env->name(), "envs/fake");
  // Asked once per connection, UNIMPLEMENTED included.
  EXPECT_EQ(old.service().info_calls.load(), 1);
}

TEST_F(ServerInfoTest, CreateEnvRefusesANewerProtocolBeforeCreating) {
  v1::ServerInfo v2;
  v2.set_server_version("2.0.0");
  v2.set_protocol_major(2);
  v2.set_protocol_minor(0);
  FakeServer newer(v2);
  const Client client = Connect(newer.address());
  for (int attempt = 0; attempt < 2; ++attempt) {
    absl::StatusOr<RemoteEnv> env = client.CreateEnv();
    EXPECT_EQ(env.status().code(), absl::StatusCode::kFailedPrecondition);
    EXPECT_THAT(env.status().message(),
                AllOf(HasSubstr("mll_server 2.0.0 at " + newer.address() +
                                " (protocol v2.0)"),
                      HasSubstr("upgrade the client")));
  }
  EXPECT_EQ(newer.service().create_calls.load(), 0);
  EXPECT_EQ(newer.service().info_calls.load(), 1);
}

TEST_F(ServerInfoTest, CliInfoPrintsOneJsonLinePerServer) {
  FakeServer old(std::nullopt);
  const CommandResult result =
      RunCli({"info", absl::StrCat("--address=", server_->address(), ",",
                                   old.address())});
  ASSERT_EQ(result.exit_code, 0) << result.err;
  const std::vector<std::string> lines =
      absl::StrSplit(result.out, '\n', absl::SkipEmpty());
  ASSERT_THAT(lines, SizeIs(2)) << result.out;
  EXPECT_THAT(lines[0],
              AllOf(StartsWith(absl::StrCat(
                        "{\"address\":\"", server_->address(),
                        "\",\"server_version\":\"", Client::Version(), "\"")),
                    HasSubstr("\"protocol_major\":1"),
                    HasSubstr("\"capabilities\":[\"packed_step_batch\""),
                    HasSubstr("\"max_envs\":50"), HasSubstr("\"threads\":2")));
  EXPECT_THAT(
      lines[1],
      AllOf(StartsWith(absl::StrCat("{\"address\":\"", old.address(), "\"")),
            HasSubstr("\"protocol_major\":1"),
            HasSubstr("\"protocol_minor\":0")));
  // An unknown command's message lists `info` among the commands.
  const CommandResult unknown = RunCli({"no_such_command"});
  EXPECT_EQ(unknown.exit_code, 2);
  EXPECT_THAT(unknown.err, HasSubstr("info"));
}

}  // namespace
}  // namespace mll::client
