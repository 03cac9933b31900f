// One Multi Lunar Lander environment (docs/environment.md).
//
// Draw order of the environment's generator (fixed; changing it changes every
// episode):
//   Reset:  1. 12 terrain heights U(0, H/2), left to right.
//           2. For each lander in index order: push x, push y ~ U(-1000, 1000);
//              then, with enable_wind, its wind index and its torque index,
//              integers in [-9999, 9999].
//           3. The no-op step, which draws like any step (below).
//   Step:   for each active lander in index order, two engine dispersions
//           U(-1, 1) / SCALE, drawn whether or not an engine fires (as
//           Gymnasium does).
// Rendering never draws: particles live in a separate decoration world.
//
// The reset's no-op step runs the physics, observations and reward shaping
// (it sets every lander's previous shaping, like Gymnasium's reset) but
// applies no outcome: nobody can end an episode at reset. Spawn places every
// lander clear of the terrain and of each other (see SpawnPosition), so the
// no-op step records no damaging contact; if some flag were set it would
// count at the first real step.

#include "mll/core/env.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <deque>
#include <limits>
#include <utility>

#include "absl/strings/str_cat.h"
#include "box2d/box2d.h"
#include "collision.h"
#include "constants.h"
#include "contact_listener.h"
#include "engine_command.h"
#include "rng.h"

namespace mll::core {

using internal::EngineCommand;
using internal::FixtureTag;
using internal::LanderContacts;
using internal::Part;

absl::string_view OutcomeName(Outcome outcome) {
  switch (outcome) {
    case Outcome::kNone:
      return "none";
    case Outcome::kLanded:
      return "landed";
    case Outcome::kCrashed:
      return "crashed";
    case Outcome::kOutOfBounds:
      return "out_of_bounds";
    case Outcome::kTruncated:
      return "truncated";
    case Outcome::kAborted:
      return "aborted";
  }
  return "unknown";
}

std::string AgentName(int agent_index) {
  return absl::StrCat("lander_", agent_index);
}

namespace {

using namespace internal;  // NOLINT: the constants of this one file's world.

// Spawn layout. For n <= kPaperRowMax, the paper's single row at y = H,
// x = (i + 1) W / (n + 1). More landers fill rows of at most kPaperRowMax,
// kSpawnRowSpacing apart, top row at y = H. A lander with its legs swung out
// spans 2.12 m across and 1.1 m from its body's top to its feet, so rows of 7
// (2.5 m apart) and rows 1.5 m apart leave about 0.4 m between neighbours, more
// than the 0.23 m that the largest pushes (1000 N) close in the reset step and
// the first step; the lowest of 5 rows (y = 7.33 m, feet at 6.8 m) stays above
// the highest terrain (0.99 * H/2 = 6.6 m).
// The paper keeps its single row up to n = 8, but that row leaves only
// 0.1 m between neighbours: their legs touch while swinging out (seed 0 damages
// landers 0 and 1 at once), breaking the rule that spawn damages nobody. So the
// single row stops at 7 and n = 8 spawns as two rows of 4.
constexpr int kPaperRowMax = 7;
constexpr double kSpawnRowSpacing = 1.5;

b2Vec2 SpawnPosition(int agent, int n_landers) {
  const int rows = (n_landers + kPaperRowMax - 1) / kPaperRowMax;
  const int base = n_landers / rows;
  const int extra = n_landers % rows;  // The first `extra` rows hold base + 1.
  int row = 0;
  int first = 0;
  while (true) {
    const int count = base + (row < extra ? 1 : 0);
    if (agent < first + count) {
      const int column = agent - first;
      return b2Vec2(static_cast<float>(kW * (column + 1) / (count + 1)),
                    static_cast<float>(kH - row * kSpawnRowSpacing));
    }
    first += count;
    ++row;
  }
}

// Gymnasium's wind and turbulence profile at index k.
double WindProfile(int64_t k) {
  const double x = static_cast<double>(k);
  return std::tanh(std::sin(0.02 * x) + std::sin(M_PI * 0.01 * x));
}

struct Lander {
  b2Body* body = nullptr;
  std::array<b2Body*, 2> legs = {nullptr, nullptr};
  int64_t wind_index = 0;
  int64_t torque_index = 0;
  double prev_shaping = 0.0;
  bool active = false;
  bool wreck = false;
  Outcome outcome = Outcome::kNone;
  double episode_return = 0.0;
  int episode_length = 0;
  std::array<float, kObservationSize> observation = {};
  // Drawing only: the engines of the latest step, and the parts as they were
  // when the bodies were destroyed (landed or removed on damage).
  EngineCommand last_command;
  std::vector<ScenePolygon> final_parts;
};

// The world polygons of a lander's body and legs (bodies must exist).
std::vector<ScenePolygon> LanderParts(const Lander& lander) {
  std::vector<ScenePolygon> parts;
  parts.reserve(3);
  for (const b2Body* body : {lander.body, lander.legs[0], lander.legs[1]}) {
    const auto* shape =
        static_cast<const b2PolygonShape*>(body->GetFixtureList()->GetShape());
    ScenePolygon polygon;
    polygon.vertices.reserve(shape->m_count);
    for (int v = 0; v < shape->m_count; ++v) {
      const b2Vec2 p = body->GetWorldPoint(shape->m_vertices[v]);
      polygon.vertices.push_back({p.x, p.y});
    }
    parts.push_back(std::move(polygon));
  }
  return parts;
}

struct Particle {
  b2Body* body = nullptr;
  double ttl = 0.0;
};

// What one step measured for one lander before the rules are applied.
struct Measurement {
  std::array<double, kObservationSize> state = {};
  double shaping = 0.0;
};

}  // namespace

class Env::Impl {
 public:
  explicit Impl(const EnvConfig& config)
      : config_(config), listener_(&contacts_) {}

  ~Impl() { DestroyWorlds(); }

  void Reset(std::optional<uint64_t> seed, StepResult* result);
  absl::Status Step(const ActionsView& actions, StepResult* result);
  absl::Status ValidateActions(const ActionsView& actions) const;
  Scene MakeScene() const;
  void AgeParticlesForFrame();
  absl::Status SetLanderState(int agent, double x, double y, double angle,
                              double vx, double vy, double omega);

  const EnvConfig config_;
  bool started_ = false;
  int num_active_ = 0;
  int cycles_ = 0;
  std::vector<Lander> landers_;

 private:
  bool rendering() const { return config_.render_mode != RenderMode::kNone; }
  void DestroyWorlds();
  void BuildTerrain();
  void CreateMoon(b2World* world) const;
  void CreateLander(int agent);
  void DestroyLanderBodies(Lander& lander);
  EngineCommand CommandFor(const ActionsView& actions, int agent) const;
  // Wind, engines and one world step for the active landers.
  void Advance(const std::vector<EngineCommand>& commands);
  void FireEngines(Lander& lander, const EngineCommand& command);
  void CreateParticle(double mass, const b2Vec2& position,
                      const b2Vec2& impulse, double ttl);
  void RemoveExpiredParticles();
  Measurement Measure(int agent, const std::vector<uint8_t>& stepped) const;
  // The parts of Step, in the order it runs them.
  // Each stepped lander's observation, shaped reward and contact outcome,
  // before any rule changes the world; true when one was damaged.
  bool ObserveLanders(const std::vector<uint8_t>& stepped,
                      const std::vector<EngineCommand>& commands,
                      std::vector<double>* rewards,
                      std::vector<uint8_t>* damaged);
  // Damage, landing and terminate_on_damage: rewards and lander removal.
  void ApplyOutcomes(const std::vector<uint8_t>& stepped,
                     const std::vector<uint8_t>& damaged, bool any_damaged,
                     std::vector<double>* rewards);
  // At max_cycles.
  void TruncateActiveLanders();
  // shared_reward: each stepped lander gets the mean.
  void ShareRewards(const std::vector<uint8_t>& stepped,
                    std::vector<double>* rewards) const;
  // Returns, lengths and the active count.
  void UpdateEpisodes(const std::vector<uint8_t>& stepped,
                      const std::vector<double>& rewards);
  void FillResult(const std::vector<uint8_t>& stepped,
                  const std::vector<double>& rewards, StepResult* result) const;

  // Step's per-lander working arrays, kept so that a step does not allocate:
  // filled anew by every Step, never read across steps.
  struct StepScratch {
    std::vector<uint8_t> stepped;
    std::vector<EngineCommand> commands;
    std::vector<double> rewards;
    std::vector<uint8_t> damaged;
  };
  StepScratch step_scratch_;

  internal::Rng rng_;  // Seed 0 until the first seeded Reset.
  std::vector<LanderContacts> contacts_;
  internal::ContactListener listener_;
  std::unique_ptr<b2World> world_;
  // Holds only a copy of the terrain and the particles: decoration that can
  // never touch a lander.
  std::unique_ptr<b2World> decoration_world_;
  std::deque<Particle> particles_;
  std::array<Vec2, kChunks> terrain_ = {};
};

void Env::Impl::DestroyWorlds() {
  particles_.clear();
  decoration_world_.reset();
  world_.reset();
  for (Lander& lander : landers_) {
    lander.body = nullptr;
    lander.legs = {nullptr, nullptr};
  }
}

void Env::Impl::BuildTerrain() {
  std::array<double, kChunks + 1> height;
  for (double& h : height) h = rng_.Uniform(0.0, kH / 2);
  for (int i = kChunks / 2 - 2; i <= kChunks / 2 + 2; ++i)
    height[i] = kHelipadY;
  for (int i = 0; i < kChunks; ++i) {
    // Python's height[-1] is height[kChunks]: the first point wraps around.
    const double left = height[i == 0 ? kChunks : i - 1];
    terrain_[i] = {kW / (kChunks - 1) * i,
                   0.33 * (left + height[i] + height[i + 1])};
  }
}

void Env::Impl::CreateMoon(b2World* world) const {
  b2BodyDef def;
  b2Body* moon = world->CreateBody(&def);
  auto add_edge = [moon](b2Vec2 a, b2Vec2 b, double friction) {
    b2EdgeShape edge;
    edge.SetTwoSided(a, b);
    b2FixtureDef fixture;
    fixture.shape = &edge;
    fixture.density = 0.0f;
    fixture.friction = static_cast<float>(friction);
    fixture.filter = MoonFilter();
    fixture.userData.pointer = EncodeFixtureTag(Part::kMoon, -1);
    moon->CreateFixture(&fixture);
  };
  add_edge(b2Vec2(0.0f, 0.0f), b2Vec2(static_cast<float>(kW), 0.0f),
           kDefaultFriction);
  for (int i = 0; i + 1 < kChunks; ++i) {
    add_edge(b2Vec2(static_cast<float>(terrain_[i].x),
                    static_cast<float>(terrain_[i].y)),
             b2Vec2(static_cast<float>(terrain_[i + 1].x),
                    static_cast<float>(terrain_[i + 1].y)),
             kTerrainFriction);
  }
}

void Env::Impl::CreateLander(int agent) {
  Lander& lander = landers_[agent];
  const b2Vec2 spawn = SpawnPosition(agent, config_.n_landers);

  b2BodyDef body_def;
  body_def.type = b2_dynamicBody;
  body_def.position = spawn;
  body_def.angle = 0.0f;
  lander.body = world_->CreateBody(&body_def);
  b2Vec2 vertices[kLanderPoly.size()];
  for (size_t i = 0; i < kLanderPoly.size(); ++i) {
    vertices[i].Set(static_cast<float>(kLanderPoly[i][0] / kScale),
                    static_cast<float>(kLanderPoly[i][1] / kScale));
  }
  b2PolygonShape body_shape;
  body_shape.Set(vertices, static_cast<int32>(kLanderPoly.size()));
  b2FixtureDef body_fixture;
  body_fixture.shape = &body_shape;
  body_fixture.density = static_cast<float>(kBodyDensity);
  body_fixture.friction = static_cast<float>(kBodyFriction);
  body_fixture.restitution = 0.0f;
  body_fixture.filter = LanderBodyFilter(agent);
  body_fixture.userData.pointer = EncodeFixtureTag(Part::kBody, agent);
  lander.body->CreateFixture(&body_fixture);

  const double push_x = rng_.Uniform(-kInitialRandom, kInitialRandom);
  const double push_y = rng_.Uniform(-kInitialRandom, kInitialRandom);
  lander.body->ApplyForceToCenter(
      b2Vec2(static_cast<float>(push_x), static_cast<float>(push_y)), true);
  if (config_.enable_wind) {
    lander.wind_index = rng_.Integer(-kWindIndexBound, kWindIndexBound);
    lander.torque_index = rng_.Integer(-kWindIndexBound, kWindIndexBound);
  }

  for (int leg = 0; leg < 2; ++leg) {
    const double side = leg == 0 ? -1.0 : 1.0;  // Gymnasium's i.
    b2BodyDef leg_def;
    leg_def.type = b2_dynamicBody;
    leg_def.position.Set(static_cast<float>(spawn.x - side * kLegAway / kScale),
                         spawn.y);
    leg_def.angle = static_cast<float>(side * 0.05);
    b2Body* leg_body = world_->CreateBody(&leg_def);
    b2PolygonShape leg_shape;
    leg_shape.SetAsBox(static_cast<float>(kLegW / kScale),
                       static_cast<float>(kLegH / kScale));
    b2FixtureDef leg_fixture;
    leg_fixture.shape = &leg_shape;
    leg_fixture.density = static_cast<float>(kLegDensity);
    leg_fixture.friction = static_cast<float>(kDefaultFriction);
    leg_fixture.restitution = 0.0f;
    leg_fixture.filter = LegFilter(agent);
    leg_fixture.userData.pointer =
        EncodeFixtureTag(leg == 0 ? Part::kLeg0 : Part::kLeg1, agent);
    leg_body->CreateFixture(&leg_fixture);

    b2RevoluteJointDef joint;
    joint.bodyA = lander.body;
    joint.bodyB = leg_body;
    joint.localAnchorA.Set(0.0f, 0.0f);
    joint.localAnchorB.Set(static_cast<float>(side * kLegAway / kScale),
                           static_cast<float>(kLegDown / kScale));
    // Gymnasium builds this joint with pybox2d, whose revoluteJointDef sets
    // referenceAngle = bodyB.angle - bodyA.angle (here 0.05 * side) whenever
    // both bodies are given; the limits below are relative to it. Box2D's own
    // default is 0, which would spread each leg 0.05 rad further out: the
    // lander then rests 3.5 cm lower, rocks longer after touchdown and falls
    // asleep (lands) later or not at all.
    joint.referenceAngle = leg_body->GetAngle() - lander.body->GetAngle();
    joint.enableMotor = true;
    joint.enableLimit = true;
    joint.maxMotorTorque = static_cast<float>(kLegSpringTorque);
    joint.motorSpeed = static_cast<float>(0.3 * side);
    if (leg == 0) {
      joint.lowerAngle = static_cast<float>(0.9 - 0.5);
      joint.upperAngle = 0.9f;
    } else {
      joint.lowerAngle = -0.9f;
      joint.upperAngle = static_cast<float>(-0.9 + 0.5);
    }
    world_->CreateJoint(&joint);
    lander.legs[leg] = leg_body;
  }
}

void Env::Impl::DestroyLanderBodies(Lander& lander) {
  // Reading positions changes nothing in the world.
  if (lander.body != nullptr) lander.final_parts = LanderParts(lander);
  // Destroying a body destroys its joints and contacts (EndContact is
  // reported, which only clears flags).
  for (b2Body*& leg : lander.legs) {
    if (leg != nullptr) world_->DestroyBody(leg);
    leg = nullptr;
  }
  if (lander.body != nullptr) world_->DestroyBody(lander.body);
  lander.body = nullptr;
}

void Env::Impl::Reset(std::optional<uint64_t> seed, StepResult* result) {
  if (seed.has_value()) rng_.Seed(*seed);
  DestroyWorlds();
  const b2Vec2 gravity(0.0f, static_cast<float>(config_.gravity));
  world_ = std::make_unique<b2World>(gravity);
  world_->SetContactListener(&listener_);
  contacts_.assign(config_.n_landers, LanderContacts());
  landers_.assign(config_.n_landers, Lander());

  BuildTerrain();
  CreateMoon(world_.get());
  if (rendering()) {
    decoration_world_ = std::make_unique<b2World>(gravity);
    CreateMoon(decoration_world_.get());
  }
  for (int i = 0; i < config_.n_landers; ++i) {
    CreateLander(i);
    landers_[i].active = true;
  }
  started_ = true;
  num_active_ = config_.n_landers;
  cycles_ = 0;

  // The no-op step (see the top of this file).
  Advance(std::vector<EngineCommand>(config_.n_landers));
  const std::vector<uint8_t> stepped(config_.n_landers, 1);
  for (int i = 0; i < config_.n_landers; ++i) {
    const Measurement m = Measure(i, stepped);
    Lander& lander = landers_[i];
    lander.prev_shaping = m.shaping;
    for (int k = 0; k < kObservationSize; ++k) {
      lander.observation[k] = static_cast<float>(m.state[k]);
    }
  }
  FillResult(stepped, std::vector<double>(config_.n_landers, 0.0), result);
}

EngineCommand Env::Impl::CommandFor(const ActionsView& actions,
                                    int agent) const {
  if (config_.continuous) {
    return DecodeContinuous(actions.continuous[2 * agent],
                            actions.continuous[2 * agent + 1]);
  }
  return DecodeDiscrete(actions.discrete[agent]);
}

void Env::Impl::Advance(const std::vector<EngineCommand>& commands) {
  for (int i = 0; i < config_.n_landers; ++i) {
    Lander& lander = landers_[i];
    if (!lander.active) continue;
    const LanderContacts& flags = contacts_[i];
    if (config_.enable_wind && !(flags.leg_ground[0] || flags.leg_ground[1])) {
      const double wind = WindProfile(lander.wind_index) * config_.wind_power;
      ++lander.wind_index;
      lander.body->ApplyForceToCenter(b2Vec2(static_cast<float>(wind), 0.0f),
                                      true);
      const double torque =
          WindProfile(lander.torque_index) * config_.turbulence_power;
      ++lander.torque_index;
      lander.body->ApplyTorque(static_cast<float>(torque), true);
    }
    FireEngines(lander, commands[i]);
  }
  world_->Step(static_cast<float>(kTimeStep), kVelocityIterations,
               kPositionIterations);
  if (decoration_world_ != nullptr) {
    decoration_world_->Step(static_cast<float>(kTimeStep), kVelocityIterations,
                            kPositionIterations);
  }
}

void Env::Impl::FireEngines(Lander& lander, const EngineCommand& command) {
  b2Body* body = lander.body;
  const double angle = body->GetAngle();
  const b2Vec2 position = body->GetPosition();
  const double tip[2] = {std::sin(angle), std::cos(angle)};
  const double side[2] = {-tip[1], tip[0]};
  const double dispersion[2] = {rng_.Uniform(-1.0, 1.0) / kScale,
                                rng_.Uniform(-1.0, 1.0) / kScale};

  if (command.main_power > 0.0) {
    const double along = kMainEngineYLocation / kScale + 2 * dispersion[0];
    const double ox = tip[0] * along + side[0] * dispersion[1];
    const double oy = -tip[1] * along - side[1] * dispersion[1];
    const b2Vec2 impulse_pos(static_cast<float>(position.x + ox),
                             static_cast<float>(position.y + oy));
    const double scale = kMainEnginePower * command.main_power;
    if (rendering()) {
      CreateParticle(kMainParticleMass, impulse_pos,
                     b2Vec2(static_cast<float>(ox * scale),
                            static_cast<float>(oy * scale)),
                     command.main_power);
    }
    body->ApplyLinearImpulse(b2Vec2(static_cast<float>(-ox * scale),
                                    static_cast<float>(-oy * scale)),
                             impulse_pos, true);
  }

  if (command.side_power > 0.0) {
    const double across =
        3 * dispersion[1] + command.side_direction * kSideEngineAway / kScale;
    const double ox = tip[0] * dispersion[0] + side[0] * across;
    const double oy = -tip[1] * dispersion[0] - side[1] * across;
    const b2Vec2 impulse_pos(
        static_cast<float>(position.x + ox -
                           tip[0] * kSideEngineTipOffset / kScale),
        static_cast<float>(position.y + oy +
                           tip[1] * kSideEngineHeight / kScale));
    const double scale = kSideEnginePower * command.side_power;
    if (rendering()) {
      CreateParticle(kSideParticleMass, impulse_pos,
                     b2Vec2(static_cast<float>(ox * scale),
                            static_cast<float>(oy * scale)),
                     command.side_power);
    }
    body->ApplyLinearImpulse(b2Vec2(static_cast<float>(-ox * scale),
                                    static_cast<float>(-oy * scale)),
                             impulse_pos, true);
  }
}

void Env::Impl::CreateParticle(double mass, const b2Vec2& position,
                               const b2Vec2& impulse, double ttl) {
  b2BodyDef def;
  def.type = b2_dynamicBody;
  def.position = position;
  b2Body* body = decoration_world_->CreateBody(&def);
  b2CircleShape circle;
  circle.m_radius = static_cast<float>(kParticleRadius);
  b2FixtureDef fixture;
  fixture.shape = &circle;
  fixture.density = static_cast<float>(mass);
  fixture.friction = static_cast<float>(kParticleFriction);
  fixture.restitution = static_cast<float>(kParticleRestitution);
  fixture.filter = ParticleFilter();
  fixture.userData.pointer = EncodeFixtureTag(Part::kParticle, -1);
  body->CreateFixture(&fixture);
  body->ApplyLinearImpulse(impulse, position, true);
  particles_.push_back({body, ttl});
  RemoveExpiredParticles();
}

void Env::Impl::RemoveExpiredParticles() {
  auto expired = [](const Particle& p) { return p.ttl < 0.0; };
  for (const Particle& p : particles_) {
    if (expired(p)) decoration_world_->DestroyBody(p.body);
  }
  particles_.erase(
      std::remove_if(particles_.begin(), particles_.end(), expired),
      particles_.end());
}

void Env::Impl::AgeParticlesForFrame() {
  if (decoration_world_ == nullptr) return;
  for (Particle& p : particles_) p.ttl -= kParticleTtlPerFrame;
  RemoveExpiredParticles();
}

Measurement Env::Impl::Measure(int agent,
                               const std::vector<uint8_t>& stepped) const {
  const Lander& lander = landers_[agent];
  const b2Vec2 pos = lander.body->GetPosition();
  const b2Vec2 vel = lander.body->GetLinearVelocity();
  const LanderContacts& flags = contacts_[agent];
  Measurement m;
  std::array<double, kObservationSize>& s = m.state;
  s[0] = (pos.x - kW / 2) / (kW / 2);
  s[1] = (pos.y - (kHelipadY + kLegDown / kScale)) / (kH / 2);
  s[2] = vel.x * (kW / 2) / kFps;
  s[3] = vel.y * (kH / 2) / kFps;
  s[4] = lander.body->GetAngle();
  s[5] = 20.0 * lander.body->GetAngularVelocity() / kFps;
  s[6] = flags.leg_ground[0] ? 1.0 : 0.0;
  s[7] = flags.leg_ground[1] ? 1.0 : 0.0;
  m.shaping = -kShapingDistance * std::sqrt(s[0] * s[0] + s[1] * s[1]) -
              kShapingSpeed * std::sqrt(s[2] * s[2] + s[3] * s[3]) -
              kShapingAngle * std::abs(s[4]) + kShapingLeg * s[6] +
              kShapingLeg * s[7];

  // The two nearest other landers stepped this step (world distance, ties to
  // the lower index), nearest first; a missing one stays (0, 0) and adds no
  // shaping term.
  std::array<int, 2> nearest = {-1, -1};
  std::array<double, 2> nearest_d2 = {std::numeric_limits<double>::infinity(),
                                      std::numeric_limits<double>::infinity()};
  for (int j = 0; j < config_.n_landers; ++j) {
    if (j == agent || !stepped[j]) continue;
    const b2Vec2 d = landers_[j].body->GetPosition() - pos;
    const double d2 =
        static_cast<double>(d.x) * d.x + static_cast<double>(d.y) * d.y;
    if (d2 < nearest_d2[0]) {
      nearest = {j, nearest[0]};
      nearest_d2 = {d2, nearest_d2[0]};
    } else if (d2 < nearest_d2[1]) {
      nearest[1] = j;
      nearest_d2[1] = d2;
    }
  }
  for (int k = 0; k < 2; ++k) {
    if (nearest[k] < 0) continue;
    const b2Vec2 other = landers_[nearest[k]].body->GetPosition();
    const double rx = (static_cast<double>(pos.x) - other.x) / (kW / 2);
    const double ry = (static_cast<double>(pos.y) - other.y) / (kH / 2);
    s[8 + 2 * k] = rx;
    s[9 + 2 * k] = ry;
    m.shaping += kShapingNeighbour * std::sqrt(rx * rx + ry * ry);
  }
  return m;
}

absl::Status Env::Impl::ValidateActions(const ActionsView& actions) const {
  const int n = config_.n_landers;
  if (config_.continuous) {
    if (actions.continuous.size() != static_cast<size_t>(2 * n)) {
      return absl::InvalidArgumentError(absl::StrCat(
          "continuous actions have ", actions.continuous.size(),
          " values: expected ", 2 * n, " (2 per lander, n_landers = ", n, ")"));
    }
  } else if (actions.discrete.size() != static_cast<size_t>(n)) {
    return absl::InvalidArgumentError(
        absl::StrCat("discrete actions have ", actions.discrete.size(),
                     " values: expected ", n, " (n_landers = ", n, ")"));
  }
  for (int i = 0; i < n; ++i) {
    if (!landers_.empty() && !landers_[i].active) continue;
    const absl::Status status =
        config_.continuous
            ? ValidateContinuousAction(i, actions.continuous[2 * i],
                                       actions.continuous[2 * i + 1])
            : ValidateDiscreteAction(i, actions.discrete[i]);
    if (!status.ok()) return status;
  }
  return absl::OkStatus();
}

absl::Status Env::Impl::Step(const ActionsView& actions, StepResult* result) {
  if (!started_) {
    return absl::FailedPreconditionError("step before reset: call Reset first");
  }
  if (num_active_ == 0) {
    return absl::FailedPreconditionError(
        "step after the episode is over: every lander is done, call Reset");
  }
  if (absl::Status status = ValidateActions(actions); !status.ok()) {
    return status;
  }
  const int n = config_.n_landers;
  std::vector<uint8_t>& stepped = step_scratch_.stepped;
  std::vector<EngineCommand>& commands = step_scratch_.commands;
  std::vector<double>& rewards = step_scratch_.rewards;
  std::vector<uint8_t>& damaged = step_scratch_.damaged;
  stepped.assign(n, 0);
  commands.assign(n, EngineCommand{});
  for (int i = 0; i < n; ++i) {
    if (!landers_[i].active) continue;
    stepped[i] = 1;
    commands[i] = CommandFor(actions, i);
    landers_[i].last_command = commands[i];
  }
  Advance(commands);

  rewards.assign(n, 0.0);
  damaged.assign(n, 0);
  const bool any_damaged =
      ObserveLanders(stepped, commands, &rewards, &damaged);
  ApplyOutcomes(stepped, damaged, any_damaged, &rewards);
  ++cycles_;
  if (cycles_ >= config_.max_cycles) TruncateActiveLanders();
  if (config_.shared_reward) ShareRewards(stepped, &rewards);
  UpdateEpisodes(stepped, rewards);
  FillResult(stepped, rewards, result);
  return absl::OkStatus();
}

bool Env::Impl::ObserveLanders(const std::vector<uint8_t>& stepped,
                               const std::vector<EngineCommand>& commands,
                               std::vector<double>* rewards,
                               std::vector<uint8_t>* damaged) {
  bool any_damaged = false;
  for (int i = 0; i < config_.n_landers; ++i) {
    if (!stepped[i]) continue;
    Lander& lander = landers_[i];
    const Measurement m = Measure(i, stepped);
    for (int k = 0; k < kObservationSize; ++k) {
      lander.observation[k] = static_cast<float>(m.state[k]);
    }
    (*rewards)[i] = m.shaping - lander.prev_shaping -
                    kMainFuelCost * commands[i].main_power -
                    kSideFuelCost * commands[i].side_power;
    lander.prev_shaping = m.shaping;
    const LanderContacts& flags = contacts_[i];
    const bool contact_damage = flags.body_touched || flags.leg_touched_other;
    if (contact_damage || std::abs(m.state[0]) >= 1.0) {
      (*damaged)[i] = 1;
      any_damaged = true;
      lander.outcome =
          contact_damage ? Outcome::kCrashed : Outcome::kOutOfBounds;
    } else if (!lander.body->IsAwake()) {
      lander.outcome = Outcome::kLanded;
    }
  }
  return any_damaged;
}

void Env::Impl::ApplyOutcomes(const std::vector<uint8_t>& stepped,
                              const std::vector<uint8_t>& damaged,
                              bool any_damaged, std::vector<double>* rewards) {
  // The outcomes, in order (docs/environment.md, "Outcomes and episode end").
  const int n = config_.n_landers;
  for (int i = 0; i < n; ++i) {
    if (!stepped[i]) continue;
    Lander& lander = landers_[i];
    if (damaged[i]) {
      (*rewards)[i] += config_.damage_reward + config_.terminate_reward;
      lander.active = false;
      if (config_.remove_on_damage) {
        DestroyLanderBodies(lander);
      } else {
        lander.wreck = true;
      }
    } else if (lander.outcome == Outcome::kLanded) {
      (*rewards)[i] += config_.successful_reward;
      lander.active = false;
      DestroyLanderBodies(lander);
    }
  }
  if (config_.terminate_on_damage && any_damaged) {
    for (int i = 0; i < n; ++i) {
      Lander& lander = landers_[i];
      if (!stepped[i] || !lander.active) continue;
      (*rewards)[i] += config_.terminate_reward;
      lander.active = false;
      lander.outcome = Outcome::kAborted;
    }
  }
}

void Env::Impl::TruncateActiveLanders() {
  for (Lander& lander : landers_) {
    if (!lander.active) continue;
    lander.active = false;
    lander.outcome = Outcome::kTruncated;
  }
}

void Env::Impl::ShareRewards(const std::vector<uint8_t>& stepped,
                             std::vector<double>* rewards) const {
  const int n = config_.n_landers;
  double sum = 0.0;
  int count = 0;
  for (int i = 0; i < n; ++i) {
    if (!stepped[i]) continue;
    sum += (*rewards)[i];
    ++count;
  }
  const double mean = sum / count;
  for (int i = 0; i < n; ++i) {
    if (stepped[i]) (*rewards)[i] = mean;
  }
}

void Env::Impl::UpdateEpisodes(const std::vector<uint8_t>& stepped,
                               const std::vector<double>& rewards) {
  num_active_ = 0;
  for (int i = 0; i < config_.n_landers; ++i) {
    Lander& lander = landers_[i];
    if (stepped[i]) {
      lander.episode_return += rewards[i];
      ++lander.episode_length;
    }
    if (lander.active) ++num_active_;
  }
}

void Env::Impl::FillResult(const std::vector<uint8_t>& stepped,
                           const std::vector<double>& rewards,
                           StepResult* result) const {
  const int n = config_.n_landers;
  result->observations.assign(static_cast<size_t>(n) * kObservationSize, 0.0f);
  result->rewards.assign(n, 0.0f);
  result->terminations.assign(n, 0);
  result->truncations.assign(n, 0);
  result->stepped = stepped;
  result->outcomes.assign(n, Outcome::kNone);
  for (int i = 0; i < n; ++i) {
    const Lander& lander = landers_[i];
    result->outcomes[i] = lander.outcome;
    if (!stepped[i]) continue;
    std::copy(lander.observation.begin(), lander.observation.end(),
              result->observations.begin() + i * kObservationSize);
    result->rewards[i] = static_cast<float>(rewards[i]);
    const bool truncated = lander.outcome == Outcome::kTruncated;
    result->truncations[i] = truncated ? 1 : 0;
    result->terminations[i] =
        (lander.outcome != Outcome::kNone && !truncated) ? 1 : 0;
  }
  result->episode_over = num_active_ == 0;
}

Scene Env::Impl::MakeScene() const {
  Scene scene;
  scene.width = kW;
  scene.height = kH;
  scene.helipad_x1 = kW / (kChunks - 1) * (kChunks / 2 - 1);
  scene.helipad_x2 = kW / (kChunks - 1) * (kChunks / 2 + 1);
  scene.helipad_y = kHelipadY;
  if (!started_) return scene;
  scene.terrain.assign(terrain_.begin(), terrain_.end());
  scene.cycles = cycles_;
  scene.agents.reserve(config_.n_landers);
  for (int i = 0; i < config_.n_landers; ++i) {
    const Lander& lander = landers_[i];
    scene.agents.push_back(
        {lander.outcome, lander.episode_return, lander.final_parts});
    if (lander.body == nullptr) continue;
    SceneLander drawn;
    drawn.agent = i;
    drawn.wreck = lander.wreck;
    drawn.parts = LanderParts(lander);
    const b2Vec2 position = lander.body->GetPosition();
    drawn.position = {position.x, position.y};
    drawn.angle = lander.body->GetAngle();
    if (lander.active) {
      drawn.main_power = lander.last_command.main_power;
      drawn.side_power = lander.last_command.side_power;
      drawn.side_direction = lander.last_command.side_direction;
    }
    scene.landers.push_back(std::move(drawn));
  }
  for (const Particle& p : particles_) {
    const b2Vec2 position = p.body->GetPosition();
    scene.particles.push_back(
        {{position.x, position.y}, kParticleRadius, p.ttl});
  }
  return scene;
}

absl::Status Env::Impl::SetLanderState(int agent, double x, double y,
                                       double angle, double vx, double vy,
                                       double omega) {
  if (agent < 0 || agent >= config_.n_landers) {
    return absl::InvalidArgumentError(
        absl::StrCat("agent = ", agent, " is out of range: allowed 0..",
                     config_.n_landers - 1));
  }
  for (double value : {x, y, angle, vx, vy, omega}) {
    if (!std::isfinite(value)) {
      return absl::InvalidArgumentError(
          absl::StrCat("lander state value ", value, " is not finite"));
    }
  }
  if (!started_ || landers_[agent].body == nullptr) {
    return absl::FailedPreconditionError(
        absl::StrCat(AgentName(agent), " has no body in the world"));
  }
  Lander& lander = landers_[agent];
  const b2Transform old_body = lander.body->GetTransform();
  const b2Vec2 position(static_cast<float>(x), static_cast<float>(y));
  lander.body->SetTransform(position, static_cast<float>(angle));
  const b2Transform new_body = lander.body->GetTransform();
  const b2Vec2 velocity(static_cast<float>(vx), static_cast<float>(vy));
  for (b2Body* leg : lander.legs) {
    const b2Transform relative = b2MulT(old_body, leg->GetTransform());
    const b2Transform placed = b2Mul(new_body, relative);
    leg->SetTransform(placed.p, new_body.q.GetAngle() + relative.q.GetAngle());
    const b2Vec2 r = placed.p - position;
    leg->SetLinearVelocity(velocity + b2Cross(static_cast<float>(omega), r));
    leg->SetAngularVelocity(static_cast<float>(omega));
    leg->SetAwake(true);
  }
  lander.body->SetLinearVelocity(velocity);
  lander.body->SetAngularVelocity(static_cast<float>(omega));
  lander.body->SetAwake(true);
  return absl::OkStatus();
}

// --- Env: the public face, forwarding to Impl. ---

absl::StatusOr<std::unique_ptr<Env>> Env::Create(const EnvConfig& config) {
  if (absl::Status status = ValidateEnvConfig(config); !status.ok()) {
    return status;
  }
  return std::unique_ptr<Env>(new Env(std::make_unique<Impl>(config)));
}

Env::Env(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
Env::~Env() = default;

const EnvConfig& Env::config() const { return impl_->config_; }
int Env::n_landers() const { return impl_->config_.n_landers; }

void Env::Reset(std::optional<uint64_t> seed, StepResult* result) {
  impl_->Reset(seed, result);
}

absl::Status Env::Step(const ActionsView& actions, StepResult* result) {
  return impl_->Step(actions, result);
}

absl::Status Env::ValidateActions(const ActionsView& actions) const {
  return impl_->ValidateActions(actions);
}

bool Env::episode_started() const { return impl_->started_; }
bool Env::episode_over() const { return impl_->num_active_ == 0; }
bool Env::is_active(int agent) const {
  return impl_->started_ && impl_->landers_[agent].active;
}
int Env::num_active() const { return impl_->num_active_; }
int Env::cycles() const { return impl_->cycles_; }

Outcome Env::outcome(int agent) const {
  return impl_->started_ ? impl_->landers_[agent].outcome : Outcome::kNone;
}
double Env::episode_return(int agent) const {
  return impl_->started_ ? impl_->landers_[agent].episode_return : 0.0;
}
int Env::episode_length(int agent) const {
  return impl_->started_ ? impl_->landers_[agent].episode_length : 0;
}
absl::Span<const float> Env::observation(int agent) const {
  if (!impl_->started_) return {};
  return impl_->landers_[agent].observation;
}

Scene Env::scene() const { return impl_->MakeScene(); }
void Env::AgeParticlesForFrame() { impl_->AgeParticlesForFrame(); }

absl::Status Env::SetLanderStateForTest(int agent, double x, double y,
                                        double angle, double vx, double vy,
                                        double omega) {
  return impl_->SetLanderState(agent, x, y, angle, vx, vy, omega);
}

}  // namespace mll::core
