// A server shared by tenants: the per-token quota (--max_envs_per_token) and
// its default, live envs per tenant in the metrics without the tokens, leases
// renewed by KeepAlive, and a NOT_FOUND that says when the idle timeout
// reclaimed an env. Waits are bounded polls.
#include <chrono>
#include <string>
#include <thread>
#include <vector>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "test_util.h"

namespace mll::service::testing {
namespace {

using ::testing::AllOf;
using ::testing::ElementsAre;
using ::testing::HasSubstr;
using ::testing::Not;

constexpr char kAlpha[] = "alpha-5d1e";
constexpr char kBeta[] = "beta-0a9c";
constexpr char kGamma[] = "gamma-77b2";

grpc::Status CreateAs(v1::MultiLunarLander::Stub& stub,
                      const std::string& token, std::string* name = nullptr) {
  grpc::ClientContext context;
  if (!token.empty()) AddToken(token, &context);
  v1::Env env;
  const grpc::Status status = stub.CreateEnv(&context, CreateRequest(1), &env);
  if (name != nullptr) *name = env.name();
  return status;
}

grpc::Status GetAs(v1::MultiLunarLander::Stub& stub, const std::string& token,
                   const std::string& name) {
  grpc::ClientContext context;
  if (!token.empty()) AddToken(token, &context);
  v1::GetEnvRequest request;
  request.set_name(name);
  v1::Env env;
  return stub.GetEnv(&context, request, &env);
}

v1::KeepAliveResponse KeepAliveAs(v1::MultiLunarLander::Stub& stub,
                                  const std::string& token,
                                  const std::vector<std::string>& names,
                                  grpc::Status* status = nullptr) {
  grpc::ClientContext context;
  if (!token.empty()) AddToken(token, &context);
  v1::KeepAliveRequest request;
  for (const std::string& name : names) request.add_names(name);
  v1::KeepAliveResponse response;
  const grpc::Status result = stub.KeepAlive(&context, request, &response);
  if (status != nullptr) *status = result;
  EXPECT_TRUE(status != nullptr || result.ok()) << result.error_message();
  return response;
}

ServiceOptions ThreeTenants(int max_envs) {
  ServiceOptions options;
  options.max_envs = max_envs;
  options.auth_tokens = {kAlpha, kBeta, kGamma};
  return options;
}

TEST(TenancyTest, DefaultQuotaIsAFairShareWithTokensAndUnlimitedWithout) {
  EXPECT_EQ(EffectiveMaxEnvsPerToken(ThreeTenants(10)), 3);  // 10 / 3.
  EXPECT_EQ(EffectiveMaxEnvsPerToken(ThreeTenants(2)), 1);   // At least one.
  ServiceOptions anonymous;
  EXPECT_EQ(EffectiveMaxEnvsPerToken(anonymous), 0);  // Unlimited.
  ServiceOptions set = ThreeTenants(10);
  set.max_envs_per_token = 7;
  EXPECT_EQ(EffectiveMaxEnvsPerToken(set), 7);
  ServerOptions negative;
  negative.service.max_envs_per_token = -1;
  EXPECT_THAT(ValidateServerOptions(negative).message(),
              HasSubstr("--max_envs_per_token: -1 is out of range"));
}

TEST(TenancyTest, OneTenantCannotTakeEveryEnvironment) {
  InProcess s(ThreeTenants(10));
  std::vector<std::string> alphas(3);
  for (std::string& name : alphas) {
    ASSERT_TRUE(CreateAs(*s.stub, kAlpha, &name).ok());
  }
  const grpc::Status refused = CreateAs(*s.stub, kAlpha);
  EXPECT_EQ(refused.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED);
  EXPECT_THAT(
      refused.error_message(),
      AllOf(HasSubstr("tenant token#1"), HasSubstr("--max_envs_per_token=3"),
            HasSubstr("the server hosts 3 of --max_envs=10"),
            Not(HasSubstr(kAlpha))));
  // The other tenants still get their shares.
  for (int i = 0; i < 3; ++i) {
    EXPECT_TRUE(CreateAs(*s.stub, kBeta).ok());
    EXPECT_TRUE(CreateAs(*s.stub, kGamma).ok());
  }
  EXPECT_EQ(CreateAs(*s.stub, kBeta).error_code(),
            grpc::StatusCode::RESOURCE_EXHAUSTED);
  // Deleting one of alpha's envs gives alpha its slot back.
  grpc::ClientContext context;
  AddToken(kAlpha, &context);
  v1::DeleteEnvRequest remove;
  remove.set_name(alphas[0]);
  v1::DeleteEnvResponse removed;
  ASSERT_TRUE(s.stub->DeleteEnv(&context, remove, &removed).ok());
  EXPECT_TRUE(CreateAs(*s.stub, kAlpha).ok());
}

TEST(TenancyTest, ExplicitQuotaAppliesToTheAnonymousTenantToo) {
  ServiceOptions options;
  options.max_envs = 10;
  options.max_envs_per_token = 2;
  InProcess s(options);
  ASSERT_TRUE(CreateAs(*s.stub, "").ok());
  ASSERT_TRUE(CreateAs(*s.stub, "").ok());
  const grpc::Status refused = CreateAs(*s.stub, "");
  EXPECT_EQ(refused.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED);
  EXPECT_THAT(
      refused.error_message(),
      AllOf(HasSubstr("tenant anonymous"), HasSubstr("--max_envs_per_token=2"),
            HasSubstr("--max_envs=10")));
}

TEST(TenancyTest, MetricsCountLiveEnvsPerTenantWithoutTokens) {
  InProcess s(ThreeTenants(10));
  ASSERT_TRUE(CreateAs(*s.stub, kAlpha).ok());
  ASSERT_TRUE(CreateAs(*s.stub, kAlpha).ok());
  ASSERT_TRUE(CreateAs(*s.stub, kGamma).ok());
  const std::string text = s.server->service().MetricsText();
  EXPECT_THAT(text, AllOf(HasSubstr("mll_tenant_envs_live{tenant=\"token#1\"} "
                                    "2\n"),
                          HasSubstr("mll_tenant_envs_live{tenant=\"token#3\"} "
                                    "1\n"),
                          Not(HasSubstr("tenant=\"token#2\"")),
                          Not(HasSubstr(kAlpha)), Not(HasSubstr(kGamma))));
}

TEST(TenancyTest, KeepAliveRenewsLeasesAndReportsUnknownNames) {
  ServiceOptions options = ThreeTenants(10);
  options.idle_timeout = absl::Milliseconds(600);
  InProcess s(options);
  std::string kept, idle, theirs;
  ASSERT_TRUE(CreateAs(*s.stub, kAlpha, &kept).ok());
  ASSERT_TRUE(CreateAs(*s.stub, kAlpha, &idle).ok());
  ASSERT_TRUE(CreateAs(*s.stub, kBeta, &theirs).ok());
  // Only KeepAlive touches `kept`, every 150 ms for 3 timeouts.
  const auto start = std::chrono::steady_clock::now();
  v1::KeepAliveResponse response;
  while (std::chrono::steady_clock::now() - start <
         std::chrono::milliseconds(1800)) {
    response = KeepAliveAs(*s.stub, kAlpha,
                           {kept, theirs, "envs/unknown", "not-a-name"});
    std::this_thread::sleep_for(std::chrono::milliseconds(150));
  }
  // Another tenant's env is as unknown as a made-up name.
  EXPECT_THAT(response.not_found(),
              ElementsAre(theirs, "envs/unknown", "not-a-name"));
  EXPECT_DOUBLE_EQ(response.idle_timeout_s(), 0.6);
  EXPECT_TRUE(GetAs(*s.stub, kAlpha, kept).ok());
  // `idle` was reclaimed; NOT_FOUND says so and what to do.
  const grpc::Status gone = GetAs(*s.stub, kAlpha, idle);
  EXPECT_EQ(gone.error_code(), grpc::StatusCode::NOT_FOUND);
  EXPECT_THAT(
      gone.error_message(),
      AllOf(HasSubstr(idle), HasSubstr("reclaimed after being idle 0.6 s"),
            HasSubstr("keep the client's env object alive"),
            HasSubstr("raise the server's --idle_timeout_s")));
  // To another tenant the reclaimed name is just unknown.
  const grpc::Status elsewhere = GetAs(*s.stub, kBeta, idle);
  EXPECT_EQ(elsewhere.error_code(), grpc::StatusCode::NOT_FOUND);
  EXPECT_THAT(
      elsewhere.error_message(),
      AllOf(HasSubstr("does not exist"), Not(HasSubstr("was reclaimed"))));
}

TEST(TenancyTest, EnvReportsTheIdleTimeoutAndKeepAliveIsBounded) {
  ServiceOptions options;
  options.idle_timeout = absl::Seconds(42);
  InProcess s(options);
  grpc::ClientContext context;
  v1::Env env;
  ASSERT_TRUE(s.stub->CreateEnv(&context, CreateRequest(1), &env).ok());
  EXPECT_DOUBLE_EQ(env.idle_timeout_s(), 42);
  grpc::Status status;
  KeepAliveAs(*s.stub, "", std::vector<std::string>(10001, env.name()),
              &status);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_THAT(status.error_message(),
              HasSubstr("names: 10001 names (allowed: at most 10000"));
  KeepAliveAs(*s.stub, "", std::vector<std::string>(10000, env.name()),
              &status);
  EXPECT_TRUE(status.ok()) << status.error_message();
}

}  // namespace
}  // namespace mll::service::testing
