#include "config_flags.h"

#include <string>

#include "absl/flags/flag.h"
#include "absl/status/status.h"
#include "absl/strings/str_cat.h"

namespace {
// The defaults come from EnvConfig itself, so they cannot drift from the core.
constexpr mll::EnvConfig kDefaults{};
}  // namespace

ABSL_FLAG(int, n_landers, kDefaults.n_landers,
          "Number of landers (agents lander_0..lander_{n-1}), 1..32.");
ABSL_FLAG(bool, continuous, kDefaults.continuous,
          "Continuous Box(-1, 1, (2,)) actions instead of Discrete(4).");
ABSL_FLAG(int, max_cycles, kDefaults.max_cycles,
          "Steps after which every active lander is truncated, >= 1.");
ABSL_FLAG(double, gravity, kDefaults.gravity,
          "Gravity along y in m/s^2, in (-12, 0).");
ABSL_FLAG(bool, enable_wind, kDefaults.enable_wind,
          "Wind and turbulence on landers in the air.");
ABSL_FLAG(double, wind_power, kDefaults.wind_power,
          "Peak wind force in N, [0, 20].");
ABSL_FLAG(double, turbulence_power, kDefaults.turbulence_power,
          "Peak turbulence torque in N*m, [0, 2].");
ABSL_FLAG(bool, remove_on_damage, kDefaults.remove_on_damage,
          "Destroy a damaged lander's bodies (else it stays as a wreck).");
ABSL_FLAG(bool, terminate_on_damage, kDefaults.terminate_on_damage,
          "Terminate every other active lander when one is damaged.");
ABSL_FLAG(bool, shared_reward, kDefaults.shared_reward,
          "Each stepped lander receives the mean reward of those stepped.");
ABSL_FLAG(double, damage_reward, kDefaults.damage_reward,
          "Added to a damaged lander's reward, finite.");
ABSL_FLAG(double, successful_reward, kDefaults.successful_reward,
          "Added to a landed lander's reward, finite.");
ABSL_FLAG(double, terminate_reward, kDefaults.terminate_reward,
          "Added to a lander terminated by damage, finite.");
ABSL_FLAG(std::string, render_mode,
          std::string(mll::RenderModeName(kDefaults.render_mode)),
          "none or rgb_array.");

namespace mll {

absl::StatusOr<RenderMode> ParseRenderMode(const std::string& name) {
  for (RenderMode mode : {RenderMode::kNone, RenderMode::kRgbArray}) {
    if (name == RenderModeName(mode)) return mode;
  }
  return absl::InvalidArgumentError(absl::StrCat(
      "render_mode is \"", name, "\"; allowed: \"",
      RenderModeName(RenderMode::kNone), "\", \"",
      RenderModeName(RenderMode::kRgbArray), "\""));
}

absl::StatusOr<EnvConfig> EnvConfigFromFlags() {
  EnvConfig config;
  config.n_landers = absl::GetFlag(FLAGS_n_landers);
  config.continuous = absl::GetFlag(FLAGS_continuous);
  config.max_cycles = absl::GetFlag(FLAGS_max_cycles);
  config.gravity = absl::GetFlag(FLAGS_gravity);
  config.enable_wind = absl::GetFlag(FLAGS_enable_wind);
  config.wind_power = absl::GetFlag(FLAGS_wind_power);
  config.turbulence_power = absl::GetFlag(FLAGS_turbulence_power);
  config.remove_on_damage = absl::GetFlag(FLAGS_remove_on_damage);
  config.terminate_on_damage = absl::GetFlag(FLAGS_terminate_on_damage);
  config.shared_reward = absl::GetFlag(FLAGS_shared_reward);
  config.damage_reward = absl::GetFlag(FLAGS_damage_reward);
  config.successful_reward = absl::GetFlag(FLAGS_successful_reward);
  config.terminate_reward = absl::GetFlag(FLAGS_terminate_reward);
  absl::StatusOr<RenderMode> mode =
      ParseRenderMode(absl::GetFlag(FLAGS_render_mode));
  if (!mode.ok()) return mode.status();
  config.render_mode = *mode;
  absl::Status status = ValidateEnvConfig(config);
  if (!status.ok()) return status;
  return config;
}

}  // namespace mll
