// Configuration of one Multi Lunar Lander environment.
//
// One struct with a comment per field (unit, range, default), validated once by
// ValidateEnvConfig() and by Env::Create(). The proto message mll.v1.EnvConfig
// mirrors it field by field and is converted in exactly one function of the
// service layer. Defaults are the paper's (shared/ENV_SPEC.md, "Options and
// defaults").
#ifndef MLL_CORE_ENV_CONFIG_H_
#define MLL_CORE_ENV_CONFIG_H_

#include "absl/status/status.h"
#include "absl/strings/string_view.h"

namespace mll {

// How frames are produced. Particles (engine exhaust) exist only when a render
// mode is set; they never change a lander's trajectory.
enum class RenderMode {
  kNone = 0,      // No frames; no particles.
  kRgbArray = 1,  // Frames on request as 600x400 RGB (or PNG).
};

struct EnvConfig {
  // Number of landers (agents `lander_0` .. `lander_{n-1}`). Range 1..32.
  int n_landers = 3;
  // false: Discrete(4) actions; true: Box(-1, 1, (2,)) actions.
  bool continuous = false;
  // Steps after which every active lander is truncated. Range >= 1.
  int max_cycles = 500;
  // Gravity along y in m/s^2. Range (-12, 0), exclusive.
  double gravity = -10.0;
  // Wind and turbulence on landers whose legs do not touch the ground.
  bool enable_wind = false;
  // Peak wind force in N. Range [0, 20].
  double wind_power = 15.0;
  // Peak turbulence torque in N*m. Range [0, 2].
  double turbulence_power = 1.5;
  // A damaged lander's bodies are destroyed (true) or stay as a wreck (false).
  bool remove_on_damage = true;
  // When any lander is damaged, every other active lander is terminated too.
  bool terminate_on_damage = true;
  // Each lander stepped receives the mean reward of the landers stepped.
  bool shared_reward = true;
  // Added to the reward of a damaged lander. Any finite value.
  double damage_reward = -100.0;
  // Added to the reward of a lander that landed. Any finite value.
  double successful_reward = 100.0;
  // Added to a lander terminated by damage (its own or, with
  // terminate_on_damage, another's). Any finite value.
  double terminate_reward = -100.0;
  // See RenderMode.
  RenderMode render_mode = RenderMode::kNone;
};

inline constexpr int kMinLanders = 1;
inline constexpr int kMaxLanders = 32;

// OK, or INVALID_ARGUMENT naming the first bad field, its value and the
// allowed range.
absl::Status ValidateEnvConfig(const EnvConfig& config);

// "none" or "rgb_array".
absl::string_view RenderModeName(RenderMode mode);

}  // namespace mll

#endif  // MLL_CORE_ENV_CONFIG_H_
