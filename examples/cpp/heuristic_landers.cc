// Flies N landers with Gymnasium's heuristic pilot through a Multi Lunar
// Lander server, one episode, and prints how each lander ended.
//
//   mll_server --address=127.0.0.1:50051 &
//   heuristic_landers 127.0.0.1:50051 [n_landers=5] [seed=0] [continuous=0]
#include <cstdlib>
#include <iostream>
#include <string>
#include <vector>

#include "mll/client.h"
#include "mll/core/heuristic.h"

int main(int argc, char** argv) {
  if (argc < 2 || argc > 5) {
    std::cerr << "usage: heuristic_landers host:port [n_landers] [seed] "
                 "[continuous 0|1]"
              << std::endl;
    return 2;
  }
  const int n_landers = argc > 2 ? std::atoi(argv[2]) : 5;
  const uint64_t seed = argc > 3 ? std::strtoull(argv[3], nullptr, 10) : 0;
  const bool continuous = argc > 4 && std::string(argv[4]) == "1";

  absl::StatusOr<mll::client::Client> client =
      mll::client::Client::Create(argv[1]);
  if (!client.ok()) {
    std::cerr << client.status() << std::endl;
    return 1;
  }
  mll::client::RemoteEnvConfig config;
  config.n_landers = n_landers;  // The server checks the range.
  config.continuous = continuous;
  // Heuristic pilots all steer for the pad and may collide; let the others
  // fly on when one is damaged.
  config.terminate_on_damage = false;
  // The handle deletes the environment when it goes out of scope.
  absl::StatusOr<mll::client::RemoteEnv> env = client->CreateEnv(config);
  if (!env.ok()) {
    std::cerr << "CreateEnv: " << env.status() << std::endl;
    return 1;
  }
  absl::StatusOr<mll::client::StepData> data = env->Reset(seed);
  std::vector<int32_t> discrete(n_landers, 0);
  std::vector<float> throttle(2 * n_landers, 0.0f);
  int steps = 0;
  while (data.ok() && !data->episode_over) {
    for (int agent = 0; agent < n_landers; ++agent) {
      if (!data->active(agent)) continue;  // Done landers' actions are ignored.
      const mll::core::AgentAction action =
          mll::core::HeuristicAction(data->observation(agent), continuous);
      discrete[agent] = action.discrete;
      throttle[2 * agent] = action.continuous[0];
      throttle[2 * agent + 1] = action.continuous[1];
    }
    data = env->Step(continuous ? mll::client::Actions::Continuous(throttle)
                                : mll::client::Actions::Discrete(discrete));
    ++steps;
  }
  if (!data.ok()) {
    std::cerr << "step " << steps << ": " << data.status() << std::endl;
    return 1;
  }
  std::cout << env->name() << ": episode over after " << steps << " steps"
            << std::endl;
  for (int agent = 0; agent < n_landers; ++agent) {
    std::cout << "  " << env->info().possible_agents[agent] << " "
              << mll::client::LanderOutcomeName(data->outcomes[agent])
              << " after " << data->episode_lengths[agent] << " steps, return "
              << data->episode_returns[agent] << std::endl;
  }
  return 0;
}
