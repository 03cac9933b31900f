// Helpers shared by the core's Env tests: building envs, stepping with fixed
// actions, and placing landers for exact contact scenarios through
// Env::SetLanderStateForTest.
#ifndef MLL_TESTS_CORE_ENV_TEST_UTIL_H_
#define MLL_TESTS_CORE_ENV_TEST_UTIL_H_

#include <cstdint>
#include <cstring>
#include <memory>
#include <random>
#include <vector>

#include "gtest/gtest.h"
#include "mll/core/env.h"

namespace mll::core {
namespace testing {

inline std::unique_ptr<Env> MakeEnv(const EnvConfig& config) {
  auto env = Env::Create(config);
  EXPECT_TRUE(env.ok()) << env.status();
  return env.ok() ? std::move(*env) : nullptr;
}

// One step with the same discrete action (or its continuous twin) for all.
inline StepResult StepAll(Env& env, const std::vector<int32_t>& discrete,
                          const std::vector<float>& continuous = {}) {
  ActionsView view;
  view.discrete = discrete;
  view.continuous = continuous;
  StepResult result;
  const absl::Status status = env.Step(view, &result);
  EXPECT_TRUE(status.ok()) << status;
  return result;
}

inline StepResult StepNoop(Env& env) {
  const int n = env.n_landers();
  return StepAll(env, std::vector<int32_t>(n, 0),
                 std::vector<float>(2 * n, 0.0f));
}

// Pad centre and height (meters).
inline constexpr double kPadX = 10.0;
inline constexpr double kPadY = 40.0 / 3.0 / 4.0;

// Upright, feet (legs swung out, 0.53 m below the centre) 3 cm above the
// pad, at rest: it settles and sleeps.
inline void PlaceRestingOnPad(Env& env, int agent, double x = kPadX) {
  ASSERT_TRUE(
      env.SetLanderStateForTest(agent, x, kPadY + 0.56, 0.0, 0.0, 0.0, 0.0)
          .ok());
}

// Upside down just above the pad, falling: its body hits the moon.
inline void PlaceUpsideDownOnPad(Env& env, int agent, double x = kPadX) {
  ASSERT_TRUE(
      env.SetLanderStateForTest(agent, x, kPadY + 0.7, M_PI, 0.0, -1.0, 0.0)
          .ok());
}

// Holds an agent high above the terrain, motionless (call every step).
inline void HoldHigh(Env& env, int agent, double x) {
  ASSERT_TRUE(
      env.SetLanderStateForTest(agent, x, 11.0, 0.0, 0.0, 0.0, 0.0).ok());
}

// No-op steps until `agent` is done (or `max_steps`), holding the agents in
// `held` high at x = 2 + 3 * index. Returns the result of every step.
inline std::vector<StepResult> StepUntilDone(Env& env, int agent,
                                             const std::vector<int>& held,
                                             int max_steps = 200) {
  std::vector<StepResult> results;
  for (int s = 0; s < max_steps && env.is_active(agent); ++s) {
    for (int h : held) {
      if (env.is_active(h)) HoldHigh(env, h, 2.0 + 3.0 * h);
    }
    results.push_back(StepNoop(env));
  }
  return results;
}

// Bits of a whole StepResult, for bit-exact comparisons.
inline void AppendBits(const StepResult& r, std::vector<uint8_t>* bits) {
  auto append = [bits](const void* data, size_t size) {
    const auto* p = static_cast<const uint8_t*>(data);
    bits->insert(bits->end(), p, p + size);
  };
  append(r.observations.data(), r.observations.size() * sizeof(float));
  append(r.rewards.data(), r.rewards.size() * sizeof(float));
  append(r.terminations.data(), r.terminations.size());
  append(r.truncations.data(), r.truncations.size());
  append(r.stepped.data(), r.stepped.size());
  append(r.outcomes.data(), r.outcomes.size() * sizeof(Outcome));
}

}  // namespace testing
}  // namespace mll::core

#endif  // MLL_TESTS_CORE_ENV_TEST_UTIL_H_
