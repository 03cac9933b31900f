// Flies one episode on the server at argv[1] with the installed mll::client:
// every lander fires its main engine when falling fast. Exit 0 when the
// episode ends normally.
#include <iostream>
#include <vector>

#include "mll/client.h"

int main(int argc, char** argv) {
  if (argc != 2) {
    std::cerr << "usage: consumer host:port" << std::endl;
    return 2;
  }
  absl::StatusOr<mll::client::Client> client =
      mll::client::Client::Create(argv[1]);
  if (!client.ok()) {
    std::cerr << client.status() << std::endl;
    return 1;
  }
  mll::client::RemoteEnvConfig config;
  config.n_landers = 2;
  config.max_cycles = 200;
  absl::StatusOr<mll::client::RemoteEnv> env = client->CreateEnv(config);
  if (!env.ok()) {
    std::cerr << env.status() << std::endl;
    return 1;
  }
  absl::StatusOr<mll::client::StepData> data = env->Reset(1);
  int steps = 0;
  std::vector<int32_t> actions(env->n_landers());
  while (data.ok() && !data->episode_over) {
    for (int agent = 0; agent < env->n_landers(); ++agent) {
      actions[agent] = data->observation(agent)[3] < -0.2f ? 2 : 0;
    }
    data = env->Step(mll::client::Actions::Discrete(actions));
    ++steps;
  }
  if (!data.ok()) {
    std::cerr << data.status() << std::endl;
    return 1;
  }
  std::cout << env->name() << " ended after " << steps << " steps:";
  for (mll::client::LanderOutcome outcome : data->outcomes) {
    std::cout << " " << mll::client::LanderOutcomeName(outcome);
  }
  std::cout << std::endl;
  return 0;
}
