// Same seed + same actions = same bits, whatever the render mode; another
// seed or an unseeded Reset gives another episode.
#include <optional>
#include <random>
#include <vector>

#include "env_test_util.h"
#include "gtest/gtest.h"
#include "mll/core/env.h"
#include "mll/core/renderer.h"

namespace mll::core {
namespace {

using testing::AppendBits;
using testing::MakeEnv;

constexpr int kSteps = 500;

// Runs kSteps steps of random actions drawn from `action_seed` (resetting
// without a seed whenever the episode ends) and returns every result's bits.
// With `render`, also draws a frame with the overlay (which ages particles)
// every step, to prove that decoration never feeds back into the physics.
// With `watch`, draws the env's scene every step as a dashboard viewer does,
// whatever the render mode.
std::vector<uint8_t> Trace(EnvConfig config, uint64_t seed,
                           uint32_t action_seed, bool render,
                           int* max_particles = nullptr, bool watch = false) {
  config.render_mode = render ? RenderMode::kRgbArray : RenderMode::kNone;
  auto env = MakeEnv(config);
  std::mt19937 actions_rng(action_seed);
  std::vector<uint8_t> bits;
  StepResult result;
  env->Reset(seed, &result);
  AppendBits(result, &bits);
  const int n = config.n_landers;
  for (int s = 0; s < kSteps; ++s) {
    if (result.episode_over) {
      env->Reset(std::nullopt, &result);
      AppendBits(result, &bits);
    }
    std::vector<int32_t> discrete(n);
    std::vector<float> continuous(2 * n);
    for (int32_t& a : discrete) a = static_cast<int32_t>(actions_rng() % 4);
    for (float& a : continuous) {
      a = static_cast<float>(actions_rng() % 2001) / 1000.0f - 1.0f;
    }
    result = testing::StepAll(*env, discrete, continuous);
    AppendBits(result, &bits);
    if (render) {
      const Scene scene = env->scene();
      const int particles = static_cast<int>(scene.particles.size());
      if (max_particles != nullptr && particles > *max_particles) {
        *max_particles = particles;
      }
      RenderOptions options;
      options.overlay = true;
      EXPECT_TRUE(RenderEnv(*env, options).ok());
    }
    if (watch) {
      RenderOptions options;
      options.overlay = s % 2 == 0;
      RenderScene(env->scene(), options);
    }
  }
  return bits;
}

EnvConfig ThreeLanders(bool continuous) {
  EnvConfig config;
  config.n_landers = 3;
  config.continuous = continuous;
  config.terminate_on_damage = false;
  return config;
}

TEST(EnvDeterminismTest, SameSeedSameActionsSameBits) {
  for (bool continuous : {false, true}) {
    const EnvConfig config = ThreeLanders(continuous);
    EXPECT_EQ(Trace(config, 42, 7, false), Trace(config, 42, 7, false))
        << "continuous " << continuous;
  }
}

TEST(EnvDeterminismTest, RenderModeDoesNotChangeTheBits) {
  for (bool continuous : {false, true}) {
    const EnvConfig config = ThreeLanders(continuous);
    int particles = 0;
    const std::vector<uint8_t> rendered =
        Trace(config, 42, 7, true, &particles);
    EXPECT_GT(particles, 0) << "rendering made no particles to test with";
    EXPECT_EQ(rendered, Trace(config, 42, 7, false));
  }
}

TEST(EnvDeterminismTest, DrawingTheSceneEveryStepDoesNotChangeTheBits) {
  for (bool render : {false, true}) {
    const EnvConfig config = ThreeLanders(false);
    EXPECT_EQ(Trace(config, 42, 7, render, nullptr, /*watch=*/true),
              Trace(config, 42, 7, false))
        << "render " << render;
  }
}

TEST(EnvDeterminismTest, WithoutRenderModeThereAreNoParticles) {
  EnvConfig config = ThreeLanders(false);
  auto env = MakeEnv(config);
  StepResult result;
  env->Reset(1, &result);
  for (int s = 0; s < 20; ++s) {
    testing::StepAll(*env, std::vector<int32_t>(3, 2));
  }
  EXPECT_TRUE(env->scene().particles.empty());
}

TEST(EnvDeterminismTest, AnotherSeedDiverges) {
  const EnvConfig config = ThreeLanders(false);
  EXPECT_NE(Trace(config, 42, 7, false), Trace(config, 43, 7, false));
}

TEST(EnvDeterminismTest, ResetWithoutSeedStartsANewEpisode) {
  EnvConfig config = ThreeLanders(false);
  auto env = MakeEnv(config);
  StepResult first;
  StepResult second;
  env->Reset(5, &first);
  env->Reset(std::nullopt, &second);
  EXPECT_NE(first.observations, second.observations);

  // The unseeded reset continues the stream: replaying it gives the same.
  auto replay = MakeEnv(config);
  StepResult replay_first;
  StepResult replay_second;
  replay->Reset(5, &replay_first);
  replay->Reset(std::nullopt, &replay_second);
  EXPECT_EQ(second.observations, replay_second.observations);
}

TEST(EnvDeterminismTest, NeverSeededEnvUsesSeedZero) {
  const EnvConfig config = ThreeLanders(false);
  auto unseeded = MakeEnv(config);
  auto seeded = MakeEnv(config);
  StepResult a;
  StepResult b;
  unseeded->Reset(std::nullopt, &a);
  seeded->Reset(0, &b);
  EXPECT_EQ(a.observations, b.observations);
}

}  // namespace
}  // namespace mll::core
