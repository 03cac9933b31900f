// Command-line flags for every EnvConfig field, defined once so that every
// tool (mll_rollout, and any CLI that wants the same spelling) maps flags to an
// EnvConfig the same way. The flags' defaults are EnvConfig's defaults; ranges
// are checked by the core's ValidateEnvConfig, never here.
#ifndef MLL_CORE_TOOLS_CONFIG_FLAGS_H_
#define MLL_CORE_TOOLS_CONFIG_FLAGS_H_

#include <string>

#include "absl/flags/declare.h"
#include "absl/status/statusor.h"
#include "mll/core/env_config.h"

ABSL_DECLARE_FLAG(int, n_landers);
ABSL_DECLARE_FLAG(bool, continuous);
ABSL_DECLARE_FLAG(int, max_cycles);
ABSL_DECLARE_FLAG(double, gravity);
ABSL_DECLARE_FLAG(bool, enable_wind);
ABSL_DECLARE_FLAG(double, wind_power);
ABSL_DECLARE_FLAG(double, turbulence_power);
ABSL_DECLARE_FLAG(bool, remove_on_damage);
ABSL_DECLARE_FLAG(bool, terminate_on_damage);
ABSL_DECLARE_FLAG(bool, shared_reward);
ABSL_DECLARE_FLAG(double, damage_reward);
ABSL_DECLARE_FLAG(double, successful_reward);
ABSL_DECLARE_FLAG(double, terminate_reward);
ABSL_DECLARE_FLAG(std::string, render_mode);

namespace mll {

// "none" or "rgb_array" (RenderModeName's spellings); else INVALID_ARGUMENT
// naming render_mode and the value.
absl::StatusOr<RenderMode> ParseRenderMode(const std::string& name);

// The EnvConfig the flags describe, validated by ValidateEnvConfig:
// INVALID_ARGUMENT naming the first bad field, its value and the range.
absl::StatusOr<EnvConfig> EnvConfigFromFlags();

}  // namespace mll

#endif  // MLL_CORE_TOOLS_CONFIG_FLAGS_H_
