"""Replay memory: a preallocated numpy ring buffer, and n-step folding.

All landers of all environments write into one buffer (parameter sharing: a
transition does not know which lander made it). Each stored transition
carries its own bootstrap discount (gamma^k, 0 when terminal), so one-step and
n-step transitions share the learning code.
"""

from __future__ import annotations

from typing import Dict, Optional

import numpy as np


class ReplayBuffer:
    """Fixed-capacity ring of (obs, action, reward, next_obs, discount)."""

    def __init__(self, capacity: int, obs_size: int):
        if capacity < 1:
            raise ValueError(f"capacity = {capacity} is out of range; allowed: >= 1")
        self.capacity = capacity
        self.obs = np.zeros((capacity, obs_size), np.float32)
        self.next_obs = np.zeros((capacity, obs_size), np.float32)
        self.actions = np.zeros(capacity, np.int64)
        self.rewards = np.zeros(capacity, np.float32)
        # gamma^k for a k-step transition that bootstraps, 0 for a terminal one.
        self.discounts = np.zeros(capacity, np.float32)
        self.size = 0
        self.next_index = 0

    def __len__(self) -> int:
        return self.size

    def add(self, obs, actions, rewards, next_obs, discounts) -> None:
        """Appends a batch of transitions (leading dimension = count)."""
        count = len(actions)
        if count == 0:
            return
        if count > self.capacity:
            raise ValueError(
                f"batch of {count} transitions exceeds the capacity "
                f"{self.capacity}")
        index = (self.next_index + np.arange(count)) % self.capacity
        self.obs[index] = obs
        self.actions[index] = actions
        self.rewards[index] = rewards
        self.next_obs[index] = next_obs
        self.discounts[index] = discounts
        self.next_index = (self.next_index + count) % self.capacity
        self.size = min(self.size + count, self.capacity)

    def sample(self, batch_size: int, rng: np.random.Generator):
        """Uniform sample without replacement, as the paper's random.sample."""
        if batch_size > self.size:
            raise ValueError(
                f"batch_size = {batch_size} exceeds the {self.size} stored "
                "transitions")
        index = rng.choice(self.size, batch_size, replace=False)
        return (self.obs[index], self.actions[index], self.rewards[index],
                self.next_obs[index], self.discounts[index])

    def state_dict(self) -> Dict[str, np.ndarray]:
        return dict(obs=self.obs[:self.size], next_obs=self.next_obs[:self.size],
                    actions=self.actions[:self.size],
                    rewards=self.rewards[:self.size],
                    discounts=self.discounts[:self.size],
                    next_index=np.array(self.next_index))

    def load_state_dict(self, state: Dict[str, np.ndarray]) -> None:
        size = len(state["actions"])
        if size > self.capacity:
            raise ValueError(
                f"saved buffer holds {size} transitions, more than the capacity "
                f"{self.capacity}")
        for name in ("obs", "next_obs", "actions", "rewards", "discounts"):
            getattr(self, name)[:size] = state[name]
        self.size = size
        self.next_index = int(state["next_index"]) % self.capacity


class PrioritizedReplayBuffer(ReplayBuffer):
    """ReplayBuffer sampled in proportion to priority^alpha (Schaul et al.,
    2016: proportional prioritized replay), a priority being the transition's
    last absolute TD error plus `epsilon`; a new transition gets the largest
    priority so far, so it is replayed at least once soon. The rare outcome
    transitions (a landing's +7 after scaling, a crash's -3) keep large errors
    until learnt, and so are replayed more often than their share of the
    buffer. The importance weights (N P(i))^-beta undo the bias.

    The priorities live in a sum tree (leaves = transitions, each node the
    sum of its children), stored as one flat array: sampling descends it for
    the whole batch at once."""

    def __init__(self, capacity: int, obs_size: int, alpha: float,
                 epsilon: float = 1e-3):
        super().__init__(capacity, obs_size)
        self.alpha = alpha
        self.epsilon = epsilon
        self._leaves = 1 << max(0, (capacity - 1).bit_length())
        self._tree = np.zeros(2 * self._leaves, np.float64)
        self._max_priority = 1.0

    def add(self, obs, actions, rewards, next_obs, discounts) -> None:
        count = len(actions)
        first = self.next_index
        super().add(obs, actions, rewards, next_obs, discounts)
        if count:
            index = (first + np.arange(count)) % self.capacity
            self._set(index, np.full(count, self._max_priority ** self.alpha))

    def sample_prioritized(self, batch_size: int, rng: np.random.Generator,
                           beta: float):
        """(batch, index, weights): a stratified draw (one per equal slice of
        the total priority), the rows' indices, and float32 importance
        weights divided by the batch's largest (as Dopamine's Rainbow)."""
        if batch_size > self.size:
            raise ValueError(
                f"batch_size = {batch_size} exceeds the {self.size} stored "
                "transitions")
        total = self._tree[1]
        targets = (np.arange(batch_size) + rng.random(batch_size)) * (
                total / batch_size)
        node = np.ones(batch_size, np.int64)
        while node[0] < self._leaves:
            left = self._tree[2 * node]
            right = targets > left
            targets = np.where(right, targets - left, targets)
            node = 2 * node + right
        index = np.minimum(node - self._leaves, self.size - 1)
        probabilities = np.maximum(self._tree[index + self._leaves] / total,
                                   np.finfo(np.float64).tiny)
        weights = (self.size * probabilities) ** -beta
        weights /= weights.max()
        batch = (self.obs[index], self.actions[index], self.rewards[index],
                 self.next_obs[index], self.discounts[index])
        return batch, index, weights.astype(np.float32)

    def update_priorities(self, index: np.ndarray, td_errors: np.ndarray):
        """Sets the sampled rows' priorities from their new absolute TD
        errors (a row drawn twice keeps the last)."""
        priorities = np.abs(td_errors).astype(np.float64) + self.epsilon
        self._max_priority = max(self._max_priority, float(priorities.max()))
        self._set(index, priorities ** self.alpha)

    def _set(self, index: np.ndarray, values: np.ndarray) -> None:
        node = index + self._leaves
        self._tree[node] = values
        node = np.unique(node // 2)
        while node[0] >= 1:
            self._tree[node] = self._tree[2 * node] + self._tree[2 * node + 1]
            if node[0] == 1:
                break
            node = np.unique(node // 2)

    def state_dict(self) -> Dict[str, np.ndarray]:
        state = super().state_dict()
        state["priorities"] = self._tree[self._leaves:self._leaves + self.size].copy()
        state["max_priority"] = np.array(self._max_priority)
        return state

    def load_state_dict(self, state: Dict[str, np.ndarray]) -> None:
        super().load_state_dict(state)
        self._tree[:] = 0
        self._max_priority = float(state["max_priority"])
        self._set(np.arange(self.size), state["priorities"])


class NStepFolder:
    """Turns per-stream one-step transitions into n-step transitions.

    A stream is one lander slot of one environment; `num_streams` slots are
    fed together, a boolean mask saying which of them produced a transition.
    While a stream's episode runs, each new transition completes the n-step
    transition that started n-1 transitions earlier:
        R = r_t + gamma r_{t+1} + ... + gamma^{n-1} r_{t+n-1},
        discount = gamma^n (0 if the last transition was terminal).
    When a stream ends (terminated or truncated), its shorter tails are
    emitted too. With n = 1 it passes transitions through.
    """

    def __init__(self, n: int, gamma: float, num_streams: int, obs_size: int):
        if n < 1:
            raise ValueError(f"n_step = {n} is out of range; allowed: >= 1")
        self.n = n
        self.gamma = gamma
        self._obs = np.zeros((n, num_streams, obs_size), np.float32)
        self._actions = np.zeros((n, num_streams), np.int64)
        self._rewards = np.zeros((n, num_streams), np.float64)
        # Transitions held per stream (at most n - 1 between calls).
        self._held = np.zeros(num_streams, np.int64)
        # Slot of the oldest held transition per stream, in the ring of n.
        self._start = np.zeros(num_streams, np.int64)

    def add(self, mask, obs, actions, rewards, next_obs, terminated, ended
            ) -> Optional[tuple]:
        """Feeds one transition per masked stream; returns what is complete.

        mask, terminated, ended: bool [num_streams]; obs, next_obs: [S, obs];
        actions, rewards: [S]. `ended` is terminated or truncated. Returns
        (obs, actions, rewards, next_obs, discounts) arrays, or None.
        """
        if self.n == 1:
            index = np.flatnonzero(mask)
            discounts = np.where(terminated[index], 0.0, self.gamma)
            return (obs[index], actions[index], rewards[index], next_obs[index],
                    discounts.astype(np.float32))
        out = []
        streams = np.flatnonzero(mask)
        slot = (self._start[streams] + self._held[streams]) % self.n
        self._obs[slot, streams] = obs[streams]
        self._actions[slot, streams] = actions[streams]
        self._rewards[slot, streams] = rewards[streams]
        self._held[streams] += 1
        # Streams whose oldest transition now spans n steps.
        full = streams[self._held[streams] == self.n]
        if len(full):
            out.append(self._emit(full, next_obs, terminated))
            self._start[full] = (self._start[full] + 1) % self.n
            self._held[full] -= 1
        # Ended streams: flush every remaining shorter tail, oldest first.
        ending = streams[ended[streams]]
        while len(ending):
            out.append(self._emit(ending, next_obs, terminated))
            self._start[ending] = (self._start[ending] + 1) % self.n
            self._held[ending] -= 1
            ending = ending[self._held[ending] > 0]
        self._start[streams[ended[streams]]] = 0
        if not out:
            return None
        return tuple(np.concatenate([part[i] for part in out])
                     for i in range(5))

    def _emit(self, streams, next_obs, terminated):
        """The transition from each stream's oldest held step to next_obs."""
        held = self._held[streams]
        start = self._start[streams]
        returns = np.zeros(len(streams), np.float64)
        for k in range(self.n):
            use = k < held
            slot = (start + k) % self.n
            returns += np.where(use, self.gamma ** k, 0.0) * self._rewards[
                slot, streams]
        discounts = np.where(terminated[streams], 0.0, self.gamma ** held)
        return (self._obs[start, streams], self._actions[start, streams],
                returns.astype(np.float32), next_obs[streams],
                discounts.astype(np.float32))
