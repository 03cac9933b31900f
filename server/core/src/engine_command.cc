#include "engine_command.h"

#include <algorithm>
#include <cmath>

#include "absl/strings/str_cat.h"

namespace mll::core {
namespace internal {

EngineCommand DecodeDiscrete(int32_t action) {
  EngineCommand command;
  if (action == 2) command.main_power = 1.0;
  if (action == 1 || action == 3) {
    command.side_power = 1.0;
    command.side_direction = action - 2;
  }
  return command;
}

EngineCommand DecodeContinuous(float main, float lateral) {
  // Gymnasium clips in float32, then computes in float64.
  const double a0 = std::clamp(main, -1.0f, 1.0f);
  const double a1 = std::clamp(lateral, -1.0f, 1.0f);
  EngineCommand command;
  if (a0 > 0.0) command.main_power = (std::clamp(a0, 0.0, 1.0) + 1.0) * 0.5;
  if (std::abs(a1) > 0.5) {
    command.side_direction = a1 > 0.0 ? 1 : -1;
    command.side_power = std::clamp(std::abs(a1), 0.5, 1.0);
  }
  return command;
}

absl::Status ValidateDiscreteAction(int agent, int32_t action) {
  if (action >= 0 && action < kDiscreteActionCount) return absl::OkStatus();
  return absl::InvalidArgumentError(
      absl::StrCat("action of ", AgentName(agent), " = ", action,
                   " is out of range: allowed 0..", kDiscreteActionCount - 1));
}

absl::Status ValidateContinuousAction(int agent, float main, float lateral) {
  const float values[kContinuousActionSize] = {main, lateral};
  const char* names[kContinuousActionSize] = {"main", "lateral"};
  for (int i = 0; i < kContinuousActionSize; ++i) {
    if (!std::isfinite(values[i])) {
      return absl::InvalidArgumentError(
          absl::StrCat("action of ", AgentName(agent), " [", i, "] (", names[i],
                       ") = ", values[i],
                       " is not finite: allowed any finite value, clipped to "
                       "[-1, 1]"));
    }
  }
  return absl::OkStatus();
}

absl::Status ValidateAgentAction(bool continuous, int agent,
                                 const AgentAction& action) {
  return continuous ? ValidateContinuousAction(agent, action.continuous[0],
                                               action.continuous[1])
                    : ValidateDiscreteAction(agent, action.discrete);
}

}  // namespace internal
}  // namespace mll::core
