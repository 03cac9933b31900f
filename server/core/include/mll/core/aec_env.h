// PettingZoo's AEC (turn-by-turn) mode as a thin adapter over Env's one
// parallel step: actions are buffered until the last active agent has acted,
// then the world steps once. This class adds bookkeeping only, mirroring
// pettingzoo.AECEnv's helpers (_accumulate_rewards, _clear_rewards,
// _was_dead_step, _deads_step_first) so that a client can copy its state into
// a pettingzoo.AECEnv verbatim. No rule of the game lives here.
#ifndef MLL_CORE_AEC_ENV_H_
#define MLL_CORE_AEC_ENV_H_

#include <optional>
#include <vector>

#include "absl/status/status.h"
#include "absl/types/span.h"
#include "mll/core/env.h"

namespace mll::core {

class AecEnv {
 public:
  // `env` is not owned and must outlive this adapter. All stepping of `env`
  // while in AEC mode goes through this adapter.
  explicit AecEnv(Env* env);

  // Resets the underlying Env and the turn order (agent_selection = lander_0).
  // `result`, when given, receives the reset's result as Env::Reset gives it.
  void Reset(std::optional<uint64_t> seed, StepResult* result = nullptr);

  // Acts for agent_selection. `action` must be absent exactly when
  // agent_selection is terminated or truncated (PettingZoo's dead step),
  // else FAILED_PRECONDITION naming the agent. FAILED_PRECONDITION before
  // Reset or when no agent is left; INVALID_ARGUMENT for a bad action value.
  absl::Status Step(const std::optional<AgentAction>& action);

  // PettingZoo's `agents`: agent indices still in the cycle, in order,
  // including done agents that have not taken their dead step yet.
  const std::vector<int>& agents() const;
  // PettingZoo's `agent_selection`, or -1 when `agents` is empty.
  int agent_selection() const;

  // Per-agent state, valid for agents in agents().
  float reward(int agent) const;             // PettingZoo's `rewards`.
  float cumulative_reward(int agent) const;  // `_cumulative_rewards`.
  bool terminated(int agent) const;
  bool truncated(int agent) const;
  // The agent's latest observation (observe(agent)).
  absl::Span<const float> observe(int agent) const;

  const Env& env() const;

 private:
  // pettingzoo.AECEnv's helpers, same names, same behaviour.
  void WasDeadStep();
  void DeadsStepFirst();
  void ClearRewards();
  void AccumulateRewards();
  // pettingzoo.utils.AgentSelector: reinit(order) and next().
  void SelectorReinit(std::vector<int> order);
  int SelectorNext();

  Env* env_;
  std::vector<int> agents_;
  int agent_selection_ = -1;
  // PettingZoo's _skip_agent_selection (-1 for None): the live agent to
  // resume with once the dead agents have taken their dead steps.
  int skip_agent_selection_ = -1;
  // AgentSelector state: the live agents of the current cycle, the index of
  // the next one and the one last returned.
  std::vector<int> selector_order_;
  int selector_current_ = 0;
  int selector_selected_ = -1;
  // Indexed by agent; entries of agents not in agents_ are stale.
  std::vector<float> rewards_;
  std::vector<float> cumulative_rewards_;
  std::vector<uint8_t> terminations_;
  std::vector<uint8_t> truncations_;
  std::vector<AgentAction> buffered_actions_;
  StepResult step_result_;
};

}  // namespace mll::core

#endif  // MLL_CORE_AEC_ENV_H_
