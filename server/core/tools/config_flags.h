// Command-line flags for every EnvConfig field, expanded from the one option
// list (MLL_ENV_OPTIONS), so that every tool (mll_rollout, mll_cli) maps flags
// to an EnvConfig the same way. Names, defaults and help come from the list;
// ranges are checked by the core's ValidateEnvConfig, never here.
#ifndef MLL_CORE_TOOLS_CONFIG_FLAGS_H_
#define MLL_CORE_TOOLS_CONFIG_FLAGS_H_

#include <string>

#include "absl/flags/declare.h"
#include "absl/status/statusor.h"
#include "mll/core/env_config.h"

#define MLL_DECLARE_OPTION_FLAG(type, name, default_value, range, help) \
  ABSL_DECLARE_FLAG(type, name);
MLL_ENV_OPTIONS(MLL_DECLARE_OPTION_FLAG)
#undef MLL_DECLARE_OPTION_FLAG
ABSL_DECLARE_FLAG(std::string, render_mode);

namespace mll::core {

// "none" or "rgb_array" (RenderModeName's spellings); else INVALID_ARGUMENT
// naming render_mode and the value.
absl::StatusOr<RenderMode> ParseRenderMode(const std::string& name);

// The EnvConfig the flags describe, validated by ValidateEnvConfig:
// INVALID_ARGUMENT naming the first bad field, its value and the range.
absl::StatusOr<EnvConfig> EnvConfigFromFlags();

}  // namespace mll::core

#endif  // MLL_CORE_TOOLS_CONFIG_FLAGS_H_
