// Every method of mll.v1.MultiLunarLander and every error code of the
// table in docs/server.md, through an in-process channel to a real server.
#include <cmath>
#include <limits>
#include <set>
#include <string>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "mll/service/convert.h"
#include "test_util.h"

namespace mll::service::testing {
namespace {

using ::testing::HasSubstr;

#define EXPECT_STATUS(status, code, substring)                  \
  do {                                                          \
    const grpc::Status status_ = (status);                      \
    EXPECT_EQ(status_.error_code(), grpc::StatusCode::code)     \
        << status_.error_message();                             \
    EXPECT_THAT(status_.error_message(), HasSubstr(substring)); \
  } while (0)

class ServiceTest : public ::testing::Test {
 protected:
  grpc::Status Reset(const std::string& name, std::optional<uint64_t> seed,
                     v1::ResetEnvResponse* out) {
    grpc::ClientContext context;
    v1::ResetEnvRequest request;
    request.set_name(name);
    if (seed.has_value()) request.set_seed(*seed);
    return s_.stub->ResetEnv(&context, request, out);
  }
  grpc::Status Step(const std::string& name, const v1::Array& actions,
                    v1::StepEnvResponse* out) {
    grpc::ClientContext context;
    v1::StepEnvRequest request;
    request.set_name(name);
    *request.mutable_actions() = actions;
    return s_.stub->StepEnv(&context, request, out);
  }
  grpc::Status Agent(const std::string& name, std::optional<int32_t> discrete,
                     v1::StepAgentResponse* out,
                     std::optional<int32_t> agent = std::nullopt) {
    grpc::ClientContext context;
    v1::StepAgentRequest request;
    request.set_name(name);
    if (discrete.has_value()) request.mutable_action()->set_discrete(*discrete);
    if (agent.has_value()) request.set_agent(*agent);
    return s_.stub->StepAgent(&context, request, out);
  }
  grpc::Status Get(const std::string& name, v1::Env* out) {
    grpc::ClientContext context;
    v1::GetEnvRequest request;
    request.set_name(name);
    return s_.stub->GetEnv(&context, request, out);
  }
  grpc::Status Delete(const std::string& name) {
    grpc::ClientContext context;
    v1::DeleteEnvRequest request;
    request.set_name(name);
    v1::DeleteEnvResponse response;
    return s_.stub->DeleteEnv(&context, request, &response);
  }
  grpc::Status Render(const std::string& name, v1::FrameFormat format,
                      v1::Frame* out) {
    grpc::ClientContext context;
    v1::RenderEnvRequest request;
    request.set_name(name);
    request.set_format(format);
    return s_.stub->RenderEnv(&context, request, out);
  }

  InProcess s_;
};

TEST_F(ServiceTest, CreateEnvFillsDefaultsAndSpaces) {
  grpc::ClientContext context;
  v1::Env env;
  ASSERT_TRUE(s_.stub->CreateEnv(&context, v1::CreateEnvRequest(), &env).ok());
  EXPECT_THAT(env.name(), ::testing::MatchesRegex("envs/[0-9a-f]{32}"));
  EXPECT_EQ(env.config().n_landers(), 3);
  EXPECT_EQ(env.config().max_cycles(), 500);
  EXPECT_EQ(env.config().gravity(), -10.0);
  EXPECT_TRUE(env.config().has_continuous());
  EXPECT_FALSE(env.config().continuous());
  EXPECT_EQ(env.config().render_mode(), v1::RENDER_MODE_NONE);
  EXPECT_THAT(env.possible_agents(),
              ::testing::ElementsAre("lander_0", "lander_1", "lander_2"));
  EXPECT_EQ(env.observation_space().kind(), v1::Space::KIND_BOX);
  EXPECT_THAT(env.observation_space().shape(), ::testing::ElementsAre(12));
  EXPECT_EQ(env.action_space().kind(), v1::Space::KIND_DISCRETE);
  EXPECT_EQ(env.action_space().n(), 4);
  EXPECT_EQ(env.render_fps(), 50);
  EXPECT_FALSE(env.episode_started());
  EXPECT_FALSE(env.session_bound());

  v1::CreateEnvRequest continuous = CreateRequest(2);
  continuous.mutable_config()->set_continuous(true);
  grpc::ClientContext context2;
  ASSERT_TRUE(s_.stub->CreateEnv(&context2, continuous, &env).ok());
  EXPECT_EQ(env.action_space().kind(), v1::Space::KIND_BOX);
  EXPECT_THAT(env.action_space().low(), ::testing::ElementsAre(-1, -1));
}

TEST_F(ServiceTest, NamesAreDistinct) {
  std::set<std::string> names;
  for (int i = 0; i < 20; ++i) names.insert(CreateEnv(*s_.stub, {}));
  EXPECT_EQ(names.size(), 20u);
}

TEST_F(ServiceTest, CreateEnvRejectsBadConfig) {
  v1::Env env;
  {
    grpc::ClientContext context;
    EXPECT_STATUS(s_.stub->CreateEnv(&context, CreateRequest(40), &env),
                  INVALID_ARGUMENT, "n_landers");
  }
  {
    v1::CreateEnvRequest request;
    request.mutable_config()->set_gravity(std::nan(""));
    grpc::ClientContext context;
    EXPECT_STATUS(s_.stub->CreateEnv(&context, request, &env), INVALID_ARGUMENT,
                  "gravity");
  }
  {
    v1::CreateEnvRequest request;
    request.mutable_config()->set_render_mode(static_cast<v1::RenderMode>(9));
    grpc::ClientContext context;
    EXPECT_STATUS(s_.stub->CreateEnv(&context, request, &env), INVALID_ARGUMENT,
                  "render_mode: 9 is not a RenderMode");
  }
}

TEST_F(ServiceTest, GetAndDeleteEnv) {
  const std::string name = CreateEnv(*s_.stub, CreateRequest(2));
  v1::Env env;
  ASSERT_TRUE(Get(name, &env).ok());
  EXPECT_EQ(env.name(), name);
  EXPECT_EQ(env.config().n_landers(), 2);
  ASSERT_TRUE(Delete(name).ok());
  EXPECT_STATUS(Get(name, &env), NOT_FOUND, name);
  EXPECT_STATUS(Delete(name), NOT_FOUND, "does not exist");
  EXPECT_STATUS(Get("bogus", &env), INVALID_ARGUMENT,
                "name: \"bogus\" is not an env name");
  EXPECT_STATUS(Get("envs/0123", &env), NOT_FOUND, "envs/0123");
}

TEST_F(ServiceTest, ListEnvsPagesInCreationOrder) {
  std::vector<std::string> created;
  for (int i = 0; i < 5; ++i) created.push_back(CreateEnv(*s_.stub, {}));
  std::vector<std::string> listed;
  std::string token;
  int pages = 0;
  do {
    grpc::ClientContext context;
    v1::ListEnvsRequest request;
    request.set_page_size(2);
    request.set_page_token(token);
    v1::ListEnvsResponse response;
    ASSERT_TRUE(s_.stub->ListEnvs(&context, request, &response).ok());
    EXPECT_LE(response.envs_size(), 2);
    for (const v1::Env& env : response.envs()) listed.push_back(env.name());
    token = response.next_page_token();
    ++pages;
  } while (!token.empty() && pages < 10);
  EXPECT_EQ(listed, created);
  EXPECT_EQ(pages, 3);

  grpc::ClientContext context;
  v1::ListEnvsResponse all;
  ASSERT_TRUE(s_.stub->ListEnvs(&context, {}, &all).ok());  // page_size 0.
  EXPECT_EQ(all.envs_size(), 5);
  EXPECT_TRUE(all.next_page_token().empty());

  v1::ListEnvsRequest bad;
  bad.set_page_size(-1);
  grpc::ClientContext context2;
  EXPECT_STATUS(s_.stub->ListEnvs(&context2, bad, &all), INVALID_ARGUMENT,
                "page_size: -1");
  bad.set_page_size(0);
  bad.set_page_token("nonsense");
  grpc::ClientContext context3;
  EXPECT_STATUS(s_.stub->ListEnvs(&context3, bad, &all), INVALID_ARGUMENT,
                "page_token");
}

TEST_F(ServiceTest, ResetReportsSeedsAndRepeatsWithTheSameSeed) {
  const std::string a = CreateEnv(*s_.stub, {});
  const std::string b = CreateEnv(*s_.stub, {});
  v1::ResetEnvResponse first_a, first_b, again, seeded1, seeded2;
  ASSERT_TRUE(Reset(a, std::nullopt, &first_a).ok());
  ASSERT_TRUE(Reset(b, std::nullopt, &first_b).ok());
  // A first unseeded reset draws a seed, and independent envs differ.
  ASSERT_TRUE(first_a.has_seed());
  ASSERT_TRUE(first_b.has_seed());
  EXPECT_NE(first_a.seed(), first_b.seed());
  EXPECT_NE(first_a.data().observations().data(),
            first_b.data().observations().data());
  // Later unseeded resets continue the stream and report no seed.
  ASSERT_TRUE(Reset(a, std::nullopt, &again).ok());
  EXPECT_FALSE(again.has_seed());
  // The reported seed reproduces the episode.
  ASSERT_TRUE(Reset(b, first_a.seed(), &seeded1).ok());
  EXPECT_EQ(seeded1.seed(), first_a.seed());
  EXPECT_EQ(seeded1.data().observations().data(),
            first_a.data().observations().data());
  ASSERT_TRUE(Reset(a, 42, &seeded1).ok());
  ASSERT_TRUE(Reset(b, 42, &seeded2).ok());
  EXPECT_EQ(ResultBits(seeded1.data()), ResultBits(seeded2.data()));
  EXPECT_EQ(seeded1.aec().agent_selection(), 0);
  EXPECT_THAT(seeded1.aec().agents(), ::testing::ElementsAre(0, 1, 2));
  EXPECT_EQ(Rewards(seeded1.data(), 3), std::vector<float>(3, 0.0f));

  v1::Env env;
  ASSERT_TRUE(Get(a, &env).ok());
  EXPECT_TRUE(env.episode_started());
  EXPECT_EQ(env.episodes(), 3);
  EXPECT_STATUS(Reset("envs/ffff", 1, &again), NOT_FOUND, "envs/ffff");
}

TEST_F(ServiceTest, StepEnvValidatesActions) {
  const std::string name = CreateEnv(*s_.stub, CreateRequest(3));
  v1::StepEnvResponse response;
  EXPECT_STATUS(Step(name, DiscreteActions({0, 0, 0}), &response),
                FAILED_PRECONDITION, "call ResetEnv first");
  v1::ResetEnvResponse reset;
  ASSERT_TRUE(Reset(name, 1, &reset).ok());
  EXPECT_STATUS(Step(name, DiscreteActions({0, 0}), &response),
                INVALID_ARGUMENT,
                "actions: shape [2] does not match [3] (one int32 per agent "
                "of n_landers = 3)");
  EXPECT_STATUS(Step(name, ContinuousActions({0, 0, 0, 0, 0, 0}), &response),
                INVALID_ARGUMENT,
                "actions: dtype DTYPE_FLOAT32 does not "
                "match DTYPE_INT32");
  v1::Array short_data = DiscreteActions({0, 0, 0});
  short_data.mutable_data()->resize(8);
  EXPECT_STATUS(Step(name, short_data, &response), INVALID_ARGUMENT,
                "actions: data has 8 bytes but shape [3] of DTYPE_INT32 "
                "needs 12");
  EXPECT_STATUS(Step(name, DiscreteActions({0, 4, 0}), &response),
                INVALID_ARGUMENT, "lander_1");
  // None of the rejected calls stepped the world.
  v1::Env env;
  ASSERT_TRUE(Get(name, &env).ok());
  EXPECT_EQ(env.cycles(), 0);
  ASSERT_TRUE(Step(name, DiscreteActions({0, 2, 0}), &response).ok());
  EXPECT_EQ(response.data().cycles(), 1);
  EXPECT_EQ(Observations(response.data(), 3).size(), 36u);
}

TEST_F(ServiceTest, StepEnvRejectsNonFiniteContinuousActions) {
  v1::CreateEnvRequest request = CreateRequest(2);
  request.mutable_config()->set_continuous(true);
  const std::string name = CreateEnv(*s_.stub, request);
  v1::ResetEnvResponse reset;
  ASSERT_TRUE(Reset(name, 3, &reset).ok());
  v1::StepEnvResponse response;
  EXPECT_STATUS(
      Step(name, ContinuousActions({0, std::nanf(""), 0, 0}), &response),
      INVALID_ARGUMENT, "lander_0");
  EXPECT_STATUS(Step(name, DiscreteActions({0, 0}), &response),
                INVALID_ARGUMENT,
                "actions: dtype DTYPE_INT32 does not match DTYPE_FLOAT32 (one "
                "float32 [main, lateral] pair per agent of n_landers = 2)");
  // Finite values out of range are clipped, not rejected.
  EXPECT_TRUE(Step(name, ContinuousActions({5, -5, 0.5, 0}), &response).ok());
}

TEST_F(ServiceTest, StepAfterEpisodeEndFailsWithoutAutoReset) {
  v1::CreateEnvRequest request = CreateRequest(1);
  request.mutable_config()->set_max_cycles(1);
  const std::string name = CreateEnv(*s_.stub, request);
  v1::ResetEnvResponse reset;
  ASSERT_TRUE(Reset(name, 5, &reset).ok());
  v1::StepEnvResponse response;
  ASSERT_TRUE(Step(name, DiscreteActions({0}), &response).ok());
  EXPECT_TRUE(response.data().episode_over());
  EXPECT_EQ(response.data().truncations().data(), std::string(1, '\1'));
  EXPECT_STATUS(Step(name, DiscreteActions({0}), &response),
                FAILED_PRECONDITION, "episode is over; call ResetEnv");
}

TEST_F(ServiceTest, AutoResetStartsTheNextEpisodeContinuingTheStream) {
  v1::CreateEnvRequest request = CreateRequest(2);
  request.mutable_config()->set_max_cycles(2);
  request.mutable_config()->set_auto_reset(true);
  const std::string name = CreateEnv(*s_.stub, request);
  const std::string twin = CreateEnv(*s_.stub, CreateRequest(2));
  v1::ResetEnvResponse reset;
  ASSERT_TRUE(Reset(name, 9, &reset).ok());
  v1::StepEnvResponse response;
  for (int i = 0; i < 2; ++i) {
    ASSERT_TRUE(Step(name, DiscreteActions({0, 0}), &response).ok());
    EXPECT_FALSE(response.data().auto_reset());
  }
  ASSERT_TRUE(response.data().episode_over());
  // Even invalid action values are ignored by the resetting step.
  ASSERT_TRUE(Step(name, DiscreteActions({7, 7}), &response).ok());
  EXPECT_TRUE(response.data().auto_reset());
  EXPECT_FALSE(response.data().episode_over());
  EXPECT_EQ(response.data().cycles(), 0);
  EXPECT_EQ(Rewards(response.data(), 2), std::vector<float>(2, 0.0f));
  // It equals an explicit unseeded reset after the same history.
  v1::ResetEnvResponse twin_reset;
  ASSERT_TRUE(Reset(twin, 9, &twin_reset).ok());
  v1::StepEnvResponse twin_step;
  for (int i = 0; i < 2; ++i) {
    ASSERT_TRUE(Step(twin, DiscreteActions({0, 0}), &twin_step).ok());
  }
  ASSERT_TRUE(Reset(twin, std::nullopt, &twin_reset).ok());
  EXPECT_EQ(response.data().observations().data(),
            twin_reset.data().observations().data());
  v1::Env env;
  ASSERT_TRUE(Get(name, &env).ok());
  EXPECT_EQ(env.episodes(), 2);
}

TEST_F(ServiceTest, StepAgentFollowsTheTurnOrder) {
  const std::string name = CreateEnv(*s_.stub, CreateRequest(2));
  v1::StepAgentResponse response;
  EXPECT_STATUS(Agent(name, 0, &response), FAILED_PRECONDITION,
                "call ResetEnv first");
  v1::ResetEnvResponse reset;
  ASSERT_TRUE(Reset(name, 4, &reset).ok());
  EXPECT_STATUS(Agent(name, 0, &response, /*agent=*/1), FAILED_PRECONDITION,
                "agent: 1 is not agent_selection (0)");
  EXPECT_STATUS(Agent(name, std::nullopt, &response), FAILED_PRECONDITION,
                "lander_0");
  EXPECT_STATUS(Agent(name, 9, &response), INVALID_ARGUMENT, "9");
  {
    grpc::ClientContext context;
    v1::StepAgentRequest request;
    request.set_name(name);
    *request.mutable_action()->mutable_continuous() = ContinuousActions({0, 0});
    EXPECT_STATUS(s_.stub->StepAgent(&context, request, &response),
                  INVALID_ARGUMENT, "action.continuous given");
  }
  ASSERT_TRUE(Agent(name, 2, &response, /*agent=*/0).ok());
  EXPECT_EQ(response.aec().agent_selection(), 1);
  EXPECT_FALSE(response.aec().world_stepped());
  // The parallel API cannot interleave with a half-finished AEC cycle.
  v1::StepEnvResponse step;
  EXPECT_STATUS(Step(name, DiscreteActions({0, 0}), &step), FAILED_PRECONDITION,
                "is stepped with StepAgent");
  ASSERT_TRUE(Agent(name, 0, &response, /*agent=*/1).ok());
  EXPECT_TRUE(response.aec().world_stepped());
  EXPECT_EQ(response.aec().agent_selection(), 0);
  // After a reset either API may be used again.
  ASSERT_TRUE(Reset(name, 4, &reset).ok());
  ASSERT_TRUE(Step(name, DiscreteActions({0, 0}), &step).ok());
  EXPECT_STATUS(Agent(name, 0, &response), FAILED_PRECONDITION,
                "is stepped with StepEnv");
}

TEST_F(ServiceTest, StepBatchKeepsOrderAndReportsItemErrors) {
  const std::string a = CreateEnv(*s_.stub, CreateRequest(1));
  const std::string b = CreateEnv(*s_.stub, CreateRequest(2));
  const std::string unreset = CreateEnv(*s_.stub, CreateRequest(1));
  v1::ResetEnvResponse reset;
  ASSERT_TRUE(Reset(a, 1, &reset).ok());
  ASSERT_TRUE(Reset(b, 1, &reset).ok());
  v1::StepBatchRequest request;
  auto add = [&](const std::string& name, const v1::Array& actions) {
    v1::StepEnvRequest* step = request.add_steps();
    step->set_name(name);
    *step->mutable_actions() = actions;
  };
  add(b, DiscreteActions({0, 0}));
  add("envs/missing", DiscreteActions({0}));
  add(a, DiscreteActions({0, 0}));
  add(unreset, DiscreteActions({0}));
  grpc::ClientContext context;
  v1::StepBatchResponse response;
  ASSERT_TRUE(s_.stub->StepBatch(&context, request, &response).ok());
  ASSERT_EQ(response.results_size(), 4);
  ASSERT_TRUE(response.results(0).has_data());
  EXPECT_EQ(Observations(response.results(0).data(), 2).size(), 24u);
  EXPECT_EQ(response.results(1).error().code(), grpc::StatusCode::NOT_FOUND);
  EXPECT_THAT(response.results(1).error().message(),
              HasSubstr("steps[1].name: envs/missing"));
  EXPECT_EQ(response.results(2).error().code(),
            grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_THAT(response.results(2).error().message(),
              HasSubstr("steps[2].actions: shape [2] does not match [1]"));
  EXPECT_EQ(response.results(3).error().code(),
            grpc::StatusCode::FAILED_PRECONDITION);

  add(b, DiscreteActions({0, 0}));  // b twice.
  grpc::ClientContext context2;
  EXPECT_STATUS(s_.stub->StepBatch(&context2, request, &response),
                INVALID_ARGUMENT,
                "steps[4].name: " + b + " also appears at steps[0]");
  grpc::ClientContext context3;
  EXPECT_TRUE(
      s_.stub->StepBatch(&context3, v1::StepBatchRequest(), &response).ok());
  EXPECT_EQ(response.results_size(), 0);
}

TEST_F(ServiceTest, RenderEnvReturnsRgbOrPng) {
  v1::CreateEnvRequest request = CreateRequest(2);
  request.mutable_config()->set_render_mode(v1::RENDER_MODE_RGB_ARRAY);
  const std::string name = CreateEnv(*s_.stub, request);
  v1::ResetEnvResponse reset;
  ASSERT_TRUE(Reset(name, 2, &reset).ok());
  v1::Frame frame;
  ASSERT_TRUE(Render(name, v1::FRAME_FORMAT_UNSPECIFIED, &frame).ok());
  EXPECT_EQ(frame.format(), v1::FRAME_FORMAT_RGB);
  EXPECT_EQ(frame.width(), 600);
  EXPECT_EQ(frame.height(), 400);
  EXPECT_EQ(frame.data().size(), 600u * 400u * 3u);
  ASSERT_TRUE(Render(name, v1::FRAME_FORMAT_PNG, &frame).ok());
  EXPECT_EQ(frame.format(), v1::FRAME_FORMAT_PNG);
  EXPECT_EQ(frame.data().substr(0, 4), "\x89PNG");
  EXPECT_STATUS(Render(name, static_cast<v1::FrameFormat>(5), &frame),
                INVALID_ARGUMENT, "format: 5 is not a FrameFormat");

  const std::string plain = CreateEnv(*s_.stub, CreateRequest(1));
  ASSERT_TRUE(Reset(plain, 2, &reset).ok());
  EXPECT_EQ(Render(plain, v1::FRAME_FORMAT_RGB, &frame).error_code(),
            grpc::StatusCode::FAILED_PRECONDITION);
}

TEST(ServiceLimitsTest, OversizedMessageIsResourceExhausted) {
  InProcess s(ServiceOptions(), /*max_message_mb=*/1);
  v1::StepEnvRequest request;
  request.set_name("envs/0");
  request.mutable_actions()->mutable_data()->assign(2 << 20, 'x');
  grpc::ClientContext context;
  v1::StepEnvResponse response;
  EXPECT_EQ(s.stub->StepEnv(&context, request, &response).error_code(),
            grpc::StatusCode::RESOURCE_EXHAUSTED);
}

TEST(StatusMappingTest, CanonicalCodesKeepTheirNumberOthersAreInternal) {
  const grpc::Status not_found =
      ToGrpcStatus(absl::NotFoundError("name: envs/x"));
  EXPECT_EQ(not_found.error_code(), grpc::StatusCode::NOT_FOUND);
  EXPECT_EQ(not_found.error_message(), "name: envs/x");
  EXPECT_TRUE(ToGrpcStatus(absl::OkStatus()).ok());
  EXPECT_EQ(ToGrpcStatus(absl::UnauthenticatedError("token")).error_code(),
            grpc::StatusCode::UNAUTHENTICATED);
  const grpc::Status odd =
      ToGrpcStatus(absl::Status(static_cast<absl::StatusCode>(42), "odd"));
  EXPECT_EQ(odd.error_code(), grpc::StatusCode::INTERNAL);
  EXPECT_THAT(odd.error_message(), HasSubstr("odd"));
}

}  // namespace
}  // namespace mll::service::testing
