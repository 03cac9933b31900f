"""The shared Q-network and its learning step."""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

import multi_lunar_lander

from mll_dqn.config import N_ACTIONS, OBS_SIZE, TrainConfig


class QNetwork(nn.Module):
    """MLP obs -> Q-values, 12-256-64-4 in the paper; no agent id input."""

    def __init__(self, hidden: Sequence[int] = (256, 64),
                 obs_size: int = OBS_SIZE, n_actions: int = N_ACTIONS):
        super().__init__()
        sizes = [obs_size, *hidden]
        layers = []
        for n_in, n_out in zip(sizes[:-1], sizes[1:]):
            layers += [nn.Linear(n_in, n_out), nn.ReLU()]
        layers.append(nn.Linear(sizes[-1], n_actions))
        self.layers = nn.Sequential(*layers)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.layers(obs)


class DQNAgent:
    """Online and target networks, Adam, epsilon-greedy action selection."""

    def __init__(self, config: TrainConfig):
        self.config = config
        # The paper seeds torch before building each network, so both start
        # equal; we copy instead, to the same effect.
        torch.manual_seed(config.seed)
        self.online = QNetwork(config.hidden)
        self.target = QNetwork(config.hidden)
        self.target.load_state_dict(self.online.state_dict())
        for param in self.target.parameters():
            param.requires_grad_(False)
        # foreach: one fused kernel per op over all parameters instead of one
        # per tensor (same arithmetic, less Python overhead).
        self.optimizer = torch.optim.Adam(self.online.parameters(), lr=config.lr,
                                          foreach=True)
        self._online_params = list(self.online.parameters())
        self._target_params = list(self.target.parameters())
        self.updates = 0

    def act(self, obs: np.ndarray, epsilon: float,
            rng: np.random.Generator) -> np.ndarray:
        """Epsilon-greedy actions for a batch of observations [B, 12]; a
        share `explore_guide` of the exploring ones is the heuristic pilot's."""
        count = len(obs)
        if count == 0:
            return np.zeros(0, np.int64)
        explore = rng.random(count) < epsilon
        actions = rng.integers(0, N_ACTIONS, count)
        if self.config.explore_guide:
            guided = explore & (rng.random(count) < self.config.explore_guide)
            if guided.any():
                actions[guided] = multi_lunar_lander.heuristic(obs[guided])
        if not explore.all():
            actions = np.where(explore, actions, self.greedy(obs))
        return actions

    @torch.inference_mode()
    def greedy(self, obs: np.ndarray) -> np.ndarray:
        q = self.online(torch.from_numpy(np.asarray(obs, np.float32)))
        return q.argmax(dim=1).numpy()

    def learn(self, batch) -> float:
        """One gradient step on (obs, actions, rewards, next_obs, discounts)."""
        return self.learn_weighted(batch, None)[0]

    def learn_weighted(self, batch, weights):
        """One gradient step with each transition's loss multiplied by its
        importance weight (None: all 1); returns the loss and the absolute TD
        errors (numpy), the new priorities of prioritized replay."""
        obs, actions, rewards, next_obs, discounts = (
            torch.from_numpy(array) for array in batch)
        config = self.config
        with torch.no_grad():
            next_q = self.target(next_obs)
            if config.double_dqn:
                # The online network picks, the target network evaluates.
                best = self.online(next_obs).argmax(dim=1, keepdim=True)
                next_value = next_q.gather(1, best).squeeze(1)
            else:
                next_value = next_q.max(dim=1)[0]
            targets = rewards + discounts * next_value
        q = self.online(obs).gather(1, actions.unsqueeze(1)).squeeze(1)
        if weights is None:
            if config.loss == "huber":
                loss = F.smooth_l1_loss(q, targets)
            else:
                loss = F.mse_loss(q, targets)
        else:
            if config.loss == "huber":
                each = F.smooth_l1_loss(q, targets, reduction="none")
            else:
                each = F.mse_loss(q, targets, reduction="none")
            loss = (torch.from_numpy(weights) * each).mean()
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if config.grad_clip > 0:
            nn.utils.clip_grad_norm_(self._online_params, config.grad_clip)
        self.optimizer.step()
        self._soft_update(config.tau)
        self.updates += 1
        return float(loss), (q.detach() - targets).abs().numpy()

    def set_lr(self, lr: float) -> None:
        for group in self.optimizer.param_groups:
            group["lr"] = lr

    @torch.no_grad()
    def _soft_update(self, tau: float) -> None:
        # target = tau * online + (1 - tau) * target
        torch._foreach_mul_(self._target_params, 1.0 - tau)
        torch._foreach_add_(self._target_params, self._online_params, alpha=tau)

    def state_dict(self):
        return dict(online=self.online.state_dict(),
                    target=self.target.state_dict(),
                    optimizer=self.optimizer.state_dict(),
                    updates=self.updates)

    def load_state_dict(self, state) -> None:
        self.online.load_state_dict(state["online"])
        self.target.load_state_dict(state["target"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.updates = int(state["updates"])


class RepeatedExploration:
    """Epsilon-greedy actions whose exploring actions last several steps
    (epsilon-z-greedy): one state per stream (a lander slot). A stream that is
    not in an exploring run starts one with probability epsilon: a random
    action kept for n steps, n ~ zeta(`zeta`) capped at `max_steps`; otherwise
    it acts greedily. A lander that rests on its legs lands only after 25
    steps without an engine (its body must fall asleep), a run one-step
    exploration almost never makes once the greedy policy fires now and then.
    """

    def __init__(self, num_streams: int, zeta: float, max_steps: int):
        self._zeta = zeta
        self._max_steps = max_steps
        self._action = np.zeros(num_streams, np.int64)
        self._left = np.zeros(num_streams, np.int64)

    def act(self, agent: DQNAgent, obs: np.ndarray, streams: np.ndarray,
            epsilon: float, rng: np.random.Generator) -> np.ndarray:
        """Actions of `streams` (indices) observing `obs` [len(streams), 12]."""
        if len(streams) == 0:
            return np.zeros(0, np.int64)
        running = self._left[streams] > 0
        starting = ~running & (rng.random(len(streams)) < epsilon)
        new = streams[starting]
        self._action[new] = rng.integers(0, N_ACTIONS, len(new))
        self._left[new] = np.minimum(rng.zipf(self._zeta, len(new)),
                                     self._max_steps)
        exploring = running | starting
        actions = self._action[streams].copy()
        if not exploring.all():
            actions[~exploring] = agent.greedy(obs[~exploring])
        self._left[streams[exploring]] -= 1
        return actions

    def stop(self, streams) -> None:
        """Ends the runs of `streams` (indices or a mask over all streams):
        their landers' episodes ended."""
        self._left[streams] = 0
