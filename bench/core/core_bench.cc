// Benchmarks of the simulation core (docs/benchmarks.md, "Core"):
// - Env::Step per agent-step against a FLOOR measured in the same run: a bare
//   Box2D world built here with LunarLander's terrain, the same landers, legs,
//   joints and collision filters, random engine impulses and
//   Step(1/50, 180, 60), the Env's spawn layout, and the same episode
//   boundaries as the Env's defaults (the episode ends when any lander is
//   damaged). The floor has no
//   observations, rewards or rules: Env / floor is the price of those.
// - Reset, RenderScene against a FLOOR in the same run (Cairo alone filling
//   50 antialiased lander-sized polygons on a 600x400 surface, as DESIGN's
//   Cairo floor), EncodePng (and libpng's defaults as the peer), and heap
//   per environment.
// bench/core/run.sh runs this binary and computes the ratios.
#include <cairo.h>
#include <malloc.h>
#include <png.h>

#include <array>
#include <cmath>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "benchmark/benchmark.h"
#include "box2d/box2d.h"
#include "collision.h"
#include "constants.h"
#include "mll/core/env.h"
#include "mll/core/renderer.h"
#include "rng.h"

namespace mll::core {
namespace {

using internal::Rng;

constexpr int kMaxCycles = EnvConfig().max_cycles;

std::unique_ptr<Env> MakeEnv(int n_landers, RenderMode mode) {
  EnvConfig config;
  config.n_landers = n_landers;
  config.render_mode = mode;
  return std::move(Env::Create(config).value());
}

// Where the Env spawns n landers, read back from a freshly reset Env so that
// the floor cannot drift from the Env's layout. Reset has pushed the landers
// and stepped once, which moves them by a few centimetres at most: the same
// layout as far as the cost of the physics is concerned.
std::vector<b2Vec2> EnvSpawnLayout(int n_landers) {
  std::unique_ptr<Env> env = MakeEnv(n_landers, RenderMode::kNone);
  StepResult result;
  env->Reset(0, &result);
  // The body polygon's vertex mean, in body coordinates.
  double local_x = 0, local_y = 0;
  for (const auto& v : internal::kLanderPoly) {
    local_x += v[0] / internal::kScale / internal::kLanderPoly.size();
    local_y += v[1] / internal::kScale / internal::kLanderPoly.size();
  }
  std::vector<b2Vec2> layout(n_landers);
  for (const SceneLander& lander : env->scene().landers) {
    const std::vector<Vec2>& body = lander.parts.at(0).vertices;
    double x = 0, y = 0;
    for (const Vec2& v : body) {
      x += v.x / body.size();
      y += v.y / body.size();
    }
    layout[lander.agent].Set(static_cast<float>(x - local_x),
                             static_cast<float>(y - local_y));
  }
  return layout;
}

// The floor: LunarLander's world for n landers, physics only.
class FloorWorld {
 public:
  FloorWorld(std::vector<b2Vec2> spawn, uint64_t seed)
      : spawn_(std::move(spawn)), rng_(seed) {
    Reset();
  }

  // A new world: terrain, landers, pushes and the reset's no-op step.
  void Reset() {
    world_ = std::make_unique<b2World>(b2Vec2(0.0f, -10.0f));
    landers_.clear();
    cycles_ = 0;
    BuildTerrain();
    for (size_t i = 0; i < spawn_.size(); ++i) AddLander(static_cast<int>(i));
    WorldStep();
  }

  // Fires each active lander's engine per its discrete action, steps the
  // world, and starts a new episode when this one is over. Returns the
  // number of landers stepped (agent-steps).
  int Step(const std::vector<int32_t>& actions) {
    int stepped = 0;
    for (size_t i = 0; i < landers_.size(); ++i) {
      if (landers_[i].body == nullptr) continue;
      FireEngine(landers_[i].body, actions[i]);
      ++stepped;
    }
    WorldStep();
    ++cycles_;
    bool over = cycles_ >= kMaxCycles;
    bool any_active = false;
    for (FloorLander& lander : landers_) {
      if (lander.body == nullptr) continue;
      const float x = lander.body->GetPosition().x;
      const bool out_of_bounds =
          std::fabs(x - internal::kW / 2) >= internal::kW / 2;
      if (Damaged(lander) || out_of_bounds) {
        over = true;  // terminate_on_damage: everyone stops.
      } else if (!lander.body->IsAwake()) {
        DestroyLander(lander);  // Landed: freed at once, as in the Env.
      } else {
        any_active = true;
      }
    }
    if (over || !any_active) Reset();
    return stepped;
  }

  b2World* world() { return world_.get(); }

 private:
  struct FloorLander {
    b2Body* body = nullptr;
    std::array<b2Body*, 2> legs = {nullptr, nullptr};
  };

  void WorldStep() {
    world_->Step(static_cast<float>(internal::kTimeStep),
                 internal::kVelocityIterations, internal::kPositionIterations);
  }

  void BuildTerrain() {
    using internal::kChunks;
    std::array<double, kChunks + 1> height;
    for (double& h : height) h = rng_.Uniform(0.0, internal::kH / 2);
    for (int i = kChunks / 2 - 2; i <= kChunks / 2 + 2; ++i) {
      height[i] = internal::kHelipadY;
    }
    b2BodyDef def;
    b2Body* moon = world_->CreateBody(&def);
    b2EdgeShape edge;
    edge.SetTwoSided(b2Vec2(0, 0), b2Vec2(internal::kW, 0));
    b2FixtureDef fixture;
    fixture.shape = &edge;
    fixture.filter = internal::MoonFilter();
    moon->CreateFixture(&fixture);
    fixture.friction = internal::kTerrainFriction;
    b2Vec2 previous;
    for (int i = 0; i < kChunks; ++i) {
      const double left = height[(i + kChunks) % (kChunks + 1)];
      const double right = height[i + 1];
      const b2Vec2 point(static_cast<float>(internal::kW / (kChunks - 1) * i),
                         static_cast<float>(0.33 * (left + height[i] + right)));
      if (i > 0) {
        edge.SetTwoSided(previous, point);
        moon->CreateFixture(&fixture);
      }
      previous = point;
    }
  }

  void AddLander(int agent) {
    using internal::kScale;
    const float x = spawn_[agent].x;
    const float y = spawn_[agent].y;

    FloorLander lander;
    b2BodyDef body_def;
    body_def.type = b2_dynamicBody;
    body_def.position.Set(x, y);
    lander.body = world_->CreateBody(&body_def);
    b2Vec2 vertices[internal::kLanderPoly.size()];
    for (size_t i = 0; i < internal::kLanderPoly.size(); ++i) {
      vertices[i].Set(static_cast<float>(internal::kLanderPoly[i][0] / kScale),
                      static_cast<float>(internal::kLanderPoly[i][1] / kScale));
    }
    b2PolygonShape body_shape;
    body_shape.Set(vertices, internal::kLanderPoly.size());
    b2FixtureDef body_fixture;
    body_fixture.shape = &body_shape;
    body_fixture.density = internal::kBodyDensity;
    body_fixture.friction = internal::kBodyFriction;
    body_fixture.filter = internal::LanderBodyFilter(agent);
    lander.body->CreateFixture(&body_fixture);
    lander.body->ApplyForceToCenter(
        b2Vec2(static_cast<float>(rng_.Uniform(-internal::kInitialRandom,
                                               internal::kInitialRandom)),
               static_cast<float>(rng_.Uniform(-internal::kInitialRandom,
                                               internal::kInitialRandom))),
        true);

    for (int side = 0; side < 2; ++side) {
      const int i = side == 0 ? -1 : 1;
      b2BodyDef leg_def;
      leg_def.type = b2_dynamicBody;
      const float away = static_cast<float>(i * internal::kLegAway / kScale);
      leg_def.position.Set(x - away, y);
      leg_def.angle = 0.05f * i;
      b2Body* leg = world_->CreateBody(&leg_def);
      b2PolygonShape box;
      box.SetAsBox(static_cast<float>(internal::kLegW / kScale),
                   static_cast<float>(internal::kLegH / kScale));
      b2FixtureDef leg_fixture;
      leg_fixture.shape = &box;
      leg_fixture.density = internal::kLegDensity;
      leg_fixture.filter = internal::LegFilter(agent);
      leg->CreateFixture(&leg_fixture);
      b2RevoluteJointDef joint;
      joint.bodyA = lander.body;
      joint.bodyB = leg;
      joint.localAnchorB.Set(away,
                             static_cast<float>(internal::kLegDown / kScale));
      joint.enableMotor = true;
      joint.enableLimit = true;
      joint.maxMotorTorque = static_cast<float>(internal::kLegSpringTorque);
      joint.motorSpeed = 0.3f * i;
      joint.lowerAngle = i < 0 ? 0.4f : -0.9f;
      joint.upperAngle = i < 0 ? 0.9f : -0.4f;
      world_->CreateJoint(&joint);
      lander.legs[side] = leg;
    }
    landers_.push_back(lander);
  }

  // Gymnasium's engine impulses for a discrete action (0 none, 1 left,
  // 2 main, 3 right), with its two dispersion draws per lander and step.
  void FireEngine(b2Body* body, int32_t action) {
    using internal::kScale;
    const double angle = body->GetAngle();
    const double tip[2] = {std::sin(angle), std::cos(angle)};
    const double side[2] = {-tip[1], tip[0]};
    const double d0 = rng_.Uniform(-1.0, 1.0) / kScale;
    const double d1 = rng_.Uniform(-1.0, 1.0) / kScale;
    const b2Vec2 p = body->GetPosition();
    double ox, oy, power, impulse_x, impulse_y;
    if (action == 2) {
      const double along = internal::kMainEngineYLocation / kScale + 2 * d0;
      ox = tip[0] * along + side[0] * d1;
      oy = -tip[1] * along - side[1] * d1;
      power = internal::kMainEnginePower;
      impulse_x = p.x + ox;
      impulse_y = p.y + oy;
    } else if (action == 1 || action == 3) {
      const double across =
          3 * d1 + (action - 2) * internal::kSideEngineAway / kScale;
      ox = tip[0] * d0 + side[0] * across;
      oy = -tip[1] * d0 - side[1] * across;
      power = internal::kSideEnginePower;
      impulse_x = p.x + ox - tip[0] * internal::kSideEngineTipOffset / kScale;
      impulse_y = p.y + oy + tip[1] * internal::kSideEngineHeight / kScale;
    } else {
      return;
    }
    body->ApplyLinearImpulse(
        b2Vec2(static_cast<float>(-ox * power),
               static_cast<float>(-oy * power)),
        b2Vec2(static_cast<float>(impulse_x), static_cast<float>(impulse_y)),
        true);
  }

  // The body touches anything, or a leg touches anything but the moon.
  static bool Damaged(const FloorLander& lander) {
    for (b2ContactEdge* e = lander.body->GetContactList(); e; e = e->next) {
      if (e->contact->IsTouching()) return true;
    }
    for (b2Body* leg : lander.legs) {
      for (b2ContactEdge* e = leg->GetContactList(); e; e = e->next) {
        if (e->contact->IsTouching() && e->other->GetType() != b2_staticBody) {
          return true;
        }
      }
    }
    return false;
  }

  void DestroyLander(FloorLander& lander) {
    for (b2Body* leg : lander.legs) world_->DestroyBody(leg);
    world_->DestroyBody(lander.body);
    lander = FloorLander();
  }

  std::vector<b2Vec2> spawn_;
  Rng rng_;
  std::unique_ptr<b2World> world_;
  std::vector<FloorLander> landers_;
  int cycles_ = 0;
};

// Random discrete actions for every agent (inactive ones are ignored).
void RandomActions(Rng& rng, std::vector<int32_t>* actions) {
  for (int32_t& a : *actions) {
    a = static_cast<int32_t>(rng.Integer(0, kDiscreteActionCount - 1));
  }
}

void BM_FloorStep(benchmark::State& state) {
  const int n = static_cast<int>(state.range(0));
  FloorWorld floor(EnvSpawnLayout(n), 1);
  Rng rng(2);
  std::vector<int32_t> actions(n);
  int64_t agent_steps = 0;
  for (auto _ : state) {
    RandomActions(rng, &actions);
    agent_steps += floor.Step(actions);
  }
  state.SetItemsProcessed(agent_steps);
}

void BM_EnvStep(benchmark::State& state) {
  const int n = static_cast<int>(state.range(0));
  std::unique_ptr<Env> env = MakeEnv(n, RenderMode::kNone);
  StepResult result;
  env->Reset(1, &result);
  Rng rng(2);
  std::vector<int32_t> actions(n);
  ActionsView view;
  view.discrete = actions;
  int64_t agent_steps = 0;
  for (auto _ : state) {
    if (env->episode_over()) env->Reset(std::nullopt, &result);
    RandomActions(rng, &actions);
    agent_steps += env->num_active();
    if (!env->Step(view, &result).ok()) {
      state.SkipWithError("Env::Step failed");
      break;
    }
  }
  state.SetItemsProcessed(agent_steps);
}

void BM_EnvReset(benchmark::State& state) {
  std::unique_ptr<Env> env =
      MakeEnv(static_cast<int>(state.range(0)), RenderMode::kNone);
  StepResult result;
  uint64_t seed = 0;
  for (auto _ : state) env->Reset(seed++, &result);
}

// A scene of n landers in flight with exhaust particles: what a viewer sees.
Scene BusyScene(int n_landers = 8) {
  std::unique_ptr<Env> env = MakeEnv(n_landers, RenderMode::kRgbArray);
  StepResult result;
  env->Reset(4, &result);
  std::vector<int32_t> actions(n_landers, 2);
  ActionsView view;
  view.discrete = actions;
  for (int i = 0; i < 20 && !env->episode_over(); ++i) {
    env->AgeParticlesForFrame();
    if (!env->Step(view, &result).ok()) break;
  }
  return env->scene();
}

// range(1) = 1 adds the overlay (the dashboard's frames).
void BM_RenderScene(benchmark::State& state) {
  const Scene scene = BusyScene(static_cast<int>(state.range(0)));
  RenderOptions options;
  options.overlay = state.range(1) != 0;
  options.caption = "envs/0123456789abcdef  episode 1";
  for (auto _ : state) benchmark::DoNotOptimize(RenderScene(scene, options));
  state.counters["landers"] = static_cast<double>(scene.landers.size());
  state.counters["particles"] = static_cast<double>(scene.particles.size());
}

// The rendering floor: Cairo alone painting a 600x400 surface and filling
// 50 antialiased lander bodies (6 vertices, 34 x 27 px) spread over it.
void BM_CairoFloor(benchmark::State& state) {
  cairo_surface_t* surface =
      cairo_image_surface_create(CAIRO_FORMAT_RGB24, kFrameWidth, kFrameHeight);
  cairo_t* cr = cairo_create(surface);
  constexpr int kPolygons = 50;
  constexpr double kBody[6][2] = {{-14, 17}, {-17, 0}, {-17, -10},
                                  {17, -10}, {17, 0},  {14, 17}};
  for (auto _ : state) {
    cairo_set_source_rgb(cr, 1, 1, 1);
    cairo_paint(cr);
    cairo_set_source_rgb(cr, 0.5, 0.4, 0.9);
    for (int i = 0; i < kPolygons; ++i) {
      const double cx = 30 + (i % 10) * 60.0 + 0.37 * i;
      const double cy = 40 + (i / 10) * 75.0 + 0.21 * i;
      cairo_move_to(cr, cx + kBody[0][0], cy - kBody[0][1]);
      for (int v = 1; v < 6; ++v) {
        cairo_line_to(cr, cx + kBody[v][0], cy - kBody[v][1]);
      }
      cairo_close_path(cr);
      cairo_fill(cr);
    }
    cairo_surface_flush(surface);
    benchmark::DoNotOptimize(cairo_image_surface_get_data(surface));
  }
  cairo_destroy(cr);
  cairo_surface_destroy(surface);
}

void BM_EncodePng(benchmark::State& state) {
  const Frame frame = RenderScene(BusyScene());
  size_t bytes = 0;
  for (auto _ : state) bytes = EncodePng(frame).value().size();
  state.counters["png_bytes"] = static_cast<double>(bytes);
}

// The peer: libpng's simplified writer with its default compression.
void BM_EncodePngLibpngDefaults(benchmark::State& state) {
  Frame frame = RenderScene(BusyScene());
  png_alloc_size_t bytes = 0;
  std::vector<uint8_t> buffer(frame.rgb.size() * 2);
  for (auto _ : state) {
    png_image image{};
    image.version = PNG_IMAGE_VERSION;
    image.width = frame.width;
    image.height = frame.height;
    image.format = PNG_FORMAT_RGB;
    bytes = buffer.size();
    if (!png_image_write_to_memory(&image, buffer.data(), &bytes, 0,
                                   frame.rgb.data(), 0, nullptr)) {
      state.SkipWithError(image.message);
      break;
    }
  }
  state.counters["png_bytes"] = static_cast<double>(bytes);
}

size_t HeapInUse() { return mallinfo2().uordblks; }

// Heap per environment after Reset: `count` envs (state.range(1)) with
// state.range(0) landers each, against the floor's bare worlds.
void BM_MemoryPerEnv(benchmark::State& state) {
  const int n = static_cast<int>(state.range(0));
  const int count = static_cast<int>(state.range(1));
  double env_bytes = 0, floor_bytes = 0;
  for (auto _ : state) {
    const size_t before = HeapInUse();
    {
      std::vector<std::unique_ptr<Env>> envs;
      StepResult result;
      for (int i = 0; i < count; ++i) {
        envs.push_back(MakeEnv(n, RenderMode::kNone));
        envs.back()->Reset(i, &result);
      }
      env_bytes = static_cast<double>(HeapInUse() - before) / count;
    }
    const std::vector<b2Vec2> layout = EnvSpawnLayout(n);
    const size_t floor_before = HeapInUse();
    {
      std::vector<std::unique_ptr<FloorWorld>> worlds;
      for (int i = 0; i < count; ++i) {
        worlds.push_back(std::make_unique<FloorWorld>(layout, i));
      }
      floor_bytes = static_cast<double>(HeapInUse() - floor_before) / count;
    }
  }
  state.counters["env_kb"] = env_bytes / 1024;
  state.counters["floor_kb"] = floor_bytes / 1024;
}

BENCHMARK(BM_FloorStep)->Arg(1)->Arg(3)->Arg(8)->Arg(32);
BENCHMARK(BM_EnvStep)->Arg(1)->Arg(3)->Arg(8)->Arg(32);
BENCHMARK(BM_EnvReset)->Arg(1)->Arg(3)->Arg(8)->Arg(32);
BENCHMARK(BM_RenderScene)
    ->Args({8, 0})
    ->Args({32, 0})
    ->Args({8, 1})
    ->Args({32, 1})
    ->Unit(benchmark::kMicrosecond);
BENCHMARK(BM_CairoFloor)->Unit(benchmark::kMicrosecond);
BENCHMARK(BM_EncodePng)->Unit(benchmark::kMicrosecond);
BENCHMARK(BM_EncodePngLibpngDefaults)->Unit(benchmark::kMicrosecond);
BENCHMARK(BM_MemoryPerEnv)
    ->Args({1, 1000})
    ->Args({3, 1000})
    ->Args({32, 100})
    ->Iterations(1)
    ->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace mll::core

BENCHMARK_MAIN();
