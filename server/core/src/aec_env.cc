#include "mll/core/aec_env.h"

#include <algorithm>
#include <utility>

#include "absl/strings/str_cat.h"
#include "engine_command.h"

namespace mll::core {

// The step and its helpers follow pettingzoo.AECEnv (utils/env.py) and the
// buffered-action pattern of pettingzoo's sisl/multiwalker step() line by
// line, so that a client copying agents, agent_selection, rewards,
// _cumulative_rewards, terminations and truncations into a real AECEnv sees
// exactly what PettingZoo would compute.

AecEnv::AecEnv(Env* env) : env_(env) {}

void AecEnv::Reset(std::optional<uint64_t> seed, StepResult* result) {
  env_->Reset(seed, &step_result_);
  if (result != nullptr) *result = step_result_;
  const int n = env_->n_landers();
  agents_.resize(n);
  for (int i = 0; i < n; ++i) agents_[i] = i;
  SelectorReinit(agents_);
  agent_selection_ = SelectorNext();
  skip_agent_selection_ = -1;
  rewards_.assign(n, 0.0f);
  cumulative_rewards_.assign(n, 0.0f);
  terminations_.assign(n, 0);
  truncations_.assign(n, 0);
  buffered_actions_.assign(n, AgentAction());
}

absl::Status AecEnv::Step(const std::optional<AgentAction>& action) {
  if (!env_->episode_started()) {
    return absl::FailedPreconditionError("step before reset: call Reset first");
  }
  if (agents_.empty()) {
    return absl::FailedPreconditionError(
        "step after the episode is over: no agent is left, call Reset");
  }
  const int agent = agent_selection_;
  if (terminations_[agent] || truncations_[agent]) {
    if (action.has_value()) {
      return absl::FailedPreconditionError(
          absl::StrCat(AgentName(agent),
                       " is done: its only valid step is a dead step with no "
                       "action"));
    }
    WasDeadStep();
    return absl::OkStatus();
  }
  if (!action.has_value()) {
    return absl::FailedPreconditionError(
        absl::StrCat(AgentName(agent),
                     " is active: an action is required (a step without "
                     "one is only for done agents)"));
  }
  if (absl::Status status = internal::ValidateAgentAction(
          env_->config().continuous, agent, *action);
      !status.ok()) {
    return status;
  }
  buffered_actions_[agent] = *action;

  const bool is_last = selector_selected_ == selector_order_.back();
  if (is_last) {
    const int n = env_->n_landers();
    std::vector<int32_t> discrete(n);
    std::vector<float> continuous(2 * static_cast<size_t>(n));
    for (int i = 0; i < n; ++i) {
      discrete[i] = buffered_actions_[i].discrete;
      continuous[2 * i] = buffered_actions_[i].continuous[0];
      continuous[2 * i + 1] = buffered_actions_[i].continuous[1];
    }
    ActionsView view;
    view.discrete = discrete;
    view.continuous = continuous;
    if (absl::Status status = env_->Step(view, &step_result_); !status.ok()) {
      return status;
    }
    for (int a : agents_) {
      rewards_[a] = step_result_.rewards[a];
      terminations_[a] = step_result_.terminations[a];
      truncations_[a] = step_result_.truncations[a];
    }
    std::vector<int> live;
    for (int a : agents_) {
      if (!terminations_[a] && !truncations_[a]) live.push_back(a);
    }
    SelectorReinit(std::move(live));
  } else {
    ClearRewards();
  }
  if (!selector_order_.empty()) agent_selection_ = SelectorNext();
  cumulative_rewards_[agent] = 0.0f;
  AccumulateRewards();
  DeadsStepFirst();
  return absl::OkStatus();
}

void AecEnv::WasDeadStep() {
  agents_.erase(std::find(agents_.begin(), agents_.end(), agent_selection_));
  int first_dead = -1;
  for (int a : agents_) {
    if (terminations_[a] || truncations_[a]) {
      first_dead = a;
      break;
    }
  }
  if (first_dead >= 0) {
    if (skip_agent_selection_ < 0) skip_agent_selection_ = agent_selection_;
    agent_selection_ = first_dead;
  } else {
    if (skip_agent_selection_ >= 0) agent_selection_ = skip_agent_selection_;
    skip_agent_selection_ = -1;
  }
  ClearRewards();
}

void AecEnv::DeadsStepFirst() {
  for (int a : agents_) {
    if (terminations_[a] || truncations_[a]) {
      skip_agent_selection_ = agent_selection_;
      agent_selection_ = a;
      return;
    }
  }
}

void AecEnv::ClearRewards() {
  for (int a : agents_) rewards_[a] = 0.0f;
}

void AecEnv::AccumulateRewards() {
  for (int a : agents_) cumulative_rewards_[a] += rewards_[a];
}

void AecEnv::SelectorReinit(std::vector<int> order) {
  selector_order_ = std::move(order);
  selector_current_ = 0;
  selector_selected_ = -1;  // Python sets 0, which never equals a name.
}

int AecEnv::SelectorNext() {
  const int size = static_cast<int>(selector_order_.size());
  selector_current_ = (selector_current_ + 1) % size;
  // Python's order[current - 1] wraps to the last element at index -1.
  selector_selected_ = selector_order_[(selector_current_ - 1 + size) % size];
  return selector_selected_;
}

const std::vector<int>& AecEnv::agents() const { return agents_; }

int AecEnv::agent_selection() const {
  return agents_.empty() ? -1 : agent_selection_;
}

float AecEnv::reward(int agent) const { return rewards_[agent]; }
float AecEnv::cumulative_reward(int agent) const {
  return cumulative_rewards_[agent];
}
bool AecEnv::terminated(int agent) const { return terminations_[agent]; }
bool AecEnv::truncated(int agent) const { return truncations_[agent]; }

absl::Span<const float> AecEnv::observe(int agent) const {
  return env_->observation(agent);
}

const Env& AecEnv::env() const { return *env_; }

}  // namespace mll::core
