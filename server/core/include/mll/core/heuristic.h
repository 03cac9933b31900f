// Gymnasium's LunarLander heuristic pilot, applied to observation[0:8] of one
// lander (docs/environment.md). For baselines, tests and
// demos.
#ifndef MLL_CORE_HEURISTIC_H_
#define MLL_CORE_HEURISTIC_H_

#include "absl/types/span.h"
#include "mll/core/env.h"

namespace mll::core {

// `observation` holds at least 8 values. Fills the member of the returned
// action that matches `continuous`.
AgentAction HeuristicAction(absl::Span<const float> observation,
                            bool continuous);

}  // namespace mll::core

#endif  // MLL_CORE_HEURISTIC_H_
