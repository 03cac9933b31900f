// Spawn: for every n in 1..32 no two landers touch and nobody touches the
// terrain after the reset's no-op step, so nobody starts damaged.
#include <algorithm>
#include <cmath>
#include <vector>

#include "env_test_util.h"
#include "gtest/gtest.h"
#include "mll/core/env.h"

namespace mll::core {
namespace {

// Box2D reports a touching contact once two polygons come within their skins
// (2 * b2_linearSlop = 1 cm); a larger gap means no contact, no damage.
constexpr double kClearance = 0.02;

// Separating-axis gap between two convex polygons (negative if they overlap).
double Gap(const ScenePolygon& a, const ScenePolygon& b) {
  double best = -1e9;
  for (const ScenePolygon* p : {&a, &b}) {
    const auto& v = p->vertices;
    for (size_t i = 0; i < v.size(); ++i) {
      const Vec2& p1 = v[i];
      const Vec2& p2 = v[(i + 1) % v.size()];
      double nx = p2.y - p1.y;
      double ny = p1.x - p2.x;
      const double len = std::hypot(nx, ny);
      nx /= len;
      ny /= len;
      auto project = [nx, ny](const ScenePolygon& q, double* lo, double* hi) {
        *lo = 1e9;
        *hi = -1e9;
        for (const Vec2& w : q.vertices) {
          const double d = w.x * nx + w.y * ny;
          *lo = std::min(*lo, d);
          *hi = std::max(*hi, d);
        }
      };
      double alo, ahi, blo, bhi;
      project(a, &alo, &ahi);
      project(b, &blo, &bhi);
      best = std::max(best, std::max(blo - ahi, alo - bhi));
    }
  }
  return best;
}

double TerrainHeight(const Scene& scene, double x) {
  const auto& t = scene.terrain;
  for (size_t i = 0; i + 1 < t.size(); ++i) {
    if (x <= t[i + 1].x) {
      const double f = (x - t[i].x) / (t[i + 1].x - t[i].x);
      return t[i].y + f * (t[i + 1].y - t[i].y);
    }
  }
  return t.back().y;
}

TEST(EnvSpawnTest, EveryLanderCountSpawnsApartAndUndamaged) {
  for (int n = 1; n <= kMaxLanders; ++n) {
    for (uint64_t seed : {0, 1, 2, 3}) {
      EnvConfig config;
      config.n_landers = n;
      config.terminate_on_damage = false;
      auto env = testing::MakeEnv(config);
      StepResult result;
      env->Reset(seed, &result);
      ASSERT_EQ(env->num_active(), n);
      // After the reset's no-op step: no two landers' parts within
      // kClearance, no part near the terrain.
      const Scene scene = env->scene();
      ASSERT_EQ(static_cast<int>(scene.landers.size()), n);
      for (int i = 0; i < n; ++i) {
        for (const ScenePolygon& part : scene.landers[i].parts) {
          for (const Vec2& v : part.vertices) {
            EXPECT_GT(v.y, TerrainHeight(scene, v.x) + kClearance)
                << "n " << n << " seed " << seed << " lander " << i;
          }
          for (int j = i + 1; j < n; ++j) {
            for (const ScenePolygon& other : scene.landers[j].parts) {
              EXPECT_GT(Gap(part, other), kClearance)
                  << "n " << n << " seed " << seed << " landers " << i << ", "
                  << j;
            }
          }
        }
      }
      if (n <= 7) {  // The paper's single row at y = H (see env.cc).
        for (int i = 0; i < n; ++i) {
          EXPECT_NEAR(result.observations[i * kObservationSize + 0],
                      ((i + 1) * 20.0 / (n + 1) - 10.0) / 10.0, 0.05);
        }
      }
      // Nothing touched during the no-op step: with every lander stopped
      // where it is, the next step damages nobody. (Contact flags set during
      // the no-op step would count here.)
      for (int i = 0; i < n; ++i) {
        const auto o = env->observation(i);
        ASSERT_TRUE(
            env->SetLanderStateForTest(i, o[0] * 10.0 + 10.0,
                                       o[1] * (20.0 / 3.0) + 10.0 / 3.0 + 0.6,
                                       o[4], 0, 0, 0)
                .ok());
      }
      const StepResult still = testing::StepNoop(*env);
      for (int i = 0; i < n; ++i) {
        EXPECT_EQ(still.outcomes[i], Outcome::kNone)
            << "n " << n << " seed " << seed << " lander " << i;
      }
    }
  }
}

}  // namespace
}  // namespace mll::core
