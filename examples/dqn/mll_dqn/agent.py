"""The shared Q-network and its learning step."""

from __future__ import annotations

import math
from typing import List, Sequence

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

import multi_lunar_lander

from mll_dqn import qnet_file
from mll_dqn.config import N_ACTIONS, OBS_SIZE, TrainConfig


_NEIGHBOR_SCALE = torch.from_numpy(qnet_file.NEIGHBOR_SCALE)


def neighbor_closeness(obs: torch.Tensor) -> torch.Tensor:
    """obs with each neighbor's offset [8:10], [10:12] (in world units)
    replaced by its direction times exp(-distance / NEIGHBOR_REACH): near 1
    when near, 0 when absent or far. The environment writes an absent
    neighbor as a zero offset, next to the offset of one about to collide;
    here the two are the furthest apart. qnet_file has the same in numpy."""
    offsets = obs[:, 8:12].reshape(-1, 2, 2) * _NEIGHBOR_SCALE
    distance = offsets.norm(dim=2, keepdim=True)
    present = distance > 0
    safe = torch.where(present, distance, torch.ones_like(distance))
    closeness = torch.where(
        present, torch.exp(-distance / qnet_file.NEIGHBOR_REACH) / safe,
        torch.zeros_like(distance))
    return torch.cat((obs[:, :8], (offsets * closeness).reshape(-1, 4)), dim=1)


class QNetwork(nn.Module):
    """MLP obs -> Q-values, 12-256-64-4 in the paper; no agent id input."""

    def __init__(self, hidden: Sequence[int] = (256, 64),
                 obs_size: int = OBS_SIZE, n_actions: int = N_ACTIONS,
                 neighbor_input: str = "offset"):
        super().__init__()
        self.neighbor_input = neighbor_input
        sizes = [obs_size, *hidden]
        layers = []
        for n_in, n_out in zip(sizes[:-1], sizes[1:]):
            layers += [nn.Linear(n_in, n_out), nn.ReLU()]
        layers.append(nn.Linear(sizes[-1], n_actions))
        self.layers = nn.Sequential(*layers)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.layers(self.inputs(obs))

    def inputs(self, obs: torch.Tensor) -> torch.Tensor:
        if self.neighbor_input == "closeness":
            return neighbor_closeness(obs)
        return obs

    def linear_layers(self) -> List[nn.Linear]:
        return [layer for layer in self.layers if isinstance(layer, nn.Linear)]


def flatten_parameters(network: nn.Module) -> torch.Tensor:
    """Moves the network's parameters into one flat tensor, each parameter
    becoming a view of it (state_dict and load_state_dict work as before),
    so that the optimiser and the target update are a few operations on one
    tensor instead of a few per parameter."""
    params = list(network.parameters())
    flat = torch.cat([param.detach().reshape(-1) for param in params])
    for param, view in zip(params, _views_of(flat, params)):
        param.data = view
    return flat


def _views_of(flat: torch.Tensor, shapes_of) -> List[torch.Tensor]:
    """Views of `flat` shaped like the tensors `shapes_of`, in order."""
    views, offset = [], 0
    for like in shapes_of:
        views.append(flat[offset:offset + like.numel()].view_as(like))
        offset += like.numel()
    return views


class FlatAdam:
    """Adam (torch.optim.Adam's arithmetic: no weight decay, no amsgrad)
    over one flat tensor of parameters and one of their gradients."""

    def __init__(self, params: torch.Tensor, grads: torch.Tensor, lr: float,
                 betas=(0.9, 0.999), eps: float = 1e-8):
        self.params, self.grads = params, grads
        self.lr, self.betas, self.eps = lr, tuple(betas), eps
        self.step_count = 0
        self.exp_avg = torch.zeros_like(params)
        self.exp_avg_sq = torch.zeros_like(params)

    @torch.no_grad()
    def step(self) -> None:
        beta1, beta2 = self.betas
        self.step_count += 1
        self.exp_avg.mul_(beta1).add_(self.grads, alpha=1 - beta1)
        self.exp_avg_sq.mul_(beta2).addcmul_(self.grads, self.grads,
                                             value=1 - beta2)
        bias_correction1 = 1 - beta1 ** self.step_count
        bias_correction2 = 1 - beta2 ** self.step_count
        denominator = (self.exp_avg_sq.sqrt() / math.sqrt(bias_correction2)
                       ).add_(self.eps)
        self.params.addcdiv_(self.exp_avg, denominator,
                             value=-self.lr / bias_correction1)

    def state_dict(self):
        return dict(lr=self.lr, betas=self.betas, eps=self.eps,
                    step=self.step_count, exp_avg=self.exp_avg.clone(),
                    exp_avg_sq=self.exp_avg_sq.clone())

    def load_state_dict(self, state) -> None:
        """Loads state_dict()'s dict, or torch.optim.Adam's over the network's
        parameters in order (as checkpoints of earlier versions hold)."""
        if "param_groups" in state:
            group = state["param_groups"][0]
            per_param = [state["state"][index] for index in group["params"]]
            state = dict(
                lr=group["lr"], betas=group["betas"], eps=group["eps"],
                step=int(per_param[0]["step"]),
                exp_avg=torch.cat([p["exp_avg"].reshape(-1) for p in per_param]),
                exp_avg_sq=torch.cat([p["exp_avg_sq"].reshape(-1)
                                      for p in per_param]))
        self.lr, self.betas, self.eps = (state["lr"], tuple(state["betas"]),
                                         state["eps"])
        self.step_count = int(state["step"])
        self.exp_avg.copy_(state["exp_avg"])
        self.exp_avg_sq.copy_(state["exp_avg_sq"])


def _forward_keeping_activations(layers: List[nn.Linear],
                                 obs: torch.Tensor) -> List[torch.Tensor]:
    """[obs, each hidden layer's output (after ReLU), Q-values]."""
    activations = [obs]
    for index, layer in enumerate(layers):
        out = torch.addmm(layer.bias, activations[-1], layer.weight.t())
        if index < len(layers) - 1:
            out.relu_()
        activations.append(out)
    return activations


def _backward(layers: List[nn.Linear], activations: List[torch.Tensor],
              grad_q: torch.Tensor, grads: List[torch.Tensor]) -> None:
    """Writes the loss's gradient for each layer's weight and bias (`grads`:
    weight, bias, weight, ... as the network's parameters) given its
    gradient for the Q-values, by the chain rule through the layers."""
    grad_out = grad_q
    for index in reversed(range(len(layers))):
        inputs = activations[index]
        torch.mm(grad_out.t(), inputs, out=grads[2 * index])
        torch.sum(grad_out, 0, out=grads[2 * index + 1])
        if index > 0:
            # Through the ReLU: no gradient where its output was 0.
            grad_out = torch.ops.aten.threshold_backward(
                grad_out.mm(layers[index].weight), inputs, 0)


class DQNAgent:
    """Online and target networks, Adam, epsilon-greedy action selection.

    The learning step computes the gradient by hand (the network is a
    stack of linear layers and ReLUs): the same arithmetic as autograd,
    test_agent checks it against autograd and torch's Adam, in half the
    time, as it keeps no graph, fuses the two forward passes of the online
    network and updates one flat tensor of parameters."""

    def __init__(self, config: TrainConfig):
        self.config = config
        # The paper seeds torch before building each network, so both start
        # equal; we copy instead, to the same effect.
        torch.manual_seed(config.seed)
        self.online = QNetwork(config.hidden, neighbor_input=config.neighbor_input)
        self.target = QNetwork(config.hidden, neighbor_input=config.neighbor_input)
        self.target.load_state_dict(self.online.state_dict())
        for param in self.target.parameters():
            param.requires_grad_(False)
        self._online_flat = flatten_parameters(self.online)
        self._target_flat = flatten_parameters(self.target)
        self._grad_flat = torch.zeros_like(self._online_flat)
        self._grads = _views_of(self._grad_flat, list(self.online.parameters()))
        self.optimizer = FlatAdam(self._online_flat, self._grad_flat,
                                  lr=config.lr)
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

    @torch.no_grad()
    def learn_weighted(self, batch, weights):
        """One gradient step with each transition's loss multiplied by its
        importance weight (None: all 1); returns the loss and the absolute TD
        errors (numpy), the new priorities of prioritized replay."""
        obs, actions, rewards, next_obs, discounts = (
            torch.from_numpy(array) for array in batch)
        config = self.config
        size = len(obs)
        online = self.online.linear_layers()
        if config.double_dqn:
            # One pass of the online network over obs and next_obs.
            seen = self.online.inputs(torch.cat((obs, next_obs)))
            activations = _forward_keeping_activations(online, seen)
            next_online_q = activations[-1][size:]
            activations = [a[:size] for a in activations]
            next_seen = seen[size:]
        else:
            activations = _forward_keeping_activations(
                online, self.online.inputs(obs))
            next_seen = self.target.inputs(next_obs)
        # The target network on next_obs as the online network saw it (the
        # input transform is the same for both, and done once).
        next_q = self.target.layers(next_seen)
        if config.double_dqn:
            # The online network picks, the target network evaluates.
            best = next_online_q.argmax(dim=1, keepdim=True)
            next_value = next_q.gather(1, best).squeeze(1)
        else:
            next_value = next_q.max(dim=1)[0]
        targets = rewards + discounts * next_value
        index = actions.unsqueeze(1)
        q = activations[-1].gather(1, index).squeeze(1)
        errors = q - targets
        # d(loss)/dq of the mean loss over the batch.
        if config.loss == "huber":
            each = F.smooth_l1_loss(q, targets, reduction="none")
            grad = errors.clamp(-1.0, 1.0)
        else:
            each = F.mse_loss(q, targets, reduction="none")
            grad = 2.0 * errors
        if weights is not None:
            weights = torch.from_numpy(weights)
            each = each * weights
            grad = grad * weights
        grad_q = torch.zeros_like(activations[-1]).scatter_(
            1, index, (grad / size).unsqueeze(1))
        _backward(online, activations, grad_q, self._grads)
        if config.grad_clip > 0:
            # As nn.utils.clip_grad_norm_: scale to the norm's limit.
            norm = float(self._grad_flat.norm())
            if norm > config.grad_clip:
                self._grad_flat.mul_(config.grad_clip / (norm + 1e-6))
        self.optimizer.step()
        self._soft_update(config.tau)
        self.updates += 1
        return float(each.mean()), errors.abs().numpy()

    def set_lr(self, lr: float) -> None:
        self.optimizer.lr = lr

    @torch.no_grad()
    def _soft_update(self, tau: float) -> None:
        # target = tau * online + (1 - tau) * target
        self._target_flat.mul_(1.0 - tau).add_(self._online_flat, alpha=tau)

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
