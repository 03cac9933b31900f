// Flies one episode on the server at argv[1] with the installed mll::client:
// every lander fires its main engine when falling fast; then steps 8 envs
// together with the batched API (mll::client::VectorEnv) over shared memory.
// Exit 0 when both worked.
#include <iostream>
#include <vector>

#include "mll/client.h"
#include "mll/vector_env.h"

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

  mll::client::ClientOptions options;
  options.session_transport = mll::client::SessionTransport::kSharedMemory;
  absl::StatusOr<mll::client::Client> local =
      mll::client::Client::Create(argv[1], options);
  absl::StatusOr<mll::client::VectorEnv> envs =
      local.ok() ? mll::client::VectorEnv::Create(*local, 8, config)
                 : absl::StatusOr<mll::client::VectorEnv>(local.status());
  absl::Status status = envs.ok() ? envs->Reset(uint64_t{2}) : envs.status();
  std::vector<int32_t> batch(8 * 2);
  int transitions = 0;
  for (int step = 0; status.ok() && step < 50; ++step) {
    const absl::Span<const float> observations = envs->observations();
    for (size_t row = 0; row < batch.size(); ++row) {
      batch[row] = observations[row * 12 + 3] < -0.2f ? 2 : 0;
    }
    status = envs->Step(batch);
    for (uint8_t active : envs->active()) transitions += active;
  }
  if (!status.ok()) {
    std::cerr << status << std::endl;
    return 1;
  }
  std::cout << "8 envs over " << envs->transport() << ": " << transitions
            << " transitions" << std::endl;
  return envs->transport() == "shared_memory" && transitions > 0 ? 0 : 1;
}
