// One Multi Lunar Lander environment: N landers in one Box2D world, with the
// physics of Gymnasium's LunarLander-v3 and the paper's collision, damage,
// landing and reward rules. docs/environment.md is the reference; this
// header is the only way into it (no Box2D type appears here).
//
// Threading: an Env is not thread-safe; callers serialise access to one Env.
// Different Env objects share nothing and can be stepped concurrently.
//
// Determinism: one generator per Env, seeded by Reset(seed). The draw order is
// fixed (see env.cc): at reset, 12 terrain heights, then for each lander in
// index order its push (x, y) and, with wind, its wind and torque indices; at
// each step, for each active lander in index order, two engine dispersions.
// Rendering never draws from the generator.
#ifndef MLL_CORE_ENV_H_
#define MLL_CORE_ENV_H_

#include <array>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "absl/types/span.h"
#include "mll/core/env_config.h"
#include "mll/core/scene.h"

namespace mll::core {

// mll/env_spec.h (through env_config.h): shared with the service and the
// client.
using ::mll::kContinuousActionSize;
using ::mll::kDiscreteActionCount;
using ::mll::kObservationSize;

// How a lander's episode ended (or kNone while it is active).
enum class Outcome : uint8_t {
  kNone = 0,
  kLanded = 1,
  kCrashed = 2,      // Damaged by a contact (docs/environment.md, "Outcomes").
  kOutOfBounds = 3,  // abs(observation[0]) >= 1.
  kTruncated = 4,    // Reached max_cycles.
  kAborted = 5,      // Terminated because another lander was damaged
                     // (terminate_on_damage).
};

// "none", "landed", "crashed", "out_of_bounds", "truncated", "aborted".
absl::string_view OutcomeName(Outcome outcome);

// `lander_<index>`.
std::string AgentName(int agent_index);

// The actions of one step, indexed by agent. Exactly one span is used,
// according to EnvConfig::continuous; entries of agents that are not active
// are ignored (not validated).
struct ActionsView {
  // Size n_landers, values 0..3, when !continuous.
  absl::Span<const int32_t> discrete;
  // Size 2 * n_landers, row-major [agent][main, lateral], when continuous.
  // Finite values are clipped to [-1, 1]; NaN or infinity is an error.
  absl::Span<const float> continuous;
};

// The action of one agent (AEC mode). Which member is read depends on
// EnvConfig::continuous.
struct AgentAction {
  int32_t discrete = 0;
  std::array<float, kContinuousActionSize> continuous = {0.0f, 0.0f};
};

// What Reset and Step produce. Arrays are indexed by agent; rows of agents
// that were not stepped (done before this step) are zero.
struct StepResult {
  // [n_landers * 12], row-major.
  std::vector<float> observations;
  // [n_landers]
  std::vector<float> rewards;
  // [n_landers], 0/1.
  std::vector<uint8_t> terminations;
  // [n_landers], 0/1.
  std::vector<uint8_t> truncations;
  // [n_landers], 1 when the agent was active at the start of this step (all
  // agents after Reset): its row carries a result.
  std::vector<uint8_t> stepped;
  // [n_landers], each agent's outcome so far.
  std::vector<Outcome> outcomes;
  // No agent is active any more.
  bool episode_over = false;
};

class Env {
 public:
  // Validates the config (INVALID_ARGUMENT naming the field) and builds an
  // environment whose episode has not started: Reset() must come first.
  static absl::StatusOr<std::unique_ptr<Env>> Create(const EnvConfig& config);

  ~Env();
  Env(const Env&) = delete;
  Env& operator=(const Env&) = delete;

  const EnvConfig& config() const;
  int n_landers() const;

  // Starts a new episode: new terrain, landers spawned and pushed, one no-op
  // world step (not counted towards max_cycles). `seed` reseeds the generator;
  // without it the generator's stream continues (a never-seeded Env starts
  // from seed 0). Fills `result` with every agent's observation, zero rewards.
  void Reset(std::optional<uint64_t> seed, StepResult* result);

  // One parallel step. FAILED_PRECONDITION before the first Reset or after
  // the episode is over; INVALID_ARGUMENT for a bad action (naming the agent,
  // the value and the allowed range), checked before any physics runs.
  absl::Status Step(const ActionsView& actions, StepResult* result);

  // The checks Step makes on `actions`, without stepping.
  absl::Status ValidateActions(const ActionsView& actions) const;

  // Reset has been called at least once.
  bool episode_started() const;
  // No agent is active (true before the first Reset).
  bool episode_over() const;
  // Agent has not terminated or been truncated in this episode.
  bool is_active(int agent) const;
  int num_active() const;
  // World steps taken this episode, not counting the reset's no-op step.
  int cycles() const;

  // Per-agent episode bookkeeping (valid after Reset).
  Outcome outcome(int agent) const;
  double episode_return(int agent) const;
  int episode_length(int agent) const;
  // The agent's latest observation (its final one once it is done).
  absl::Span<const float> observation(int agent) const;

  // Geometry for drawing, in world units (meters).
  Scene scene() const;
  // Ages particles by one rendered frame (Gymnasium: ttl -= 0.15 per frame)
  // and removes the expired ones. No-op without a render mode.
  void AgeParticlesForFrame();

  // Test-only hook: places an agent still in the world (active or a wreck)
  // at body position (x, y) m, angle rad, with linear velocity (vx, vy) m/s
  // and angular velocity omega rad/s; its legs move rigidly with the body.
  // Lets tests set up exact contact scenarios. Changes no rule and draws no
  // random number. FAILED_PRECONDITION before Reset or when the agent's
  // bodies are gone; INVALID_ARGUMENT for a bad index or non-finite value.
  absl::Status SetLanderStateForTest(int agent, double x, double y,
                                     double angle, double vx, double vy,
                                     double omega);

 private:
  class Impl;
  explicit Env(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace mll::core

#endif  // MLL_CORE_ENV_H_
