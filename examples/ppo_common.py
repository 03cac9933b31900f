"""What the PPO examples (ppo_cleanrl.py, async_ppo.py) share: their PPO flags, CleanRL's
actor-critic network, generalised advantage estimation and the clipped PPO update."""

from __future__ import annotations

import argparse

import numpy as np
import torch
from torch import nn


def add_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """PPO's hyperparameters (CleanRL's defaults), beside trainer_common.parser's flags."""
    parser.add_argument("--minibatches", type=int, default=4)
    parser.add_argument("--gamma", type=float, default=0.99)
    parser.add_argument("--gae-lambda", type=float, default=0.95)
    parser.add_argument("--clip", type=float, default=0.2)
    parser.add_argument("--ent-coef", type=float, default=0.01)
    parser.add_argument("--vf-coef", type=float, default=0.5)
    parser.add_argument("--max-grad-norm", type=float, default=0.5)
    return parser


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


@torch.no_grad()
def advantages(agent: Agent, next_observations, rewards, values, terminated, done, gamma: float, lam: float):
    """GAE over a rollout whose first axis is time and whose other axes are independent
    sequences (each sequence contiguous in time): returns (advantages, value targets). A
    truncated episode bootstraps from its final observation (next_observations)."""
    next_values = agent.value(next_observations)
    deltas = rewards + gamma * next_values * (1 - terminated) - values
    result = torch.zeros_like(rewards)
    running = torch.zeros(rewards.shape[1:])
    for step in reversed(range(rewards.shape[0])):
        running = deltas[step] + gamma * lam * (1 - done[step]) * running
        result[step] = running
    return result, result + values


def update(agent: Agent, optimizer, batch, args) -> dict[str, float]:
    """args.epochs epochs of the clipped PPO loss over `batch` = (observations, actions, log
    probabilities, advantages, value targets) of the real transitions, in args.minibatches
    minibatches; returns the losses' means over the minibatches."""
    b_obs, b_act, b_logp, b_adv, b_ret = batch
    count = len(b_obs)
    size = max(1, count // args.minibatches)
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
