// Each option changes what it should and nothing else.
#include <cmath>
#include <vector>

#include "env_test_util.h"
#include "gtest/gtest.h"
#include "mll/core/env.h"

namespace mll::core {
namespace {

using testing::MakeEnv;

// Observations of `steps` steps of a fixed action cycle.
std::vector<float> ObservationTrace(const EnvConfig& config, int steps,
                                    bool continuous_twin) {
  auto env = MakeEnv(config);
  StepResult r;
  env->Reset(9, &r);
  std::vector<float> trace = r.observations;
  // Discrete 0..3 and their continuous twins (same engine command).
  const float twins[4][2] = {{0, 0}, {0, -1}, {1, 0}, {0, 1}};
  const int n = config.n_landers;
  for (int s = 0; s < steps && !r.episode_over; ++s) {
    std::vector<int32_t> d(n);
    std::vector<float> c(2 * n);
    for (int i = 0; i < n; ++i) {
      d[i] = (s / 3 + i) % 4;
      // Out-of-range continuous values are clipped onto the twins.
      c[2 * i] = twins[d[i]][0] * (continuous_twin ? 5.0f : 1.0f);
      c[2 * i + 1] = twins[d[i]][1] * (continuous_twin ? 7.0f : 1.0f);
    }
    r = testing::StepAll(*env, d, c);
    trace.insert(trace.end(), r.observations.begin(), r.observations.end());
  }
  return trace;
}

TEST(EnvOptionsTest, NLandersSizesEverything) {
  for (int n : {1, 5, 32}) {
    EnvConfig config;
    config.n_landers = n;
    auto env = MakeEnv(config);
    StepResult r;
    env->Reset(0, &r);
    EXPECT_EQ(r.observations.size(), static_cast<size_t>(n) * 12);
    EXPECT_EQ(r.rewards.size(), static_cast<size_t>(n));
    EXPECT_EQ(env->num_active(), n);
    EXPECT_EQ(AgentName(n - 1), "lander_" + std::to_string(n - 1));
  }
}

TEST(EnvOptionsTest, ContinuousTwinsOfDiscreteActionsFlyTheSame) {
  EnvConfig discrete;
  discrete.terminate_on_damage = false;
  EnvConfig continuous = discrete;
  continuous.continuous = true;
  EXPECT_EQ(ObservationTrace(discrete, 60, false),
            ObservationTrace(continuous, 60, true));
}

TEST(EnvOptionsTest, MaxCyclesTruncatesNotTerminates) {
  EnvConfig config;
  config.max_cycles = 5;
  auto env = MakeEnv(config);
  StepResult r;
  env->Reset(0, &r);
  for (int s = 0; s < 4; ++s) {
    r = testing::StepNoop(*env);
    EXPECT_FALSE(r.episode_over);
  }
  r = testing::StepNoop(*env);
  EXPECT_TRUE(r.episode_over);
  EXPECT_EQ(env->cycles(), 5);
  for (int i = 0; i < 3; ++i) {
    EXPECT_EQ(r.truncations[i], 1);
    EXPECT_EQ(r.terminations[i], 0);
    EXPECT_EQ(r.outcomes[i], Outcome::kTruncated);
    EXPECT_EQ(env->episode_length(i), 5);
  }
}

TEST(EnvOptionsTest, GravityChangesOnlyTheFall) {
  EnvConfig normal;
  normal.n_landers = 1;
  EnvConfig light = normal;
  light.gravity = -2.0;
  const std::vector<float> a = ObservationTrace(normal, 20, false);
  const std::vector<float> b = ObservationTrace(light, 20, false);
  ASSERT_EQ(a.size(), b.size());
  const size_t last = a.size() - 12;
  EXPECT_LT(a[last + 3], b[last + 3] - 0.1f);   // Falls faster.
  EXPECT_NEAR(a[last + 0], b[last + 0], 2e-3);  // Same sideways drift.
}

TEST(EnvOptionsTest, WindPushesOnlyWhenEnabled) {
  EnvConfig calm;
  calm.n_landers = 1;
  EnvConfig calm_strong = calm;
  calm_strong.wind_power = 20.0;  // Ignored without enable_wind.
  calm_strong.turbulence_power = 2.0;
  EXPECT_EQ(ObservationTrace(calm, 50, false),
            ObservationTrace(calm_strong, 50, false));
  EnvConfig windy = calm_strong;
  windy.enable_wind = true;
  const std::vector<float> w1 = ObservationTrace(windy, 50, false);
  EXPECT_NE(w1, ObservationTrace(calm, 50, false));
  EXPECT_EQ(w1, ObservationTrace(windy, 50, false)) << "wind is seeded too";
}

TEST(EnvOptionsTest, RewardOptionsDoNotChangeThePhysics) {
  EnvConfig base;
  base.terminate_on_damage = false;
  EnvConfig other = base;
  other.shared_reward = false;
  other.damage_reward = -3;
  other.successful_reward = 3;
  other.terminate_reward = -3;
  EXPECT_EQ(ObservationTrace(base, 100, false),
            ObservationTrace(other, 100, false));
}

}  // namespace
}  // namespace mll::core
