// An environment's step allocates nothing with the C++ heap once its episode
// has started (without rendering), except in the step that ends a lander: a
// server steps thousands of envs per second on each thread. This executable
// replaces the global operator new to count calls; Box2D's own pool allocator
// (b2Alloc, malloc) is not ours and not counted.
#include <atomic>
#include <cstdint>
#include <cstdlib>
#include <new>
#include <random>
#include <vector>

#include "env_test_util.h"
#include "gtest/gtest.h"
#include "mll/core/env.h"

namespace {
std::atomic<int64_t> g_operator_news{0};
}  // namespace

void* operator new(std::size_t size) {
  g_operator_news.fetch_add(1, std::memory_order_relaxed);
  if (void* memory = std::malloc(size == 0 ? 1 : size)) return memory;
  throw std::bad_alloc();
}
void operator delete(void* memory) noexcept { std::free(memory); }
void operator delete(void* memory, std::size_t) noexcept { std::free(memory); }

namespace mll::core {
namespace {

struct Counted {
  int steps = 0;     // Steps in which every active lander stayed active.
  int64_t news = 0;  // Their operator new calls.
};

int ActiveLanders(const Env& env) {
  int active = 0;
  for (int i = 0; i < env.n_landers(); ++i) active += env.is_active(i) ? 1 : 0;
  return active;
}

// The operator new calls of up to `steps` steps of `env` with random actions
// (drawn beforehand), stopping when the episode ends, counted over the steps
// in which no lander ended: the step that ends one keeps its outline for
// drawing (LanderParts), which allocates once per lander and episode.
Counted OperatorNewsOfSteps(Env& env, int steps, uint32_t seed) {
  const int n = env.n_landers();
  std::mt19937 random(seed);
  std::uniform_int_distribution<int32_t> discrete_action(0, 3);
  std::uniform_real_distribution<float> continuous_value(-1.0f, 1.0f);
  std::vector<std::vector<int32_t>> discrete(steps, std::vector<int32_t>(n));
  std::vector<std::vector<float>> continuous(steps, std::vector<float>(2 * n));
  for (int s = 0; s < steps; ++s) {
    for (int32_t& action : discrete[s]) action = discrete_action(random);
    for (float& value : continuous[s]) value = continuous_value(random);
  }
  StepResult result;
  Counted counted;
  for (int s = 0; s < steps && !env.episode_over(); ++s) {
    ActionsView actions;
    actions.discrete = discrete[s];
    actions.continuous = continuous[s];
    const int active_before = ActiveLanders(env);
    const int64_t news_before = g_operator_news.load();
    const bool ok = env.Step(actions, &result).ok();
    const int64_t news = g_operator_news.load() - news_before;
    EXPECT_TRUE(ok) << "step " << s;
    // The first step sizes `result`'s arrays.
    if (s == 0 || ActiveLanders(env) != active_before) continue;
    ++counted.steps;
    counted.news += news;
  }
  return counted;
}

// Resets an env of `config` with `seed` and expects no operator new in its
// steps that end no lander, over at least 20 such steps.
void ExpectStepsDoNotAllocate(const EnvConfig& config, uint64_t seed) {
  auto env = testing::MakeEnv(config);
  ASSERT_NE(env, nullptr);
  StepResult reset;
  env->Reset(seed, &reset);
  const Counted counted =
      OperatorNewsOfSteps(*env, 200, static_cast<uint32_t>(seed));
  EXPECT_GE(counted.steps, 20);
  EXPECT_EQ(counted.news, 0) << "over " << counted.steps << " steps";
}

TEST(EnvAllocationTest, ADiscreteStepDoesNotAllocate) {
  EnvConfig config;
  config.n_landers = 3;
  ExpectStepsDoNotAllocate(config, 7);
}

TEST(EnvAllocationTest, AContinuousStepDoesNotAllocate) {
  EnvConfig config;
  config.n_landers = 8;
  config.continuous = true;
  // The others fly on when one is damaged, so the episode lasts.
  config.terminate_on_damage = false;
  ExpectStepsDoNotAllocate(config, 11);
}

// The counter sees the allocations it is meant to catch.
TEST(EnvAllocationTest, TheCounterCountsAVector) {
  const int64_t before = g_operator_news.load();
  std::vector<double>* values = new std::vector<double>(16, 0.0);
  const int64_t counted = g_operator_news.load() - before;
  delete values;
  EXPECT_EQ(counted, 2);
}

}  // namespace
}  // namespace mll::core
