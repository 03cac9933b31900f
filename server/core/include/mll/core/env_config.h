// Configuration of one Multi Lunar Lander environment.
//
// Every option is defined once, in MLL_ENV_OPTIONS (mll/env_spec.h, beside
// the wire contract): its C++ type, name, default, allowed range and help
// text. EnvConfig's fields and defaults and ValidateEnvConfig expand that
// list here.
#ifndef MLL_CORE_ENV_CONFIG_H_
#define MLL_CORE_ENV_CONFIG_H_

#include "absl/status/status.h"
#include "absl/strings/string_view.h"
#include "mll/env_spec.h"

namespace mll::core {

// The options and their ranges are defined beside the wire contract
// (mll/env_spec.h), shared with the service and the C++ client; the core
// names them as its own.
using ::mll::kMaxLanders;
using ::mll::kMinLanders;
using ::mll::OptionRange;

// How frames are produced. Particles (engine exhaust) exist only when a render
// mode is set; they never change a lander's trajectory.
enum class RenderMode {
  kNone = 0,      // No frames; no particles.
  kRgbArray = 1,  // Frames on request as 600x400 RGB (or PNG).
};

struct EnvConfig {
#define MLL_ENV_OPTION_FIELD(type, name, default_value, range, help) \
  type name = default_value;
  MLL_ENV_OPTIONS(MLL_ENV_OPTION_FIELD)
#undef MLL_ENV_OPTION_FIELD
  // See RenderMode.
  RenderMode render_mode = RenderMode::kNone;
};

// OK, or INVALID_ARGUMENT naming the first bad field, its value and the
// allowed range.
absl::Status ValidateEnvConfig(const EnvConfig& config);

// "none" or "rgb_array".
absl::string_view RenderModeName(RenderMode mode);

}  // namespace mll::core

#endif  // MLL_CORE_ENV_CONFIG_H_
