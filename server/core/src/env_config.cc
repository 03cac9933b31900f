#include "mll/core/env_config.h"

#include <cmath>

#include "absl/strings/str_cat.h"

namespace mll {
namespace {

// Ranges of shared/ENV_SPEC.md, "Options and defaults".
constexpr double kMinGravity = -12.0;  // Exclusive.
constexpr double kMaxGravity = 0.0;    // Exclusive.
constexpr double kMaxWindPower = 20.0;
constexpr double kMaxTurbulencePower = 2.0;

absl::Status OutOfRange(absl::string_view field, double value,
                        absl::string_view allowed) {
  return absl::InvalidArgumentError(absl::StrCat(
      field, " = ", value, " is out of range: allowed ", allowed));
}

absl::Status CheckClosed(absl::string_view field, double value, double low,
                         double high) {
  if (std::isfinite(value) && value >= low && value <= high) {
    return absl::OkStatus();
  }
  return OutOfRange(field, value, absl::StrCat("[", low, ", ", high, "]"));
}

absl::Status CheckFinite(absl::string_view field, double value) {
  if (std::isfinite(value)) return absl::OkStatus();
  return OutOfRange(field, value, "any finite value");
}

}  // namespace

absl::Status ValidateEnvConfig(const EnvConfig& config) {
  if (config.n_landers < kMinLanders || config.n_landers > kMaxLanders) {
    return OutOfRange("n_landers", config.n_landers,
                      absl::StrCat(kMinLanders, "..", kMaxLanders));
  }
  if (config.max_cycles < 1) {
    return OutOfRange("max_cycles", config.max_cycles, ">= 1");
  }
  if (!(std::isfinite(config.gravity) && config.gravity > kMinGravity &&
        config.gravity < kMaxGravity)) {
    return OutOfRange(
        "gravity", config.gravity,
        absl::StrCat("(", kMinGravity, ", ", kMaxGravity, "), exclusive"));
  }
  if (absl::Status s =
          CheckClosed("wind_power", config.wind_power, 0.0, kMaxWindPower);
      !s.ok()) {
    return s;
  }
  if (absl::Status s = CheckClosed("turbulence_power", config.turbulence_power,
                                   0.0, kMaxTurbulencePower);
      !s.ok()) {
    return s;
  }
  for (const auto& [field, value] :
       {std::pair<absl::string_view, double>{"damage_reward",
                                             config.damage_reward},
        {"successful_reward", config.successful_reward},
        {"terminate_reward", config.terminate_reward}}) {
    if (absl::Status s = CheckFinite(field, value); !s.ok()) return s;
  }
  if (config.render_mode != RenderMode::kNone &&
      config.render_mode != RenderMode::kRgbArray) {
    return OutOfRange("render_mode", static_cast<int>(config.render_mode),
                      "none (0) or rgb_array (1)");
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

}  // namespace mll
