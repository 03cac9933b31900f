// A read-only snapshot of what is drawn: terrain, helipad, landers and
// particles, in world units (meters, y up). Produced by Env::scene(), consumed
// by the renderer; holds no Box2D types.
#ifndef MLL_CORE_SCENE_H_
#define MLL_CORE_SCENE_H_

#include <vector>

namespace mll {

struct Vec2 {
  double x = 0.0;
  double y = 0.0;
};

struct ScenePolygon {
  std::vector<Vec2> vertices;  // World coordinates, counter-clockwise.
};

struct SceneLander {
  int agent = 0;                      // Agent index, picks the colour.
  bool wreck = false;                 // Damaged but kept (remove_on_damage off).
  std::vector<ScenePolygon> parts;    // Body first, then the two legs.
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
};

}  // namespace mll

#endif  // MLL_CORE_SCENE_H_
