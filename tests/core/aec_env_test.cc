// AecEnv: PettingZoo's AEC bookkeeping over the one parallel step, checked
// against a parallel Env run with the same seed and actions.
#include "mll/core/aec_env.h"

#include <optional>
#include <random>
#include <vector>

#include "env_test_util.h"
#include "gtest/gtest.h"
#include "mll/core/env.h"

namespace mll::core {
namespace {

EnvConfig Config() {
  EnvConfig config;
  config.n_landers = 3;
  config.shared_reward = false;
  config.terminate_on_damage = false;
  config.max_cycles = 300;
  return config;
}

TEST(AecEnvTest, MatchesParallelRunWithPettingZooBookkeeping) {
  auto aec_core = testing::MakeEnv(Config());
  auto parallel = testing::MakeEnv(Config());
  AecEnv aec(aec_core.get());
  aec.Reset(11);
  StepResult expected;
  parallel->Reset(11, &expected);
  std::mt19937 rng(5);
  std::vector<double> parallel_returns(3, 0.0);
  std::vector<double> aec_returns(3, 0.0);
  int cycles = 0;
  int dead_steps = 0;
  while (!aec.agents().empty()) {
    ASSERT_LT(cycles, 400);
    // One cycle: every agent in agents() acts (or takes its dead step) once,
    // in order; the world steps when the last live agent has acted.
    std::vector<int32_t> actions(3, 0);
    for (int a = 0; a < 3; ++a) actions[a] = static_cast<int32_t>(rng() % 4);
    const std::vector<int> live_before = aec.agents();
    for (int a : live_before) {
      ASSERT_EQ(aec.agent_selection(), a);
      EXPECT_FALSE(aec.terminated(a) || aec.truncated(a));
      // last(): the cumulative reward since this agent's previous turn.
      aec_returns[a] += aec.cumulative_reward(a);
      AgentAction action;
      action.discrete = actions[a];
      ASSERT_TRUE(aec.Step(action).ok());
      if (a != live_before.back()) {
        EXPECT_EQ(aec.reward(aec.agent_selection()), 0.0f)
            << "_clear_rewards before the last agent";
      }
    }
    expected = testing::StepAll(*parallel, actions);
    ++cycles;
    for (int a : live_before) {
      parallel_returns[a] += expected.rewards[a];
      EXPECT_EQ(aec.reward(a), expected.rewards[a]);
      EXPECT_EQ(aec.terminated(a), expected.terminations[a] == 1);
      EXPECT_EQ(aec.truncated(a), expected.truncations[a] == 1);
      for (int k = 0; k < kObservationSize; ++k) {
        EXPECT_EQ(aec.observe(a)[k],
                  expected.observations[a * kObservationSize + k]);
      }
    }
    // Done agents take their dead steps first, in agents() order, then the
    // turn returns to the first live agent.
    std::vector<int> dead;
    for (int a : live_before) {
      if (expected.terminations[a] || expected.truncations[a])
        dead.push_back(a);
    }
    for (int a : dead) {
      ASSERT_EQ(aec.agent_selection(), a);
      aec_returns[a] += aec.cumulative_reward(a);
      AgentAction wrong;
      EXPECT_EQ(aec.Step(wrong).code(), absl::StatusCode::kFailedPrecondition);
      ASSERT_TRUE(aec.Step(std::nullopt).ok());
      ++dead_steps;
    }
    std::vector<int> live;
    for (int a : live_before) {
      if (!expected.terminations[a] && !expected.truncations[a])
        live.push_back(a);
    }
    EXPECT_EQ(aec.agents(), live);
    if (!live.empty()) {
      EXPECT_EQ(aec.agent_selection(), live.front());
    }
  }
  EXPECT_EQ(dead_steps, 3);
  EXPECT_EQ(aec.agent_selection(), -1);
  for (int a = 0; a < 3; ++a) {
    EXPECT_NEAR(aec_returns[a], parallel_returns[a], 1e-3) << a;
    EXPECT_NEAR(aec_returns[a], aec_core->episode_return(a), 1e-3) << a;
  }
  EXPECT_EQ(aec.Step(std::nullopt).code(),
            absl::StatusCode::kFailedPrecondition);
}

TEST(AecEnvTest, CumulativeRewardResetsOnTheAgentsOwnTurn) {
  auto core = testing::MakeEnv(Config());
  AecEnv aec(core.get());
  aec.Reset(2);
  AgentAction main_engine;
  main_engine.discrete = 2;
  // Cycle 1: agents 0, 1 act (rewards cleared), agent 2 steps the world.
  ASSERT_TRUE(aec.Step(main_engine).ok());
  ASSERT_TRUE(aec.Step(main_engine).ok());
  ASSERT_TRUE(aec.Step(main_engine).ok());
  const float r0 = aec.reward(0);
  const float r1 = aec.reward(1);
  EXPECT_NE(r0, 0.0f);
  EXPECT_EQ(aec.cumulative_reward(0), r0);
  EXPECT_EQ(aec.cumulative_reward(2), aec.reward(2));
  // Agent 0 acts: its cumulative restarts from 0, the rewards are cleared.
  ASSERT_TRUE(aec.Step(main_engine).ok());
  EXPECT_EQ(aec.cumulative_reward(0), 0.0f);
  EXPECT_EQ(aec.reward(1), 0.0f);
  // Agent 1 has not acted yet: it still holds the world step's reward.
  EXPECT_EQ(aec.cumulative_reward(1), r1);
  EXPECT_EQ(aec.agent_selection(), 1);
}

TEST(AecEnvTest, Errors) {
  auto core = testing::MakeEnv(Config());
  AecEnv aec(core.get());
  AgentAction action;
  EXPECT_EQ(aec.Step(action).code(), absl::StatusCode::kFailedPrecondition);
  aec.Reset(1);
  EXPECT_EQ(aec.Step(std::nullopt).code(),
            absl::StatusCode::kFailedPrecondition);
  action.discrete = 9;
  const absl::Status bad = aec.Step(action);
  EXPECT_EQ(bad.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(bad.message().find("lander_0"), absl::string_view::npos);
  EXPECT_EQ(aec.agent_selection(), 0) << "a rejected action changes nothing";
}

}  // namespace
}  // namespace mll::core
