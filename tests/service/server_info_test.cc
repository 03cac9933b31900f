// GetServerInfo: the release, protocol version, capabilities and limits a
// server reports, from its options (in-process) and from mll_server's flags
// (the binary over loopback); the token it needs; its metrics label.
#include "mll/service/server_info.h"

#include <string>

#include "absl/strings/str_cat.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "mll/service/load_meter.h"
#include "server_process.h"
#include "test_util.h"

namespace mll::service::testing {
namespace {

using ::testing::ElementsAre;
using ::testing::HasSubstr;
using ::testing::MatchesRegex;
using ::testing::Not;

grpc::Status GetServerInfo(v1::MultiLunarLander::Stub& stub,
                           v1::ServerInfo* info,
                           const std::string& token = "") {
  grpc::ClientContext context;
  if (!token.empty()) AddToken(token, &context);
  return stub.GetServerInfo(&context, v1::GetServerInfoRequest(), info);
}

TEST(ServerInfoTest, ReportsVersionsCapabilitiesAndTheOptions) {
  ServiceOptions options;
  options.threads = 3;
  options.max_envs = 7;
  options.idle_timeout = absl::Seconds(42.5);
  options.shared_memory_sessions = 5;
  InProcess s(options, /*max_message_mb=*/5);
  v1::ServerInfo info;
  ASSERT_TRUE(GetServerInfo(*s.stub, &info).ok());
  EXPECT_EQ(info.server_version(), ServerVersion());
  EXPECT_THAT(info.server_version(), MatchesRegex("[0-9]+\\.[0-9]+\\.[0-9]+"));
  EXPECT_EQ(info.protocol_major(), 1);
  EXPECT_EQ(info.protocol_minor(), kProtocolMinor);
  EXPECT_GE(info.protocol_minor(), 1);
  EXPECT_THAT(info.capabilities(),
              ElementsAre("packed_step_batch", "auto_reset", "keep_alive",
                          "packed_batch_handles", "server_load",
                          "shared_memory_sessions"));
  const v1::ServerLimits& limits = info.limits();
  EXPECT_EQ(limits.max_envs(), 7);
  EXPECT_EQ(limits.max_envs_per_token(), 0);  // No tokens: unlimited.
  EXPECT_EQ(limits.max_message_bytes(), 5 << 20);
  EXPECT_EQ(limits.idle_timeout_s(), 42.5);
  EXPECT_EQ(limits.max_landers(), 32);
  EXPECT_EQ(limits.threads(), 3);
  EXPECT_EQ(limits.shared_memory_sessions(), 5);
}

TEST(ServerInfoTest, NoSharedMemoryCapabilityWhenTurnedOff) {
  ServiceOptions options;
  options.shared_memory_sessions = 0;
  InProcess s(options);
  v1::ServerInfo info;
  ASSERT_TRUE(GetServerInfo(*s.stub, &info).ok());
  EXPECT_THAT(info.capabilities(),
              Not(::testing::Contains("shared_memory_sessions")));
  EXPECT_THAT(info.capabilities(), ::testing::Contains("packed_step_batch"));
  EXPECT_EQ(info.limits().shared_memory_sessions(), 0);
}

// Like every call of the service (only health checks and reflection go
// without a token): the server's release and limits are for its tenants.
TEST(ServerInfoTest, NeedsTheTokenOfAServerWithTokens) {
  ServiceOptions options;
  options.max_envs = 10;
  options.auth_tokens = {"alpha-7f3c", "beta-19d2"};
  InProcess s(options);
  v1::ServerInfo info;
  for (const std::string& token : {std::string(), std::string("wrong")}) {
    const grpc::Status status = GetServerInfo(*s.stub, &info, token);
    EXPECT_EQ(status.error_code(), grpc::StatusCode::UNAUTHENTICATED) << token;
    EXPECT_THAT(status.error_message(),
                HasSubstr("authorization: Bearer <token>"));
  }
  ASSERT_TRUE(GetServerInfo(*s.stub, &info, "beta-19d2").ok());
  EXPECT_EQ(info.protocol_major(), 1);
  EXPECT_EQ(info.limits().max_envs_per_token(), 5);  // 10 / 2 tokens.
}

TEST(ServerInfoTest, CountedUnderItsOwnMethodLabel) {
  InProcess s;
  v1::ServerInfo info;
  ASSERT_TRUE(GetServerInfo(*s.stub, &info).ok());
  ASSERT_TRUE(GetServerInfo(*s.stub, &info).ok());
  EXPECT_THAT(
      s.server->service().MetricsText(),
      HasSubstr(
          "mll_rpc_duration_seconds_count{method=\"GetServerInfo\"} 2\n"));
}

// ServerInfo.load: the envs hosted follow creates and deletes (all owners
// together); CPU and agent-steps/s rise under a bounded step load, the CPU
// within [0, cores_available].
TEST(ServerInfoTest, LoadFollowsTheEnvsAndTheWork) {
  ServiceOptions options;
  options.max_envs = 8;
  InProcess s(options);
  v1::ServerInfo info;
  ASSERT_TRUE(GetServerInfo(*s.stub, &info).ok());
  EXPECT_EQ(info.load().envs_hosted(), 0);
  const double cores = info.load().cores_available();
  EXPECT_GT(cores, 0);
  EXPECT_EQ(cores, CoresAvailable());
  EXPECT_GE(info.load().cpu_cores(), 0);
  EXPECT_LE(info.load().cpu_cores(), cores);

  std::vector<std::string> names;
  for (int i = 0; i < 3; ++i) {
    names.push_back(CreateEnv(*s.stub, CreateRequest(/*n_landers=*/1)));
  }
  ASSERT_TRUE(GetServerInfo(*s.stub, &info).ok());
  EXPECT_EQ(info.load().envs_hosted(), 3);
  {
    grpc::ClientContext context;
    v1::DeleteEnvRequest request;
    request.set_name(names.back());
    v1::DeleteEnvResponse response;
    ASSERT_TRUE(s.stub->DeleteEnv(&context, request, &response).ok());
    names.pop_back();
  }
  ASSERT_TRUE(GetServerInfo(*s.stub, &info).ok());
  EXPECT_EQ(info.load().envs_hosted(), 2);

  // Steps for 1.5 s or 20,000 steps, whichever ends first; an env whose
  // lander is done is reset.
  const absl::Time end = absl::Now() + absl::Seconds(1.5);
  int64_t agent_steps = 0;
  std::vector<bool> done(names.size(), true);
  for (int step = 0; step < 20'000 && absl::Now() < end; ++step) {
    const size_t e = step % names.size();
    if (done[e]) {
      grpc::ClientContext context;
      v1::ResetEnvRequest reset;
      reset.set_name(names[e]);
      reset.set_seed(step);
      v1::ResetEnvResponse reset_response;
      ASSERT_TRUE(s.stub->ResetEnv(&context, reset, &reset_response).ok());
    }
    v1::StepEnvRequest request;
    request.set_name(names[e]);
    *request.mutable_actions() = DiscreteActions({2});
    grpc::ClientContext context;
    v1::StepEnvResponse response;
    const grpc::Status status = s.stub->StepEnv(&context, request, &response);
    ASSERT_TRUE(status.ok()) << status.error_message();
    const v1::StepData& data = response.data();
    agent_steps += data.stepped().data() == std::string(1, '\1');
    done[e] = data.terminations().data() != std::string(1, '\0') ||
              data.truncations().data() != std::string(1, '\0');
  }
  ASSERT_GT(agent_steps, 0);
  ASSERT_TRUE(GetServerInfo(*s.stub, &info).ok());
  EXPECT_GT(info.load().cpu_cores(), 0);
  EXPECT_LE(info.load().cpu_cores(), cores);
  EXPECT_GT(info.load().agent_steps_per_s(), 0);
  EXPECT_EQ(info.load().envs_hosted(), 2);
}

// The binary's flags reach the answer (Server::Start sets the message size).
TEST(ServerInfoTest, MllServerReportsItsFlags) {
  ServerProcess process({"--threads=2", "--max_envs=11", "--max_message_mb=3",
                         "--idle_timeout_s=9", "--shared_memory_sessions=0"});
  const int port = process.WaitForPort();
  ASSERT_NE(port, 0);
  auto stub = v1::MultiLunarLander::NewStub(grpc::CreateChannel(
      absl::StrCat("127.0.0.1:", port), grpc::InsecureChannelCredentials()));
  v1::ServerInfo info;
  const grpc::Status status = GetServerInfo(*stub, &info);
  ASSERT_TRUE(status.ok()) << status.error_message();
  EXPECT_EQ(info.server_version(), ServerVersion());
  EXPECT_THAT(info.capabilities(),
              ElementsAre("packed_step_batch", "auto_reset", "keep_alive",
                          "packed_batch_handles", "server_load"));
  EXPECT_EQ(info.limits().threads(), 2);
  EXPECT_EQ(info.limits().max_envs(), 11);
  EXPECT_EQ(info.limits().max_message_bytes(), 3 << 20);
  EXPECT_EQ(info.limits().idle_timeout_s(), 9);
  EXPECT_EQ(info.limits().shared_memory_sessions(), 0);
}

}  // namespace
}  // namespace mll::service::testing
