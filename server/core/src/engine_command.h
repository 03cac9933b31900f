// The two action decoders (discrete and continuous) and the one engine command
// they produce, so that Env fires engines through a single code path
// (Gymnasium's step(): m_power, s_power and the side engine's direction).
#ifndef MLL_CORE_SRC_ENGINE_COMMAND_H_
#define MLL_CORE_SRC_ENGINE_COMMAND_H_

#include <cstdint>

#include "absl/status/status.h"
#include "mll/core/env.h"

namespace mll::core {
namespace internal {

struct EngineCommand {
  double main_power = 0.0;  // 0 (off) or 0.5..1.
  double side_power = 0.0;  // 0 (off) or 0.5..1.
  int side_direction = 0;   // -1 left engine, +1 right engine, 0 off.
};

// Discrete(4): 0 nothing, 1 left, 2 main, 3 right. `action` must be valid.
EngineCommand DecodeDiscrete(int32_t action);
// Box(-1, 1, (2,)): [main, lateral], clipped to [-1, 1]. Values must be
// finite.
EngineCommand DecodeContinuous(float main, float lateral);

// INVALID_ARGUMENT naming the agent, the value and the allowed range.
absl::Status ValidateDiscreteAction(int agent, int32_t action);
absl::Status ValidateContinuousAction(int agent, float main, float lateral);
// The check matching `continuous`, for one agent's action.
absl::Status ValidateAgentAction(bool continuous, int agent,
                                 const AgentAction& action);

}  // namespace internal
}  // namespace mll::core

#endif  // MLL_CORE_SRC_ENGINE_COMMAND_H_
