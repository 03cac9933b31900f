#include "core_bridge.h"

#include <algorithm>
#include <cmath>

#include "absl/strings/str_cat.h"
#include "mll/core/heuristic.h"

namespace mll::client {

RemoteEnvConfig RemoteConfigFrom(const core::EnvConfig& config) {
  RemoteEnvConfig remote;
#define MLL_COPY_OPTION(type, name, default_value, range, help) \
  remote.name = config.name;
  MLL_ENV_OPTIONS(MLL_COPY_OPTION)
#undef MLL_COPY_OPTION
  remote.render_rgb_array = config.render_mode == core::RenderMode::kRgbArray;
  return remote;
}

absl::StatusOr<PilotPolicy> ParsePilotPolicy(absl::string_view name) {
  if (name == "heuristic") return PilotPolicy::kHeuristic;
  if (name == "random") return PilotPolicy::kRandom;
  return absl::InvalidArgumentError(
      absl::StrCat("policy is \"", name,
                   "\"; allowed: \"heuristic\", \"random\", \"trained\""));
}

RemotePilot::RemotePilot(PilotPolicy policy, int n_landers, bool continuous,
                         uint64_t seed)
    : policy_(policy),
      continuous_(continuous),
      rng_(seed),
      discrete_(n_landers, 0),
      continuous_actions_(core::kContinuousActionSize * n_landers, 0.0f) {}

Actions RemotePilot::Act(const StepData& last) {
  std::fill(discrete_.begin(), discrete_.end(), 0);
  std::fill(continuous_actions_.begin(), continuous_actions_.end(), 0.0f);
  const int n = std::min<int>(last.n_landers, discrete_.size());
  for (int agent = 0; agent < n; ++agent) {
    if (!last.stepped[agent] || !last.active(agent)) continue;
    const core::AgentAction action =
        policy_ == PilotPolicy::kHeuristic
            ? core::HeuristicAction(last.observation(agent), continuous_)
            : RandomAction();
    discrete_[agent] = action.discrete;
    std::copy(
        action.continuous.begin(), action.continuous.end(),
        continuous_actions_.begin() + core::kContinuousActionSize * agent);
  }
  return continuous_ ? Actions::Continuous(continuous_actions_)
                     : Actions::Discrete(discrete_);
}

// Raw 64-bit draws, not std distributions (whose algorithms differ between
// standard libraries), so a seed means the same actions everywhere.
core::AgentAction RemotePilot::RandomAction() {
  core::AgentAction action;
  if (!continuous_) {
    action.discrete = static_cast<int32_t>(rng_() % core::kDiscreteActionCount);
    return action;
  }
  for (float& value : action.continuous) {
    value = static_cast<float>(
        std::ldexp(static_cast<double>(rng_() >> 11), -52) - 1.0);
  }
  return action;
}

}  // namespace mll::client
