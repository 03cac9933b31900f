// The paper's collision table I, pair by pair: the filter data our fixtures
// carry, judged by Box2D's own contact filter, and real contacts between
// placed landers.
#include "collision.h"

#include <string>
#include <vector>

#include "box2d/box2d.h"
#include "env_test_util.h"
#include "gtest/gtest.h"
#include "mll/core/env.h"

namespace mll::core {
namespace {

using internal::LanderBodyFilter;
using internal::LegFilter;
using internal::MoonFilter;
using internal::ParticleFilter;

// Asks Box2D's default b2ContactFilter whether fixtures with these filters
// collide.
bool Box2DSaysCollide(const b2Filter& a, const b2Filter& b) {
  b2World world(b2Vec2(0, 0));
  b2PolygonShape box;
  box.SetAsBox(1, 1);
  b2Fixture* fixtures[2];
  const b2Filter* filters[2] = {&a, &b};
  for (int i = 0; i < 2; ++i) {
    b2BodyDef def;
    def.type = b2_dynamicBody;
    b2Body* body = world.CreateBody(&def);
    b2FixtureDef fixture;
    fixture.shape = &box;
    fixture.filter = *filters[i];
    fixtures[i] = body->CreateFixture(&fixture);
  }
  b2ContactFilter filter;
  const bool ab = filter.ShouldCollide(fixtures[0], fixtures[1]);
  EXPECT_EQ(ab, filter.ShouldCollide(fixtures[1], fixtures[0]));
  return ab;
}

TEST(CollisionTest, TableOnePairByPair) {
  struct Row {
    std::string name;
    b2Filter a;
    b2Filter b;
    bool collide;
  };
  const std::vector<Row> table = {
      {"lander-lander", LanderBodyFilter(0), LanderBodyFilter(1), true},
      {"lander-leg", LanderBodyFilter(0), LegFilter(1), true},
      {"lander-particle", LanderBodyFilter(0), ParticleFilter(), false},
      {"lander-moon", LanderBodyFilter(0), MoonFilter(), true},
      {"leg-leg", LegFilter(0), LegFilter(1), true},
      {"leg-particle", LegFilter(0), ParticleFilter(), false},
      {"leg-moon", LegFilter(0), MoonFilter(), true},
      {"particle-moon", ParticleFilter(), MoonFilter(), true},
      {"particle-particle", ParticleFilter(), ParticleFilter(), false},
      {"moon-moon", MoonFilter(), MoonFilter(), true},
      // One lander's own parts never collide (shared negative group).
      {"own body-leg", LanderBodyFilter(3), LegFilter(3), false},
      {"own leg-leg", LegFilter(3), LegFilter(3), false},
  };
  for (const Row& row : table) {
    EXPECT_EQ(Box2DSaysCollide(row.a, row.b), row.collide) << row.name;
  }
  // Table II's bits.
  EXPECT_EQ(MoonFilter().categoryBits, 0x1);
  EXPECT_EQ(LanderBodyFilter(0).categoryBits, 0x2);
  EXPECT_EQ(LegFilter(0).categoryBits, 0x4);
  EXPECT_EQ(ParticleFilter().categoryBits, 0x8);
  EXPECT_EQ(LanderBodyFilter(4).groupIndex, -5);
  EXPECT_EQ(LegFilter(4).groupIndex, -5);
}

EnvConfig TwoLanders() {
  EnvConfig config;
  config.n_landers = 2;
  config.shared_reward = false;
  config.terminate_on_damage = false;
  return config;
}

TEST(CollisionTest, LandersLegsAndMoonReallyCollide) {
  // Lander-moon: an upside-down drop damages (body touched the moon).
  {
    auto env = testing::MakeEnv(TwoLanders());
    StepResult r;
    env->Reset(4, &r);
    testing::PlaceUpsideDownOnPad(*env, 0);
    testing::StepUntilDone(*env, 0, {1}, 100);
    EXPECT_EQ(env->outcome(0), Outcome::kCrashed);
  }
  // Lander-lander, leg-leg: two landers flying into each other side by side
  // both end crashed; so does a lander falling onto the other.
  for (const double dy : {0.0, 1.2}) {
    auto env = testing::MakeEnv(TwoLanders());
    StepResult r;
    env->Reset(4, &r);
    ASSERT_TRUE(env->SetLanderStateForTest(0, 6.0, 9.0 + dy, 0, 4, 0, 0).ok());
    ASSERT_TRUE(env->SetLanderStateForTest(1, 6.0 + (dy > 0 ? 0.0 : 3.0), 9.0,
                                           0, dy > 0 ? 0 : -4, 0, 0)
                    .ok());
    for (int s = 0; s < 60 && env->num_active() > 0; ++s)
      testing::StepNoop(*env);
    EXPECT_EQ(env->outcome(0), Outcome::kCrashed) << "dy " << dy;
    EXPECT_EQ(env->outcome(1), Outcome::kCrashed) << "dy " << dy;
  }
}

TEST(CollisionTest, ALanderNeverCollidesWithItsOwnLegs) {
  // A free-falling lander held high for many steps, spun fast: its legs
  // sweep through its body's neighbourhood and nothing is ever damaged.
  auto env = testing::MakeEnv(TwoLanders());
  StepResult r;
  env->Reset(4, &r);
  for (int s = 0; s < 100; ++s) {
    testing::HoldHigh(*env, 1, 16.0);
    ASSERT_TRUE(
        env->SetLanderStateForTest(0, 6.0, 10.0, 0.1 * s, 0, 0, 8.0).ok());
    testing::StepNoop(*env);
    ASSERT_TRUE(env->is_active(0)) << "step " << s;
  }
}

TEST(CollisionTest, ParticlesRestOnTheMoonAndNeverTouchLanders) {
  EnvConfig config = TwoLanders();
  config.render_mode = RenderMode::kRgbArray;
  auto env = testing::MakeEnv(config);
  StepResult r;
  env->Reset(4, &r);
  // Lander 0 hovers low over the pad firing its main engine at the ground.
  bool seen = false;
  for (int s = 0; s < 40; ++s) {
    ASSERT_TRUE(env->SetLanderStateForTest(0, testing::kPadX,
                                           testing::kPadY + 1.5, 0, 0, 0, 0)
                    .ok());
    testing::HoldHigh(*env, 1, 16.0);
    testing::StepAll(*env, {2, 0});
    for (const SceneParticle& p : env->scene().particles) {
      seen = true;
      // The moon stops them: never below the pad surface (minus radius).
      EXPECT_GT(p.position.y, testing::kPadY - 2 * p.radius);
    }
  }
  EXPECT_TRUE(seen);
  EXPECT_TRUE(env->is_active(0)) << "exhaust hitting the pad is no damage";
}

}  // namespace
}  // namespace mll::core
