#include "mll/core/env_config.h"

#include "absl/strings/str_cat.h"

namespace mll::core {

absl::Status ValidateEnvConfig(const EnvConfig& config) {
  // The fields in list order: the error names the first bad one.
#define MLL_CHECK_OPTION(type, name, default_value, range, help)        \
  if (const double value = static_cast<double>(config.name);            \
      !(range).Contains(value)) {                                       \
    return absl::InvalidArgumentError(                                  \
        absl::StrCat(#name, " = ", value, " is out of range: allowed ", \
                     (range).Describe()));                              \
  }
  MLL_ENV_OPTIONS(MLL_CHECK_OPTION)
#undef MLL_CHECK_OPTION
  if (config.render_mode != RenderMode::kNone &&
      config.render_mode != RenderMode::kRgbArray) {
    return absl::InvalidArgumentError(
        absl::StrCat("render_mode = ", static_cast<int>(config.render_mode),
                     " is out of range: allowed none (0) or rgb_array (1)"));
  }
  return absl::OkStatus();
}

absl::string_view RenderModeName(RenderMode mode) {
  switch (mode) {
    case RenderMode::kNone:
      return "none";
    case RenderMode::kRgbArray:
      return "rgb_array";
  }
  return "unknown";
}

}  // namespace mll::core
