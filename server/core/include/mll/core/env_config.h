// Configuration of one Multi Lunar Lander environment.
//
// Every option is defined once, in MLL_ENV_OPTIONS below: its C++ type, name,
// default, allowed range and help text. Everything else that lists the
// options expands that list: EnvConfig's fields and defaults,
// ValidateEnvConfig, the tools' command-line flags (config_flags.cc), the
// proto <-> core conversion of the service (convert.cc) and the C++ client
// bridge (core_bridge.cc). The wire's mll.v1.EnvConfig and the clients follow
// the proto; tests fail when the proto, this list or a client drift apart
// (docs/design.md, "Adding an option").
#ifndef MLL_CORE_ENV_CONFIG_H_
#define MLL_CORE_ENV_CONFIG_H_

#include <string>

#include "absl/status/status.h"
#include "absl/strings/string_view.h"

namespace mll::core {

inline constexpr int kMinLanders = 1;
inline constexpr int kMaxLanders = 32;

// The values an option allows; its check and its wording in errors.
class OptionRange {
 public:
  // Any value of the type (bool options).
  static constexpr OptionRange Any() { return {Kind::kAny, 0, 0}; }
  // Integers low..high, both included.
  static constexpr OptionRange Integers(int low, int high) {
    return {Kind::kIntegers, static_cast<double>(low),
            static_cast<double>(high)};
  }
  // >= low.
  static constexpr OptionRange AtLeast(double low) {
    return {Kind::kAtLeast, low, 0};
  }
  // Finite, in [low, high].
  static constexpr OptionRange Closed(double low, double high) {
    return {Kind::kClosed, low, high};
  }
  // Finite, in (low, high).
  static constexpr OptionRange Open(double low, double high) {
    return {Kind::kOpen, low, high};
  }
  // Any finite value.
  static constexpr OptionRange Finite() { return {Kind::kFinite, 0, 0}; }

  bool Contains(double value) const;
  // "1..32", ">= 1", "[0, 20]", "(-12, 0), exclusive", "any finite value".
  std::string Describe() const;

 private:
  enum class Kind { kAny, kIntegers, kAtLeast, kClosed, kOpen, kFinite };
  constexpr OptionRange(Kind kind, double low, double high)
      : kind_(kind), low_(low), high_(high) {}
  Kind kind_;
  double low_;
  double high_;
};

// X(type, name, default, range, help): every option of an environment, in
// the order of mll.v1.EnvConfig's fields. `help` says what the option does,
// its unit and (in words) its range; `range` is what ValidateEnvConfig
// checks. render_mode (below) is the one option that is not a number or a
// flag; the service's auto_reset is the service's, not the simulation's.
#define MLL_ENV_OPTIONS(X)                                                     \
  X(int, n_landers, 3,                                                         \
    ::mll::core::OptionRange::Integers(::mll::core::kMinLanders,               \
                                       ::mll::core::kMaxLanders),              \
    "Number of landers (agents lander_0..lander_{n-1}), 1..32.")               \
  X(bool, continuous, false, ::mll::core::OptionRange::Any(),                  \
    "Continuous Box(-1, 1, (2,)) actions instead of Discrete(4).")             \
  X(int, max_cycles, 500, ::mll::core::OptionRange::AtLeast(1),                \
    "Steps after which every active lander is truncated, >= 1.")               \
  X(double, gravity, -10.0, ::mll::core::OptionRange::Open(-12.0, 0.0),        \
    "Gravity along y in m/s^2, in (-12, 0).")                                  \
  X(bool, enable_wind, false, ::mll::core::OptionRange::Any(),                 \
    "Wind and turbulence on landers whose legs do not touch the ground.")      \
  X(double, wind_power, 15.0, ::mll::core::OptionRange::Closed(0.0, 20.0),     \
    "Peak wind force in N, [0, 20].")                                          \
  X(double, turbulence_power, 1.5, ::mll::core::OptionRange::Closed(0.0, 2.0), \
    "Peak turbulence torque in N*m, [0, 2].")                                  \
  X(bool, remove_on_damage, true, ::mll::core::OptionRange::Any(),             \
    "Destroy a damaged lander's bodies (else it stays as a wreck).")           \
  X(bool, terminate_on_damage, true, ::mll::core::OptionRange::Any(),          \
    "Terminate every other active lander when one is damaged.")                \
  X(bool, shared_reward, true, ::mll::core::OptionRange::Any(),                \
    "Each stepped lander receives the mean reward of those stepped.")          \
  X(double, damage_reward, -100.0, ::mll::core::OptionRange::Finite(),         \
    "Added to a damaged lander's reward, any finite value.")                   \
  X(double, successful_reward, 100.0, ::mll::core::OptionRange::Finite(),      \
    "Added to a landed lander's reward, any finite value.")                    \
  X(double, terminate_reward, -100.0, ::mll::core::OptionRange::Finite(),      \
    "Added to a lander terminated by damage (its own or, with "                \
    "terminate_on_damage, another's), any finite value.")

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
