// What programs that link both the client and the core (mll_cli, the
// examples, the tests) share: the core's EnvConfig as a RemoteEnvConfig, and a
// pilot choosing every active lander's action from a remote StepData with the
// core's heuristic (or a seeded random policy).
#ifndef MLL_CLIENT_TOOLS_CORE_BRIDGE_H_
#define MLL_CLIENT_TOOLS_CORE_BRIDGE_H_

#include <cstdint>
#include <random>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "mll/client.h"
#include "mll/core/env.h"
#include "mll/core/env_config.h"

namespace mll::client {

// Every field set, so the server builds exactly `config`.
RemoteEnvConfig RemoteConfigFrom(const core::EnvConfig& config);

enum class PilotPolicy { kHeuristic, kRandom };

// "heuristic" or "random"; else INVALID_ARGUMENT naming policy and the value.
absl::StatusOr<PilotPolicy> ParsePilotPolicy(absl::string_view name);

class RemotePilot {
 public:
  // `seed` seeds the random policy's own generator, so runs repeat.
  RemotePilot(PilotPolicy policy, int n_landers, bool continuous,
              uint64_t seed);

  // Actions for the agents still active after `last` (a reset or a step);
  // the others get 0, which the server ignores. The view stays valid until
  // the next call.
  Actions Act(const StepData& last);

 private:
  core::AgentAction RandomAction();

  PilotPolicy policy_;
  bool continuous_;
  std::mt19937_64 rng_;
  std::vector<int32_t> discrete_;
  std::vector<float> continuous_actions_;
};

}  // namespace mll::client

#endif  // MLL_CLIENT_TOOLS_CORE_BRIDGE_H_
