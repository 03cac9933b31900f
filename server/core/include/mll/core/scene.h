// A read-only snapshot of what is drawn: terrain, helipad, landers and
// particles, in world units (meters, y up). Produced by Env::scene(), consumed
// by the renderer; holds no Box2D types.
#ifndef MLL_CORE_SCENE_H_
#define MLL_CORE_SCENE_H_

#include <cstdint>
#include <vector>

namespace mll::core {

enum class Outcome : uint8_t;  // env.h

struct Vec2 {
  double x = 0.0;
  double y = 0.0;
};

struct ScenePolygon {
  std::vector<Vec2> vertices;  // World coordinates, counter-clockwise.
};

struct SceneLander {
  int agent = 0;                    // Agent index, picks the colour.
  bool wreck = false;               // Damaged but kept (remove_on_damage off).
  std::vector<ScenePolygon> parts;  // Body first, then the two legs.
  Vec2 position;                    // The body's origin.
  double angle = 0.0;               // The body's angle, rad.
  // The engines fired in the latest step (0: off), drawn as flames. Powers
  // are 0.5..1 when on; side_direction is -1 (left engine), +1 or 0.
  double main_power = 0.0;
  double side_power = 0.0;
  int side_direction = 0;
};

// One per agent, in agent order: how its episode is going.
struct SceneAgent {
  Outcome outcome{};            // Outcome::kNone while active.
  double episode_return = 0.0;  // Sum of its rewards so far.
  // Where its episode ended when its bodies left the world (landed, or
  // damaged with remove_on_damage): the parts as in its last step, so that
  // the place stays marked. Empty otherwise.
  std::vector<ScenePolygon> final_parts;
};

struct SceneParticle {
  Vec2 position;
  double radius = 0.0;
  double ttl = 0.0;  // Gymnasium's time-to-live; colour fades with it.
};

struct Scene {
  double width = 0.0;   // W = 20 m.
  double height = 0.0;  // H = 13.333 m.
  // Surface points (chunk_x[i], smooth_y[i]), i = 0..10, left to right.
  std::vector<Vec2> terrain;
  double helipad_x1 = 0.0;
  double helipad_x2 = 0.0;
  double helipad_y = 0.0;
  // Landers still in the world (landed and removed ones are absent).
  std::vector<SceneLander> landers;
  std::vector<SceneParticle> particles;
  std::vector<SceneAgent> agents;
  int cycles = 0;  // World steps this episode (Env::cycles()).
};

}  // namespace mll::core

#endif  // MLL_CORE_SCENE_H_
