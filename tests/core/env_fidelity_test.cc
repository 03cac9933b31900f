// Fidelity with Gymnasium's LunarLander-v3 at n_landers = 1: Gymnasium's own
// heuristic pilot must fly our lander as well as it flies Gymnasium's
// (a faithful port on Box2D 2.4.1 scores about 237 / 88.5%
// landed discrete and 286 / 100% continuous; our crash adds terminate_reward).
#include <cstdio>

#include "gtest/gtest.h"
#include "mll/core/env.h"
#include "mll/core/heuristic.h"

namespace mll::core {
namespace {

struct PilotStats {
  double mean_return = 0.0;
  double landed_fraction = 0.0;
  double mean_length = 0.0;
};

PilotStats FlyHeuristic(bool continuous, int episodes) {
  EnvConfig config;
  config.n_landers = 1;
  config.continuous = continuous;
  config.max_cycles = 1000;  // Gymnasium's TimeLimit for LunarLander-v3.
  auto env = Env::Create(config);
  EXPECT_TRUE(env.ok()) << env.status();
  PilotStats stats;
  int landed = 0;
  for (int seed = 0; seed < episodes; ++seed) {
    StepResult result;
    (*env)->Reset(seed, &result);
    while (!result.episode_over) {
      const AgentAction action =
          HeuristicAction((*env)->observation(0), continuous);
      ActionsView view;
      view.discrete = absl::MakeConstSpan(&action.discrete, 1);
      view.continuous = action.continuous;
      const absl::Status status = (*env)->Step(view, &result);
      EXPECT_TRUE(status.ok()) << status;
      if (!status.ok()) break;
    }
    stats.mean_return += (*env)->episode_return(0);
    stats.mean_length += (*env)->episode_length(0);
    if ((*env)->outcome(0) == Outcome::kLanded) ++landed;
  }
  stats.mean_return /= episodes;
  stats.mean_length /= episodes;
  stats.landed_fraction = static_cast<double>(landed) / episodes;
  std::printf("%s: mean return %.1f, landed %.1f%%, mean length %.1f\n",
              continuous ? "continuous" : "discrete", stats.mean_return,
              100 * stats.landed_fraction, stats.mean_length);
  return stats;
}

TEST(EnvFidelityTest, DiscreteHeuristicScoresLikeGymnasium) {
  const PilotStats stats = FlyHeuristic(/*continuous=*/false, 100);
  EXPECT_GE(stats.mean_return, 200.0);
  EXPECT_GE(stats.landed_fraction, 0.85);
}

TEST(EnvFidelityTest, ContinuousHeuristicScoresLikeGymnasium) {
  const PilotStats stats = FlyHeuristic(/*continuous=*/true, 100);
  EXPECT_GE(stats.mean_return, 240.0);
  EXPECT_GE(stats.landed_fraction, 0.95);
}

}  // namespace
}  // namespace mll::core
