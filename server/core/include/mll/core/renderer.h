// Draws an environment's Scene into a 600x400 RGB frame with Cairo, like
// Gymnasium's LunarLander (white ground, black sky, yellow helipad flags), each
// lander in its own antialiased, outlined colour with its engine flames; the
// place where a lander landed or was destroyed stays marked. The view has a
// margin above the spawn row and beside the out-of-bounds edges, so landers
// are in frame from the first step. An optional overlay names the landers
// and shows the step, returns and outcomes. Also encodes frames as PNG.
#ifndef MLL_CORE_RENDERER_H_
#define MLL_CORE_RENDERER_H_

#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "mll/core/env.h"
#include "mll/core/scene.h"

namespace mll::core {

inline constexpr int kFrameWidth = 600;
inline constexpr int kFrameHeight = 400;

struct Frame {
  int width = 0;
  int height = 0;
  std::vector<uint8_t> rgb;  // [height][width][3], row 0 at the top.
};

// The world seen in a frame, in meters: x from -kViewMarginX to W +
// kViewMarginX (the strips outside [0, W] are out of bounds and drawn
// shaded), y from 0 to H + kViewTopMargin. Landers spawn at y = H with their
// tops 17/30 m higher and the initial push can lift them about 0.9 m more.
// The scale is the same on both axes: 600 / (W + 2 kViewMarginX) =
// 400 / (H + kViewTopMargin), about 27 px per meter (Gymnasium: 30).
inline constexpr double kViewTopMargin = 1.5;
inline constexpr double kViewMarginX = 0.75 * kViewTopMargin;

// The frame position (pixels, x right, y down, (0, 0) the top-left corner of
// the top-left pixel) of world point `world` of a scene W x H meters.
Vec2 WorldToFrame(const Scene& scene, const Vec2& world);

struct RenderOptions {
  // Draws the step, each lander's id beside it, and a table of every agent's
  // return and outcome. Off by default, so that rgb_array frames are a
  // picture of the world only, as Gymnasium's.
  bool overlay = false;
  // With the overlay: a line shown before the step (e.g. the env's name and
  // episode number).
  std::string caption;
};

// The mean of a polygon's vertices: inside it, as every part is convex.
// Marks (a wreck's cross, a landing's check) are centred on the body's.
Vec2 VertexMean(const ScenePolygon& polygon);

// RGB colour of an agent's lander, distinct for agents 0..31.
std::array<uint8_t, 3> AgentColor(int agent);

// Draws `scene`. Pure: no state, thread-safe.
Frame RenderScene(const Scene& scene, const RenderOptions& options = {});

// Ages the env's particles by one frame (as Gymnasium does per rendered frame)
// and draws it. FAILED_PRECONDITION if the env has no render mode or has not
// been reset.
absl::StatusOr<Frame> RenderEnv(Env& env, const RenderOptions& options = {});

// PNG bytes of `frame`, with a fast compression level.
absl::StatusOr<std::string> EncodePng(const Frame& frame);

}  // namespace mll::core

#endif  // MLL_CORE_RENDERER_H_
