// Validation: bad configs and actions get INVALID_ARGUMENT naming the field,
// the value and the allowed range; stepping out of turn gets
// FAILED_PRECONDITION.
#include <cmath>
#include <limits>
#include <string>
#include <vector>

#include "env_test_util.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "mll/core/env.h"

namespace mll::core {
namespace {

using ::testing::AllOf;
using ::testing::HasSubstr;

void ExpectInvalid(const EnvConfig& config, const std::string& field,
                   const std::string& value, const std::string& allowed) {
  const absl::Status status = ValidateEnvConfig(config);
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument) << status;
  EXPECT_THAT(std::string(status.message()),
              AllOf(HasSubstr(field), HasSubstr(value), HasSubstr(allowed)));
  EXPECT_EQ(Env::Create(config).status().code(),
            absl::StatusCode::kInvalidArgument);
}

TEST(EnvConfigTest, DefaultsAreValid) {
  EXPECT_TRUE(ValidateEnvConfig(EnvConfig()).ok());
}

TEST(EnvConfigTest, EveryRangeIsChecked) {
  const double nan = std::numeric_limits<double>::quiet_NaN();
  const double inf = std::numeric_limits<double>::infinity();
  EnvConfig c;
  c.n_landers = 40;
  ExpectInvalid(c, "n_landers", "40", "allowed 1..32");
  c = EnvConfig();
  c.n_landers = 0;
  ExpectInvalid(c, "n_landers", "0", "1..32");
  c = EnvConfig();
  c.max_cycles = 0;
  ExpectInvalid(c, "max_cycles", "0", ">= 1");
  for (double g : {0.0, -12.0, 3.0, nan}) {
    c = EnvConfig();
    c.gravity = g;
    ExpectInvalid(c, "gravity", "", "(-12, 0)");
  }
  c = EnvConfig();
  c.wind_power = 20.5;
  ExpectInvalid(c, "wind_power", "20.5", "[0, 20]");
  c = EnvConfig();
  c.wind_power = -1;
  ExpectInvalid(c, "wind_power", "-1", "[0, 20]");
  c = EnvConfig();
  c.turbulence_power = 2.5;
  ExpectInvalid(c, "turbulence_power", "2.5", "[0, 2]");
  c = EnvConfig();
  c.damage_reward = nan;
  ExpectInvalid(c, "damage_reward", "nan", "finite");
  c = EnvConfig();
  c.successful_reward = inf;
  ExpectInvalid(c, "successful_reward", "inf", "finite");
  c = EnvConfig();
  c.terminate_reward = -inf;
  ExpectInvalid(c, "terminate_reward", "-inf", "finite");
  c = EnvConfig();
  c.render_mode = static_cast<RenderMode>(7);
  ExpectInvalid(c, "render_mode", "7", "rgb_array");
}

TEST(EnvConfigTest, BoundariesAreAccepted) {
  EnvConfig c;
  c.n_landers = 32;
  c.max_cycles = 1;
  c.gravity = -11.99;
  c.wind_power = 20;
  c.turbulence_power = 0;
  EXPECT_TRUE(ValidateEnvConfig(c).ok());
  c.n_landers = 1;
  c.gravity = -0.01;
  c.wind_power = 0;
  c.turbulence_power = 2;
  EXPECT_TRUE(ValidateEnvConfig(c).ok());
}

TEST(EnvConfigTest, StepBeforeResetAndAfterTheEpisode) {
  EnvConfig config;
  config.n_landers = 2;
  config.max_cycles = 1;
  auto env = testing::MakeEnv(config);
  std::vector<int32_t> actions = {0, 0};
  StepResult result;
  absl::Status status = env->Step(ActionsView{actions, {}}, &result);
  EXPECT_EQ(status.code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(std::string(status.message()), HasSubstr("before reset"));
  env->Reset(1, &result);
  EXPECT_TRUE(env->Step(ActionsView{actions, {}}, &result).ok());
  EXPECT_TRUE(result.episode_over);
  status = env->Step(ActionsView{actions, {}}, &result);
  EXPECT_EQ(status.code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(std::string(status.message()), HasSubstr("episode is over"));
}

TEST(EnvConfigTest, BadActionsAreRejectedBeforeAnyPhysics) {
  EnvConfig config;
  config.n_landers = 3;
  auto env = testing::MakeEnv(config);
  StepResult reset;
  env->Reset(1, &reset);
  StepResult result;
  std::vector<int32_t> too_few = {0, 0};
  absl::Status status = env->Step(ActionsView{too_few, {}}, &result);
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(status.message()),
              AllOf(HasSubstr("2"), HasSubstr("expected 3")));
  std::vector<int32_t> bad = {0, 4, 0};
  status = env->Step(ActionsView{bad, {}}, &result);
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(status.message()),
              AllOf(HasSubstr("lander_1"), HasSubstr("4"), HasSubstr("0..3")));
  EXPECT_EQ(env->cycles(), 0) << "a rejected step must not run";
  // The rejected steps changed nothing: the next valid step equals a fresh
  // env's first step.
  auto fresh = testing::MakeEnv(config);
  fresh->Reset(1, &reset);
  const std::vector<int32_t> ok = {0, 2, 0};
  EXPECT_EQ(testing::StepAll(*env, ok).observations,
            testing::StepAll(*fresh, ok).observations);

  config.continuous = true;
  auto cont = testing::MakeEnv(config);
  cont->Reset(1, &reset);
  std::vector<float> wrong_size(5, 0.0f);
  status = cont->Step(ActionsView{{}, wrong_size}, &result);
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(status.message()), HasSubstr("expected 6"));
  std::vector<float> not_finite = {0, 0, 0, std::nanf(""), 0, 0};
  status = cont->Step(ActionsView{{}, not_finite}, &result);
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(
      std::string(status.message()),
      AllOf(HasSubstr("lander_1"), HasSubstr("nan"), HasSubstr("finite")));
}

}  // namespace
}  // namespace mll::core
