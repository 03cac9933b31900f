// What every layer shares about one Multi Lunar Lander environment, beside
// the wire contract (proto/mll/v1/multi_lunar_lander.proto): its options and
// the sizes of an agent's observation and action. The simulation core
// (server/core), the service (server/service) and the C++ client
// (client_cpp) all include this header; none copies a value from it.
//
// Every option is defined once, in MLL_ENV_OPTIONS below: its C++ type, name,
// default, allowed range and help text. Everything else that lists the
// options expands that list: the core's EnvConfig fields and defaults and
// ValidateEnvConfig (mll/core/env_config.h), the tools' command-line flags
// (config_flags.cc), the service's proto <-> core conversion (convert.cc),
// the C++ client's RemoteEnvConfig (mll/client_types.h) and wire encoding
// (wire.cc), and the client's core bridge (core_bridge.cc). The wire's
// mll.v1.EnvConfig and the Python client follow the proto; tests fail when
// the proto, this list or a client drift apart (docs/design.md, "Adding an
// option").
#ifndef MLL_ENV_SPEC_H_
#define MLL_ENV_SPEC_H_

#include <cmath>
#include <string>

#include "absl/strings/str_cat.h"

namespace mll {

// Floats in one agent's observation: its position, velocity, angle, angular
// velocity and leg contacts, then its two nearest neighbours' relative
// positions (docs/environment.md, "Observation space").
inline constexpr int kObservationSize = 12;
// Discrete actions: noop, left engine, main engine, right engine.
inline constexpr int kDiscreteActionCount = 4;
// Floats in one continuous action: main, lateral.
inline constexpr int kContinuousActionSize = 2;

// Landers (agents) an environment may have: the n_landers option's range.
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

  bool Contains(double value) const {
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

  // "1..32", ">= 1", "[0, 20]", "(-12, 0), exclusive", "any finite value".
  std::string Describe() const {
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

 private:
  enum class Kind { kAny, kIntegers, kAtLeast, kClosed, kOpen, kFinite };
  constexpr OptionRange(Kind kind, double low, double high)
      : kind_(kind), low_(low), high_(high) {}
  Kind kind_;
  double low_;
  double high_;
};

}  // namespace mll

// X(type, name, default, range, help): every option of an environment, in
// the order of mll.v1.EnvConfig's fields. `help` says what the option does,
// its unit and (in words) its range; `range` is what the core's
// ValidateEnvConfig checks. render_mode is the one option that is not a
// number or a flag (the core's RenderMode, the proto's RenderMode); the
// service's auto_reset is the service's, not the simulation's.
#define MLL_ENV_OPTIONS(X)                                                \
  X(int, n_landers, 3,                                                    \
    ::mll::OptionRange::Integers(::mll::kMinLanders, ::mll::kMaxLanders), \
    "Number of landers (agents lander_0..lander_{n-1}), 1..32.")          \
  X(bool, continuous, false, ::mll::OptionRange::Any(),                   \
    "Continuous Box(-1, 1, (2,)) actions instead of Discrete(4).")        \
  X(int, max_cycles, 500, ::mll::OptionRange::AtLeast(1),                 \
    "Steps after which every active lander is truncated, >= 1.")          \
  X(double, gravity, -10.0, ::mll::OptionRange::Open(-12.0, 0.0),         \
    "Gravity along y in m/s^2, in (-12, 0).")                             \
  X(bool, enable_wind, false, ::mll::OptionRange::Any(),                  \
    "Wind and turbulence on landers whose legs do not touch the ground.") \
  X(double, wind_power, 15.0, ::mll::OptionRange::Closed(0.0, 20.0),      \
    "Peak wind force in N, [0, 20].")                                     \
  X(double, turbulence_power, 1.5, ::mll::OptionRange::Closed(0.0, 2.0),  \
    "Peak turbulence torque in N*m, [0, 2].")                             \
  X(bool, remove_on_damage, true, ::mll::OptionRange::Any(),              \
    "Destroy a damaged lander's bodies (else it stays as a wreck).")      \
  X(bool, terminate_on_damage, true, ::mll::OptionRange::Any(),           \
    "Terminate every other active lander when one is damaged.")           \
  X(bool, shared_reward, true, ::mll::OptionRange::Any(),                 \
    "Each stepped lander receives the mean reward of those stepped.")     \
  X(double, damage_reward, -100.0, ::mll::OptionRange::Finite(),          \
    "Added to a damaged lander's reward, any finite value.")              \
  X(double, successful_reward, 100.0, ::mll::OptionRange::Finite(),       \
    "Added to a landed lander's reward, any finite value.")               \
  X(double, terminate_reward, -100.0, ::mll::OptionRange::Finite(),       \
    "Added to a lander terminated by damage (its own or, with "           \
    "terminate_on_damage, another's), any finite value.")

#endif  // MLL_ENV_SPEC_H_
