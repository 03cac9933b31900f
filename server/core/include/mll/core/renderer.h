// Draws an environment's Scene into a 600x400 RGB frame with Cairo, like
// Gymnasium's LunarLander (white ground, black sky, yellow helipad flags), each
// lander in its own colour; and encodes frames as PNG.
#ifndef MLL_CORE_RENDERER_H_
#define MLL_CORE_RENDERER_H_

#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "mll/core/env.h"
#include "mll/core/scene.h"

namespace mll {

inline constexpr int kFrameWidth = 600;
inline constexpr int kFrameHeight = 400;

struct Frame {
  int width = 0;
  int height = 0;
  std::vector<uint8_t> rgb;  // [height][width][3], row 0 at the top.
};

// RGB colour of an agent's lander, distinct for agents 0..31.
std::array<uint8_t, 3> AgentColor(int agent);

// Draws `scene`. Pure: no state, thread-safe.
Frame RenderScene(const Scene& scene);

// Ages the env's particles by one frame (as Gymnasium does per rendered frame)
// and draws it. FAILED_PRECONDITION if the env has no render mode or has not
// been reset.
absl::StatusOr<Frame> RenderEnv(Env& env);

// PNG bytes of `frame`, with a fast compression level.
absl::StatusOr<std::string> EncodePng(const Frame& frame);

}  // namespace mll

#endif  // MLL_CORE_RENDERER_H_
