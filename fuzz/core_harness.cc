// RunCoreInput: arbitrary configs and action sequences through mll::core::Env,
// mll::core::AecEnv and the renderer.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/types/span.h"
#include "harness.h"
#include "mll/core/aec_env.h"
#include "mll/core/env.h"
#include "mll/core/env_config.h"
#include "mll/core/renderer.h"

namespace mll::fuzz {
namespace {

// Bounds the work of one input: 32 landers step in about 0.5 ms.
constexpr int kMaxSteps = 600;
// Rendering costs ~1 ms and PNG encoding ~8 ms: a few per input.
constexpr int kMaxRenders = 3;

[[noreturn]] void Fail(const std::string& what) {
  HarnessFailure("core harness", what);
}

// Consumes the input front to back; zeros once it is exhausted.
class ByteReader {
 public:
  ByteReader(const uint8_t* data, size_t size) : data_(data), size_(size) {}
  bool empty() const { return offset_ >= size_; }

  template <typename T>
  T Take() {
    T value{};
    const size_t n = std::min(sizeof(T), size_ - std::min(offset_, size_));
    std::memcpy(&value, data_ + offset_, n);
    offset_ += sizeof(T);
    return value;
  }

  // A double for a field with range [low, high]: the default, a value in
  // range, one just outside or at an edge, or raw bits (NaN, inf, huge).
  double Real(double fallback, double low, double high) {
    switch (Take<uint8_t>() % 4) {
      case 0:
        return fallback;
      case 1:
        return low + (high - low) * (Take<uint16_t>() / 65535.0);
      case 2: {
        const double edges[] = {low,
                                high,
                                std::nextafter(low, -HUGE_VAL),
                                std::nextafter(high, HUGE_VAL),
                                0.0,
                                std::numeric_limits<double>::quiet_NaN(),
                                HUGE_VAL,
                                -HUGE_VAL};
        return edges[Take<uint8_t>() % 8];
      }
      default:
        return Take<double>();
    }
  }

  // An action value: mostly in [-1.5, 1.5], sometimes raw float bits.
  float ActionValue() {
    const uint8_t selector = Take<uint8_t>();
    if (selector < 224) return (selector / 223.0f) * 3.0f - 1.5f;
    return Take<float>();
  }

 private:
  const uint8_t* data_;
  size_t size_;
  size_t offset_ = 0;
};

core::EnvConfig TakeConfig(ByteReader& in) {
  core::EnvConfig config;
  const uint8_t landers = in.Take<uint8_t>();
  config.n_landers = landers < 240 ? landers % 34 : in.Take<int32_t>();
  const uint8_t flags = in.Take<uint8_t>();
  config.continuous = flags & 1;
  config.enable_wind = flags & 2;
  config.remove_on_damage = flags & 4;
  config.terminate_on_damage = flags & 8;
  config.shared_reward = flags & 16;
  config.render_mode =
      (flags & 32) ? core::RenderMode::kRgbArray : core::RenderMode::kNone;
  const uint8_t cycles = in.Take<uint8_t>();
  config.max_cycles = cycles < 250 ? cycles : in.Take<int32_t>();
  config.gravity = in.Real(-10.0, -12.0, 0.0);
  config.wind_power = in.Real(15.0, 0.0, 20.0);
  config.turbulence_power = in.Real(1.5, 0.0, 2.0);
  config.damage_reward = in.Real(-100.0, -1e6, 1e6);
  config.successful_reward = in.Real(100.0, -1e6, 1e6);
  config.terminate_reward = in.Real(-100.0, -1e6, 1e6);
  return config;
}

core::AgentAction TakeAgentAction(ByteReader& in, bool continuous) {
  core::AgentAction action;
  if (continuous) {
    action.continuous = {in.ActionValue(), in.ActionValue()};
  } else {
    const uint8_t selector = in.Take<uint8_t>();
    action.discrete = selector < 240 ? selector % 5 : in.Take<int32_t>();
  }
  return action;
}

void CheckFinite(absl::Span<const float> values, const char* what) {
  for (float value : values) {
    if (!std::isfinite(value)) Fail(absl::StrCat(what, " has ", value));
  }
}

void CheckStepCode(const absl::Status& status, const char* call) {
  if (status.ok() || status.code() == absl::StatusCode::kInvalidArgument ||
      status.code() == absl::StatusCode::kFailedPrecondition) {
    return;
  }
  Fail(absl::StrCat(call, ": unexpected status ", status.ToString()));
}

}  // namespace

void RunCoreInput(const uint8_t* data, size_t size) {
  ByteReader in(data, size);
  const core::EnvConfig config = TakeConfig(in);
  absl::StatusOr<std::unique_ptr<core::Env>> created =
      core::Env::Create(config);
  const absl::Status valid = core::ValidateEnvConfig(config);
  if (created.ok() != valid.ok()) {
    Fail(absl::StrCat("Env::Create and ValidateEnvConfig disagree: ",
                      created.status().ToString(), " vs ", valid.ToString()));
  }
  if (!created.ok()) {
    if (created.status().code() != absl::StatusCode::kInvalidArgument) {
      Fail(absl::StrCat("Env::Create: ", created.status().ToString()));
    }
    return;
  }
  core::Env& env = **created;
  core::AecEnv aec(&env);
  const int n = env.n_landers();
  core::StepResult result;
  // The service never mixes the two step APIs within an episode; neither do
  // we (see mll::service::StepMode).
  enum { kUnset, kParallel, kAec } mode = kUnset;
  int renders = 0;
  std::vector<int32_t> discrete(n);
  std::vector<float> continuous(2 * n);

  for (int step = 0; step < kMaxSteps && !in.empty(); ++step) {
    const uint8_t op = in.Take<uint8_t>() % 16;
    if (op == 0) {
      const uint8_t seeded = in.Take<uint8_t>();
      std::optional<uint64_t> seed;
      if (seeded & 1) seed = in.Take<uint64_t>();
      aec.Reset(seed);
      mode = kUnset;
      for (int i = 0; i < n; ++i) CheckFinite(env.observation(i), "reset");
    } else if (op == 1) {
      if (config.render_mode == core::RenderMode::kNone ||
          renders >= kMaxRenders) {
        continue;
      }
      ++renders;
      absl::StatusOr<core::Frame> frame = core::RenderEnv(env);
      CheckStepCode(frame.status(), "RenderEnv");
      if (frame.ok() && renders == 1) {  // PNG once: it is the slow part.
        absl::StatusOr<std::string> png = core::EncodePng(*frame);
        if (!png.ok()) Fail(png.status().ToString());
      }
    } else if (op < 10 && mode != kAec) {
      const int cycles = env.cycles();
      for (int i = 0; i < n; ++i) {
        const core::AgentAction action = TakeAgentAction(in, config.continuous);
        discrete[i] = action.discrete;
        continuous[2 * i] = action.continuous[0];
        continuous[2 * i + 1] = action.continuous[1];
      }
      core::ActionsView view;
      if (config.continuous) {
        view.continuous = continuous;
      } else {
        view.discrete = discrete;
      }
      const absl::Status status = env.Step(view, &result);
      CheckStepCode(status, "Env::Step");
      if (!status.ok()) {
        if (env.cycles() != cycles) Fail("a failed Env::Step moved the env");
        continue;
      }
      mode = kParallel;
      CheckFinite(result.observations, "Env::Step observations");
      CheckFinite(result.rewards, "Env::Step rewards");
    } else if (op >= 10 && mode != kParallel) {
      std::optional<core::AgentAction> action;
      if (in.Take<uint8_t>() < 230) {
        action = TakeAgentAction(in, config.continuous);
      }
      const absl::Status status = aec.Step(action);
      CheckStepCode(status, "AecEnv::Step");
      if (!status.ok()) continue;
      mode = kAec;
      for (int i = 0; i < n; ++i) {
        CheckFinite(aec.observe(i), "AecEnv::observe");
        if (!std::isfinite(aec.cumulative_reward(i))) {
          Fail("AecEnv cumulative reward is not finite");
        }
      }
    }
  }
}

}  // namespace mll::fuzz
