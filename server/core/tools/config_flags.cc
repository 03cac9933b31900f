#include "config_flags.h"

#include <string>

#include "absl/flags/flag.h"
#include "absl/status/status.h"
#include "absl/strings/str_cat.h"

namespace {
// The defaults come from EnvConfig itself, so they cannot drift from the core.
constexpr mll::core::EnvConfig kDefaults{};
}  // namespace

#define MLL_DEFINE_OPTION_FLAG(type, name, default_value, range, help) \
  ABSL_FLAG(type, name, kDefaults.name, help);
MLL_ENV_OPTIONS(MLL_DEFINE_OPTION_FLAG)
#undef MLL_DEFINE_OPTION_FLAG
ABSL_FLAG(std::string, render_mode,
          std::string(mll::core::RenderModeName(kDefaults.render_mode)),
          "none or rgb_array.");

namespace mll::core {

absl::StatusOr<RenderMode> ParseRenderMode(const std::string& name) {
  for (RenderMode mode : {RenderMode::kNone, RenderMode::kRgbArray}) {
    if (name == RenderModeName(mode)) return mode;
  }
  return absl::InvalidArgumentError(
      absl::StrCat("render_mode is \"", name, "\"; allowed: \"",
                   RenderModeName(RenderMode::kNone), "\", \"",
                   RenderModeName(RenderMode::kRgbArray), "\""));
}

absl::StatusOr<EnvConfig> EnvConfigFromFlags() {
  EnvConfig config;
#define MLL_READ_OPTION_FLAG(type, name, default_value, range, help) \
  config.name = absl::GetFlag(FLAGS_##name);
  MLL_ENV_OPTIONS(MLL_READ_OPTION_FLAG)
#undef MLL_READ_OPTION_FLAG
  absl::StatusOr<RenderMode> mode =
      ParseRenderMode(absl::GetFlag(FLAGS_render_mode));
  if (!mode.ok()) return mode.status();
  config.render_mode = *mode;
  absl::Status status = ValidateEnvConfig(config);
  if (!status.ok()) return status;
  return config;
}

}  // namespace mll::core
