#include "mll/core/env_config.h"

#include <cmath>

#include "absl/strings/str_cat.h"

namespace mll::core {

bool OptionRange::Contains(double value) const {
  switch (kind_) {
    case Kind::kAny:
      return true;
    case Kind::kIntegers:
      return value >= low_ && value <= high_;
    case Kind::kAtLeast:
      return value >= low_;
    case Kind::kClosed:
      return std::isfinite(value) && value >= low_ && value <= high_;
    case Kind::kOpen:
      return std::isfinite(value) && value > low_ && value < high_;
    case Kind::kFinite:
      return std::isfinite(value);
  }
  return false;
}

std::string OptionRange::Describe() const {
  switch (kind_) {
    case Kind::kAny:
      return "any value";
    case Kind::kIntegers:
      return absl::StrCat(low_, "..", high_);
    case Kind::kAtLeast:
      return absl::StrCat(">= ", low_);
    case Kind::kClosed:
      return absl::StrCat("[", low_, ", ", high_, "]");
    case Kind::kOpen:
      return absl::StrCat("(", low_, ", ", high_, "), exclusive");
    case Kind::kFinite:
      return "any finite value";
  }
  return "";
}

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
