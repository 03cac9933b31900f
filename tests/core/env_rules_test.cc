// The rules of one step (docs/environment.md): damage, leg contact,
// landing, outcomes and terminal rewards, set up with exact placements.
#include <cmath>
#include <vector>

#include "env_test_util.h"
#include "gtest/gtest.h"
#include "mll/core/env.h"

namespace mll::core {
namespace {

using testing::HoldHigh;
using testing::kPadX;
using testing::kPadY;
using testing::MakeEnv;
using testing::PlaceRestingOnPad;
using testing::PlaceUpsideDownOnPad;
using testing::StepNoop;
using testing::StepUntilDone;

// Three landers, nothing shared or cascading, so each rule shows alone.
EnvConfig Independent() {
  EnvConfig config;
  config.n_landers = 3;
  config.shared_reward = false;
  config.terminate_on_damage = false;
  return config;
}

// Resets, then holds every lander high for a few steps: the leg joints start
// outside their limits and take about 5 steps to swing the legs out, and a
// lander placed on the pad before that would land on its body.
std::unique_ptr<Env> ResetEnv(const EnvConfig& config, uint64_t seed = 3) {
  auto env = MakeEnv(config);
  StepResult result;
  env->Reset(seed, &result);
  for (int s = 0; s < 10; ++s) {
    for (int i = 0; i < config.n_landers; ++i) HoldHigh(*env, i, 2.0 + 3 * i);
    StepNoop(*env);
  }
  return env;
}

bool InScene(const Env& env, int agent) {
  for (const SceneLander& lander : env.scene().landers) {
    if (lander.agent == agent) return true;
  }
  return false;
}

TEST(EnvRulesTest, BodyOnTheMoonCrashes) {
  auto env = ResetEnv(Independent());
  PlaceUpsideDownOnPad(*env, 0);
  const auto results = StepUntilDone(*env, 0, {1, 2});
  ASSERT_FALSE(env->is_active(0));
  EXPECT_EQ(env->outcome(0), Outcome::kCrashed);
  const StepResult& last = results.back();
  EXPECT_EQ(last.terminations[0], 1);
  EXPECT_EQ(last.truncations[0], 0);
  // Damage and terminate rewards (-100 each) on top of the shaping delta.
  EXPECT_LT(last.rewards[0], -150.0f);
  EXPECT_TRUE(env->is_active(1));
  EXPECT_TRUE(env->is_active(2));
  EXPECT_FALSE(InScene(*env, 0)) << "remove_on_damage keeps no wreck";
}

TEST(EnvRulesTest, LegTouchingAnotherLanderDamagesBoth) {
  auto env = ResetEnv(Independent());
  // Lander 0's legs[0] hangs at x + 20/30, feet about 0.87 m below its
  // centre; lander 1's body top is 17/30 above its centre. Drop the one leg
  // onto the other's roof.
  ASSERT_TRUE(
      env->SetLanderStateForTest(1, 5.0 + 20.0 / 30, 8.0, 0, 0, 0, 0).ok());
  ASSERT_TRUE(env->SetLanderStateForTest(0, 5.0, 8.0 + 1.6, 0, 0, -3, 0).ok());
  for (int s = 0; s < 40 && env->is_active(0); ++s) {
    HoldHigh(*env, 2, 15.0);
    ASSERT_TRUE(env->is_active(1) || !env->is_active(0));
    StepNoop(*env);
  }
  EXPECT_EQ(env->outcome(0), Outcome::kCrashed);
  EXPECT_EQ(env->outcome(1), Outcome::kCrashed);
  EXPECT_TRUE(env->is_active(2));
}

TEST(EnvRulesTest, BodyTouchingAnotherLanderDamagesBoth) {
  auto env = ResetEnv(Independent());
  // Straight above: lander 0's legs straddle lander 1's body, so the bodies
  // meet first.
  ASSERT_TRUE(env->SetLanderStateForTest(1, 5.0, 8.0, 0, 0, 0, 0).ok());
  ASSERT_TRUE(env->SetLanderStateForTest(0, 5.0, 8.0 + 1.0, 0, 0, -2, 0).ok());
  for (int s = 0; s < 40 && env->is_active(0); ++s) {
    HoldHigh(*env, 2, 15.0);
    StepNoop(*env);
  }
  EXPECT_EQ(env->outcome(0), Outcome::kCrashed);
  EXPECT_EQ(env->outcome(1), Outcome::kCrashed);
}

TEST(EnvRulesTest, LeavingTheViewportIsOutOfBounds) {
  auto env = ResetEnv(Independent());
  ASSERT_TRUE(env->SetLanderStateForTest(0, 0.5, 10.0, 0, -20, 0, 0).ok());
  StepUntilDone(*env, 0, {1, 2}, 20);
  EXPECT_EQ(env->outcome(0), Outcome::kOutOfBounds);
  EXPECT_GE(std::abs(env->observation(0)[0]), 1.0f);
}

TEST(EnvRulesTest, LegGroundContactOnAndOff) {
  auto env = ResetEnv(Independent());
  PlaceRestingOnPad(*env, 0);
  bool both = false;
  for (int s = 0; s < 30 && !both; ++s) {
    HoldHigh(*env, 1, 2.0);
    HoldHigh(*env, 2, 15.0);
    const StepResult r = StepNoop(*env);
    both = r.observations[6] == 1.0f && r.observations[7] == 1.0f;
  }
  ASSERT_TRUE(both) << "legs never touched the pad";
  ASSERT_TRUE(env->is_active(0));
  // Lift it high: both contacts end.
  ASSERT_TRUE(env->SetLanderStateForTest(0, kPadX, 10.0, 0, 0, 0, 0).ok());
  const StepResult r = StepNoop(*env);
  EXPECT_EQ(r.observations[6], 0.0f);
  EXPECT_EQ(r.observations[7], 0.0f);
  EXPECT_TRUE(env->is_active(0)) << "leg contact with the moon is no damage";
}

TEST(EnvRulesTest, LanderAtRestLandsOnceAndIsRemoved) {
  auto env = ResetEnv(Independent());
  PlaceRestingOnPad(*env, 0);
  const auto results = StepUntilDone(*env, 0, {1, 2});
  ASSERT_EQ(env->outcome(0), Outcome::kLanded);
  const StepResult& landing = results.back();
  EXPECT_EQ(landing.terminations[0], 1);
  EXPECT_GT(landing.rewards[0], 90.0f);  // successful_reward + tiny delta.
  EXPECT_LT(landing.rewards[0], 110.0f);
  // Step 0 carries the shaping jump of the placement itself.
  int rewarded = 0;
  for (size_t s = 1; s < results.size(); ++s) {
    rewarded += results[s].rewards[0] > 50.0f;
  }
  EXPECT_EQ(rewarded, 1);
  EXPECT_FALSE(InScene(*env, 0));

  // The others fly on; the landed lander is never stepped or rewarded again
  // and is nobody's neighbour.
  for (int s = 0; s < 5; ++s) {
    HoldHigh(*env, 1, 2.0);
    HoldHigh(*env, 2, 15.0);
    const StepResult r = StepNoop(*env);
    EXPECT_EQ(r.stepped[0], 0);
    EXPECT_EQ(r.rewards[0], 0.0f);
    EXPECT_EQ(r.terminations[0], 0);
    EXPECT_EQ(r.stepped[1], 1);
    // Lander 1's nearest is lander 2; the second neighbour slot is empty.
    EXPECT_EQ(r.observations[12 + 10], 0.0f);
    EXPECT_EQ(r.observations[12 + 11], 0.0f);
    EXPECT_NE(r.observations[12 + 8], 0.0f);
  }
  EXPECT_EQ(env->episode_length(0), 10 + static_cast<int>(results.size()));
}

TEST(EnvRulesTest, NeighboursAreTheTwoNearestNearestFirst) {
  EnvConfig config = Independent();
  config.n_landers = 4;
  auto env = ResetEnv(config);
  // Lander 0 at (10, 10); 1 far, 2 nearest, 3 second.
  const double xs[4] = {10.0, 2.0, 11.5, 7.0};
  for (int i = 0; i < 4; ++i) {
    ASSERT_TRUE(env->SetLanderStateForTest(i, xs[i], 10.0, 0, 0, 0, 0).ok());
  }
  const StepResult r = StepNoop(*env);
  const float* o = &r.observations[0];
  const float x0 = o[0];  // Normalised x of lander 0.
  const float x2 = r.observations[2 * 12];
  const float x3 = r.observations[3 * 12];
  EXPECT_NEAR(o[8], x0 - x2, 1e-5);
  EXPECT_NEAR(o[10], x0 - x3, 1e-5);
  // obs[1] shares the neighbour term's scale, H/2.
  EXPECT_NEAR(o[9], o[1] - r.observations[2 * 12 + 1], 1e-5);
  EXPECT_NEAR(o[11], o[1] - r.observations[3 * 12 + 1], 1e-5);
}

TEST(EnvRulesTest, WreckStaysAndCollidesWithoutRemoveOnDamage) {
  EnvConfig config = Independent();
  config.remove_on_damage = false;
  auto env = ResetEnv(config);
  PlaceUpsideDownOnPad(*env, 0);
  StepUntilDone(*env, 0, {1, 2});
  ASSERT_EQ(env->outcome(0), Outcome::kCrashed);
  const Scene scene = env->scene();
  ASSERT_FALSE(scene.landers.empty());
  EXPECT_EQ(scene.landers[0].agent, 0);
  EXPECT_TRUE(scene.landers[0].wreck);
  EXPECT_EQ(scene.landers[0].parts.size(), 3u);
  // A lander dropped on the wreck is damaged by it.
  ASSERT_TRUE(
      env->SetLanderStateForTest(1, kPadX, kPadY + 2.5, 0, 0, -3, 0).ok());
  StepUntilDone(*env, 1, {2}, 60);
  EXPECT_EQ(env->outcome(1), Outcome::kCrashed);
}

TEST(EnvRulesTest, TerminateOnDamageAbortsTheOthers) {
  EnvConfig config = Independent();
  config.terminate_on_damage = true;
  config.terminate_reward = -11.0;
  auto env = ResetEnv(config);
  PlaceUpsideDownOnPad(*env, 0);
  const auto results = StepUntilDone(*env, 0, {1, 2});
  ASSERT_EQ(env->outcome(0), Outcome::kCrashed);
  EXPECT_EQ(env->outcome(1), Outcome::kAborted);
  EXPECT_EQ(env->outcome(2), Outcome::kAborted);
  const StepResult& last = results.back();
  EXPECT_TRUE(last.episode_over);
  EXPECT_EQ(last.terminations[1], 1);
  EXPECT_EQ(last.terminations[2], 1);
  StepResult after;
  const absl::Status status =
      env->Step(ActionsView{std::vector<int32_t>(3, 0), {}}, &after);
  EXPECT_EQ(status.code(), absl::StatusCode::kFailedPrecondition);
}

// The three terminal rewards: two runs that differ only in those values give
// rewards that differ by exactly the configured difference, on the step of
// the event and nowhere else.
std::vector<StepResult> CrashRun(const EnvConfig& config, bool land) {
  auto env = ResetEnv(config);
  if (land) {
    PlaceRestingOnPad(*env, 0);
  } else {
    PlaceUpsideDownOnPad(*env, 0);
  }
  return StepUntilDone(*env, 0, {1, 2});
}

void ExpectRewardShift(const std::vector<StepResult>& base,
                       const std::vector<StepResult>& changed, int agent,
                       double shift_at_last) {
  ASSERT_EQ(base.size(), changed.size());
  for (size_t s = 0; s < base.size(); ++s) {
    const double expected = s + 1 == base.size() ? shift_at_last : 0.0;
    EXPECT_NEAR(changed[s].rewards[agent] - base[s].rewards[agent], expected,
                1e-3)
        << "step " << s;
  }
}

TEST(EnvRulesTest, DamageAndTerminateRewardsAddOnCrash) {
  EnvConfig base = Independent();
  EnvConfig changed = base;
  changed.damage_reward = -7.0;
  changed.terminate_reward = -11.0;
  ExpectRewardShift(CrashRun(base, false), CrashRun(changed, false), 0,
                    (-7.0 - 11.0) - (-100.0 - 100.0));
}

TEST(EnvRulesTest, SuccessfulRewardAddsOnLanding) {
  EnvConfig base = Independent();
  EnvConfig changed = base;
  changed.successful_reward = 5.0;
  ExpectRewardShift(CrashRun(base, true), CrashRun(changed, true), 0,
                    5.0 - 100.0);
}

TEST(EnvRulesTest, TerminateRewardReachesAbortedLanders) {
  EnvConfig base = Independent();
  base.terminate_on_damage = true;
  EnvConfig changed = base;
  changed.terminate_reward = -11.0;
  ExpectRewardShift(CrashRun(base, false), CrashRun(changed, false), 1,
                    -11.0 - (-100.0));
}

TEST(EnvRulesTest, SharedRewardIsTheMeanOfTheLandersStepped) {
  EnvConfig unshared = Independent();
  EnvConfig shared = unshared;
  shared.shared_reward = true;
  // Same physics: lander 0 lands, then the others fly on for a while.
  const auto a = CrashRun(unshared, true);
  const auto b = CrashRun(shared, true);
  ASSERT_EQ(a.size(), b.size());
  for (size_t s = 0; s < a.size(); ++s) {
    const double mean = (static_cast<double>(a[s].rewards[0]) +
                         a[s].rewards[1] + a[s].rewards[2]) /
                        3;
    for (int i = 0; i < 3; ++i) EXPECT_NEAR(b[s].rewards[i], mean, 1e-3);
  }
  // After the landing, lander 0's +100 never reaches the others' mean.
  auto env = ResetEnv(shared);
  auto env_unshared = ResetEnv(unshared);
  for (Env* e : {env.get(), env_unshared.get()}) {
    PlaceRestingOnPad(*e, 0);
    StepUntilDone(*e, 0, {1, 2});
    ASSERT_EQ(e->outcome(0), Outcome::kLanded);
  }
  for (int s = 0; s < 10; ++s) {
    const StepResult rs = StepNoop(*env);
    const StepResult ru = StepNoop(*env_unshared);
    const double mean =
        (static_cast<double>(ru.rewards[1]) + ru.rewards[2]) / 2;
    EXPECT_EQ(rs.rewards[0], 0.0f);
    EXPECT_NEAR(rs.rewards[1], mean, 1e-3);
    EXPECT_NEAR(rs.rewards[2], mean, 1e-3);
    EXPECT_LT(std::abs(mean), 50.0);
  }
}

TEST(EnvRulesTest, EpisodeReturnIsTheSumOfRewards) {
  auto env = ResetEnv(Independent());
  const double before = env->episode_return(0);
  const int length_before = env->episode_length(0);
  EXPECT_EQ(length_before, 10);  // ResetEnv's holding steps.
  PlaceUpsideDownOnPad(*env, 0);
  const auto results = StepUntilDone(*env, 0, {1, 2});
  double sum = 0.0;
  for (const StepResult& r : results) sum += r.rewards[0];
  EXPECT_NEAR(env->episode_return(0) - before, sum, 1e-3);
  EXPECT_EQ(env->episode_length(0) - length_before,
            static_cast<int>(results.size()));
}

}  // namespace
}  // namespace mll::core
