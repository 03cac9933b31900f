#include "mll/core/heuristic.h"

#include <algorithm>
#include <cmath>

namespace mll::core {

// Gymnasium's heuristic(env, s) from lunar_lander.py, on s = observation[0:8].
AgentAction HeuristicAction(absl::Span<const float> observation,
                            bool continuous) {
  const auto s = [&observation](int i) {
    return static_cast<double>(observation[i]);
  };
  // Point towards the centre, but never more than 0.4 rad (22 degrees).
  const double angle_target = std::clamp(s(0) * 0.5 + s(2), -0.4, 0.4);
  // Target height proportional to the horizontal offset.
  const double hover_target = 0.55 * std::abs(s(0));
  double angle_todo = (angle_target - s(4)) * 0.5 - s(5);
  double hover_todo = (hover_target - s(1)) * 0.5 - s(3) * 0.5;
  if (s(6) != 0.0 || s(7) != 0.0) {
    // After contact, only slow the fall.
    angle_todo = 0.0;
    hover_todo = -s(3) * 0.5;
  }
  AgentAction action;
  if (continuous) {
    action.continuous = {
        static_cast<float>(std::clamp(hover_todo * 20 - 1, -1.0, 1.0)),
        static_cast<float>(std::clamp(-angle_todo * 20, -1.0, 1.0))};
  } else if (hover_todo > std::abs(angle_todo) && hover_todo > 0.05) {
    action.discrete = 2;
  } else if (angle_todo < -0.05) {
    action.discrete = 3;
  } else if (angle_todo > 0.05) {
    action.discrete = 1;
  }
  return action;
}

}  // namespace mll::core
