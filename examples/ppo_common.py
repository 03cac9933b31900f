"""What the PPO examples (ppo_cleanrl.py, async_ppo.py, and ppo_sb3.py for the flags, scores and
evaluation) share: the recipe's flags, CleanRL's actor-critic network, generalised advantage
estimation, the clipped PPO update, environment episode scores, saving and greedy evaluation."""

from __future__ import annotations

import argparse
import math

import numpy as np
import torch
from torch import nn

import multi_lunar_lander as mll
import trainer_common


# The environments --evaluate-on names: the paper's experiment, and the environment's own
# defaults (3 landers, 500 steps, shared rewards, one lander's crash ends every lander's episode).
EVALUATION_ENVIRONMENTS = {"paper": trainer_common.PAPER_OPTIONS, "default": {}}


def add_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """PPO's hyperparameters, beside trainer_common.parser's flags. The defaults are the recipe
    of docs/training.md "PPO recipes": RL Zoo's tuned LunarLander PPO (rollouts of 1,024 steps,
    minibatches of 64, 4 epochs, gamma 0.999, GAE 0.98, lr 3e-4) over 16 environments of 3
    landers, with an entropy coefficient of 0.001 instead of 0.01 (a lander must rest 25 steps
    without firing to land, which a policy kept random rarely does), observations normalised, and
    rewards clipped to +-100 (the paper's landing +700 and crash -400 at Gymnasium's scale)
    before they are scaled."""
    parser.set_defaults(num_steps=1024, lr=3e-4, total_steps=4_500_000)
    parser.add_argument("--minibatch-size", type=int, default=64, help="transitions per gradient step")
    parser.add_argument("--gamma", type=float, default=0.999)
    parser.add_argument("--gae-lambda", type=float, default=0.98)
    parser.add_argument("--clip", type=float, default=0.2)
    parser.add_argument("--ent-coef", type=float, default=0.001)
    parser.add_argument("--vf-coef", type=float, default=0.5)
    parser.add_argument("--max-grad-norm", type=float, default=0.5)
    parser.add_argument("--normalize-observations", action=argparse.BooleanOptionalAction, default=True,
                        help="scale observations by their running mean and variance")
    parser.add_argument("--neighbor-closeness", action=argparse.BooleanOptionalAction, default=False,
                        help="the policy sees the neighbours by closeness (mll.neighbor_closeness)")
    parser.add_argument("--team-credit", action=argparse.BooleanOptionalAction, default=False,
                        help="credit every lander with its environment's summed rewards, also after it is done")
    parser.add_argument("--clip-rewards", type=float, default=100.0, metavar="C",
                        help="clip each reward the learner sees to [-C, C] before scaling it (0: no clipping)")
    parser.add_argument("--save", default=None, metavar="PATH", help="write the trained policy")
    parser.add_argument("--evaluate", default=None, metavar="PATH",
                        help="do not train: reload the policy saved at PATH and evaluate it greedily")
    parser.add_argument("--evaluate-on", choices=sorted(EVALUATION_ENVIRONMENTS), default=None,
                        help="fly the evaluation episodes on this environment instead of the policy's own")
    parser.add_argument("--eval-episodes", type=int, default=10,
                        help="environment episodes of greedy evaluation after training or with --evaluate (0: none)")
    parser.add_argument("--episodes-csv", default=None,
                        help="write one row per environment episode: its score and the running 50-episode mean")
    return parser


class EnvEpisodes:
    """Environment episodes' scores (the sum of their landers' returns) from the landers'
    episode ends: an environment's episode is complete once each of its landers has ended.
    `rows`: (episode, score, running 50-episode mean, environment steps so far, wall seconds),
    the columns of examples/dqn's episodes.csv."""

    COLUMNS = ["episode", "score", "mean50", "env_steps", "wall_s"]

    def __init__(self, envs: int, landers: int):
        self.landers = landers
        self.sums = np.zeros(envs)
        self.ended = np.zeros(envs, dtype=int)
        self.scores: list[float] = []
        self.rows: list[tuple] = []

    def add(self, ended: np.ndarray, returns: np.ndarray, env_steps: int, seconds: float, envs=slice(None)) -> None:
        """ended, returns: [len(envs), landers], the landers whose episode ended in this step
        and their returns; `envs` the environments they are (default: all)."""
        self.sums[envs] += np.where(ended, returns, 0.0).sum(axis=1)
        self.ended[envs] += np.asarray(ended).sum(axis=1)
        for env in np.flatnonzero(self.ended == self.landers):
            self.scores.append(float(self.sums[env]))
            self.sums[env], self.ended[env] = 0.0, 0
            mean50 = float(np.mean(self.scores[-50:]))
            self.rows.append((len(self.scores), self.scores[-1], mean50, env_steps, seconds))

    def write(self, path: str | None) -> None:
        trainer_common.write_csv(
            path, self.COLUMNS, ((e, f"{s:.3f}", f"{m:.3f}", n, f"{w:.3f}") for e, s, m, n, w in self.rows)
        )


# CleanRL's orthogonal initialisation gain for hidden layers.
HIDDEN_GAIN = float(np.sqrt(2))


def layer(inputs, outputs, std=HIDDEN_GAIN):
    linear = nn.Linear(inputs, outputs)
    nn.init.orthogonal_(linear.weight, std)
    nn.init.constant_(linear.bias, 0.0)
    return linear


class Agent(nn.Module):
    def __init__(self, observations: int, actions: int):
        super().__init__()
        self.critic = nn.Sequential(layer(observations, 64), nn.Tanh(), layer(64, 64), nn.Tanh(), layer(64, 1, 1.0))
        self.actor = nn.Sequential(
            layer(observations, 64), nn.Tanh(), layer(64, 64), nn.Tanh(), layer(64, actions, 0.01)
        )

    def value(self, x):
        return self.critic(x).squeeze(-1)

    def act(self, x, action=None):
        distribution = torch.distributions.Categorical(logits=self.actor(x))
        if action is None:
            action = distribution.sample()
        return action, distribution.log_prob(action), distribution.entropy(), self.value(x)


def team_credit(rewards, valid, next_values, goes_on, landers: int):
    """Credits every lander with its team's return. All arguments are [steps, rows] tensors whose
    rows hold environments' landers side by side (row k is lander k % landers of environment
    k // landers): the rewards, which transitions are real (`valid`), each row's value of its next
    observation, and whether that value counts (`goes_on`: the lander flies on, or was cut off and
    bootstraps its final observation). Returns (team rewards, next values) per row: the rewards of
    the environment's real transitions on that step summed, and the row's own next value where it
    goes on, else the mean next value of the environment's landers that go on (0 when none does).
    So a lander that lands first still earns what its neighbours earn after it: with shared
    rewards its own return would lose their landings, and every lander would wait for the others."""
    by_env = (rewards.shape[0], -1, landers)
    per_row = lambda per_env: per_env.expand(by_env).reshape(rewards.shape)  # noqa: E731
    team_rewards = per_row((rewards * valid).view(by_env).sum(-1, keepdim=True))
    on = goes_on.float().view(by_env)
    team_next = per_row((next_values.view(by_env) * on).sum(-1, keepdim=True) / on.sum(-1, keepdim=True).clamp(min=1))
    return team_rewards, torch.where(goes_on, next_values, team_next)


@torch.no_grad()
def advantages(agent: Agent, next_observations, rewards, values, terminated, done, gamma: float, lam: float,
               team: tuple | None = None):
    """GAE over a rollout whose first axis is time and whose other axes are independent
    sequences (each sequence contiguous in time): returns (advantages, value targets). A
    truncated episode bootstraps from its final observation (next_observations). With `team` =
    (valid, landers), every lander is credited with its team's return (team_credit)."""
    next_values = agent.value(next_observations)
    if team is None:
        deltas = rewards + gamma * next_values * (1 - terminated) - values
    else:
        valid, landers = team
        team_rewards, next_values = team_credit(rewards, valid, next_values, valid & (terminated == 0), landers)
        deltas = team_rewards + gamma * next_values - values
    result = discounted_sums(deltas, done, gamma * lam)
    return result, result + values


def discounted_sums(deltas, done, discount: float):
    """GAE's backward pass: each step's delta plus `discount` times the next step's sum, the
    sequences cut after every step whose `done` is set (time is the first axis)."""
    result = torch.zeros_like(deltas)
    running = torch.zeros(deltas.shape[1:])
    for step in reversed(range(deltas.shape[0])):
        running = deltas[step] + discount * (1 - done[step]) * running
        result[step] = running
    return result


def update(agent: Agent, optimizer, batch, args) -> dict[str, float]:
    """args.epochs epochs of the clipped PPO loss over `batch` = (observations, actions, log
    probabilities, advantages, value targets) of the real transitions, in minibatches of
    args.minibatch_size; returns the losses' means over the minibatches."""
    b_obs, b_act, b_logp, b_adv, b_ret = batch
    count = len(b_obs)
    size = max(1, args.minibatch_size)
    sums, minibatches = {"policy_loss": 0.0, "value_loss": 0.0, "entropy": 0.0}, 0
    for _ in range(args.epochs):
        order = torch.randperm(count)
        for start in range(0, count, size):
            rows = order[start : start + size]
            _, logprob, entropy, value = agent.act(b_obs[rows], b_act[rows])
            ratio = (logprob - b_logp[rows]).exp()
            adv = b_adv[rows]
            adv = (adv - adv.mean()) / (adv.std() + 1e-8) if len(rows) > 1 else adv
            policy_loss = torch.max(-adv * ratio, -adv * ratio.clamp(1 - args.clip, 1 + args.clip)).mean()
            value_loss = 0.5 * ((value - b_ret[rows]) ** 2).mean()
            loss = policy_loss - args.ent_coef * entropy.mean() + args.vf_coef * value_loss
            optimizer.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)
            optimizer.step()
            sums["policy_loss"] += float(policy_loss)
            sums["value_loss"] += float(value_loss)
            sums["entropy"] += float(entropy.mean())
            minibatches += 1
    return {name: total / max(1, minibatches) for name, total in sums.items()}


class ObservationScale:
    """Observation normalisation as a fixed function (the running statistics a training run ended
    with): (observation - mean) / sqrt(var + 1e-8), clipped to [-clip, clip] when `clip` is set
    (Gymnasium's NormalizeObservation does not clip; SB3's VecNormalize clips at 10)."""

    def __init__(self, mean, var, clip: float | None = None):
        self.mean, self.var, self.clip = np.asarray(mean, np.float32), np.asarray(var, np.float32), clip

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        scaled = (observation - self.mean) / np.sqrt(self.var + 1e-8)
        if self.clip is not None:
            scaled = np.clip(scaled, -self.clip, self.clip)
        return scaled.astype(np.float32)


def greedy(agent: Agent, scale: ObservationScale | None = None, closeness: bool = False):
    """The agent's greedy policy as a function of a numpy observation batch [..., features]:
    the most probable action of each row, the observations seen as in training (neighbours by
    closeness when `closeness`, then scaled by `scale`)."""

    def act(observation: np.ndarray) -> np.ndarray:
        observation = np.asarray(observation, np.float32)
        if closeness:
            observation = mll.neighbor_closeness(observation)
        if scale is not None:
            observation = scale(observation)
        with torch.no_grad():
            return agent.actor(torch.from_numpy(observation)).argmax(-1).numpy()

    return act


def save(path: str, agent: Agent, options: dict, args, scale: ObservationScale | None = None) -> None:
    """Writes the policy, the environment options it was trained on, its observation scaling
    and the training flags (torch.save)."""
    config = {"observations": agent.actor[0].in_features, "actions": agent.actor[-1].out_features,
              "options": options, "args": vars(args),
              "observation_scale": None if scale is None else (scale.mean.tolist(), scale.var.tolist())}
    torch.save({"state_dict": agent.state_dict(), "config": config}, path)


def load(path: str):
    """The policy saved by save() as a greedy policy (greedy()) on plain observations, and its
    config."""
    saved = torch.load(path)
    config = saved["config"]
    agent = Agent(config["observations"], config["actions"])
    agent.load_state_dict(saved["state_dict"])
    scale = config["observation_scale"]
    scale = None if scale is None else ObservationScale(*scale)
    return greedy(agent, scale, config["args"].get("neighbor_closeness", False)), config


def evaluation_options(args, trained_options: dict) -> dict:
    """The environment options of the greedy evaluation: --evaluate-on's, else the policy's own."""
    return dict(EVALUATION_ENVIRONMENTS[args.evaluate_on]) if args.evaluate_on else trained_options


# Evaluation seeds start here: far from the training seeds (seed + environment index).
EVALUATION_SEED_OFFSET = 1_000_000


def evaluate_greedy(act, options: dict, episodes: int, address=None, envs: int = 16, seed: int = 1) -> dict:
    """Runs `act` (observations [envs, landers, features] -> actions [envs, landers]) for
    `episodes` environment episodes of `options` on min(envs, episodes) environments seeded from
    seed + EVALUATION_SEED_OFFSET; returns the mean score (an episode's landers' returns summed),
    the mean lander return and the share of landers per outcome ("landed", "crashed", ...)."""
    count = min(envs, episodes)
    scores, lander_returns, outcomes = [], [], []
    limit = math.ceil(episodes / count) * (options.get("max_cycles", 500) + 1) + 1  # Every env has ended by then.
    with mll.vector_env(count, address=address, **options) as vector:
        observation, _ = vector.reset(seed=seed + EVALUATION_SEED_OFFSET)
        for _ in range(limit):
            observation, _, _, _, _, infos = vector.step(act(observation))
            over = infos["episode_over"]
            scores.extend(infos["episode_return"][over].sum(axis=1).tolist())
            lander_returns.extend(infos["episode_return"][over].ravel().tolist())
            outcomes.extend(infos["outcome"][over].ravel().tolist())
            if len(scores) >= episodes:
                break
    landers = len(outcomes) // len(scores) * episodes  # The landers of the first `episodes` episodes.
    shares = {name: float(np.mean([o == code for o in outcomes[:landers]]))
              for code, name in enumerate(mll.OUTCOMES) if name}
    return {"evaluation_episodes": episodes, "mean_score": float(np.mean(scores[:episodes])),
            "mean_lander_return": float(np.mean(lander_returns[:landers])), **shares}
