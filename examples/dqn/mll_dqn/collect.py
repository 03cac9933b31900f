"""Experience collection from the Multi Lunar Lander server.

Two collectors with one interface, `step(epsilon) -> (transitions, episodes)`:
  ParallelCollector  the paper's loop: one PettingZoo parallel_env, one gRPC
                     call per environment step;
  VectorCollector    many environments stepped by one StepBatch call, with
                     the server's auto-reset.
Both select the actions of all active landers with one batched forward pass of
the shared network, and feed the per-lander transitions through the n-step
folder. Time spent in the environment and in action selection is added to
`timers`.

`step(epsilon, during)` runs `during()` (the trainer's owed gradient steps) on
the calling thread while the environment call is in flight on a helper thread:
the gRPC call releases the GIL while it waits, so the server's physics on one
core overlaps the learner's arithmetic on the other. What runs and in which
order does not depend on timing, so a seed still gives the same bits.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import time
from typing import Dict, List, Optional

import numpy as np

import multi_lunar_lander
from mll_dqn.agent import RepeatedExploration
from mll_dqn.config import OBS_SIZE, TrainConfig
from mll_dqn.replay import NStepFolder

# A lander that is still flying (the client reports no outcome yet).
NO_OUTCOME = "none"


@dataclasses.dataclass
class EpisodeRecord:
    """One finished episode of one environment."""
    # Sum of every lander's rewards over the episode (the paper's score).
    score: float
    # Per-lander return and outcome name, indexed by lander.
    returns: List[float]
    outcomes: List[str]
    # Environment steps the episode took.
    steps: int


def lander_index(agent: str) -> int:
    """`lander_7` -> 7."""
    return int(agent.rsplit("_", 1)[1])


def outcome_name(info: Dict) -> str:
    """The outcome a lander's info dict reports ("none" while flying)."""
    return info.get("outcome") or NO_OUTCOME


class Timers:
    """Seconds spent per activity (env, act, sample, learn, ...).

    With overlap, "env" is only the wait for the environment left after the
    overlapped work; "env_call" is the whole call as timed on its own thread
    (not part of the split that sums to wall time)."""

    def __init__(self):
        self.seconds: Dict[str, float] = {}

    def add(self, name: str, seconds: float) -> None:
        self.seconds[name] = self.seconds.get(name, 0.0) + seconds


class _Collector:
    """What both collectors share: the agent, one n-step stream per lander
    slot, the timers and the count of environment steps."""

    def __init__(self, agent, config: TrainConfig, rng: np.random.Generator,
                 timers: Timers, num_envs: int):
        self._agent = agent
        self._rng = rng
        self._timers = timers
        self._num_envs = num_envs
        self._n = config.env_config.get("n_landers", 3)
        self._folder = NStepFolder(config.n_step, config.gamma,
                                   num_envs * self._n, OBS_SIZE)
        self._exploration = (
            RepeatedExploration(num_envs * self._n, config.explore_zeta,
                                config.explore_max_steps)
            if config.explore_zeta else None)
        self.env = None
        self.env_steps = 0
        # Made on the first overlapped call; one thread, so calls stay ordered.
        self._worker: Optional[concurrent.futures.ThreadPoolExecutor] = None

    def _act(self, obs: np.ndarray, streams: np.ndarray, epsilon: float):
        """Actions of the lander slots `streams` observing `obs`."""
        if self._exploration is None:
            return self._agent.act(obs, epsilon, self._rng)
        return self._exploration.act(self._agent, obs, streams, epsilon,
                                     self._rng)

    def _ended(self, ended: np.ndarray) -> None:
        """The lander slots where `ended` (bool, one per slot) is True finished
        their episodes."""
        if self._exploration is not None:
            self._exploration.stop(ended)

    def _timed(self, call, *args, during=None):
        """call(*args), its seconds added to the "env" timer; with `during`,
        the call runs on the helper thread while `during()` runs here, and
        "env" gets only the wait left after `during()` returns."""
        if during is None:
            start = time.perf_counter()
            result = call(*args)
            self._timers.add("env", time.perf_counter() - start)
            return result
        if self._worker is None:
            self._worker = concurrent.futures.ThreadPoolExecutor(
                max_workers=1, thread_name_prefix="mll-env")
        future = self._worker.submit(self._call_timed, call, *args)
        during()
        start = time.perf_counter()
        result, seconds = future.result()
        self._timers.add("env", time.perf_counter() - start)
        self._timers.add("env_call", seconds)
        return result

    @staticmethod
    def _call_timed(call, *args):
        start = time.perf_counter()
        result = call(*args)
        return result, time.perf_counter() - start

    def close(self) -> None:
        if self._worker is not None:
            self._worker.shutdown()
        self.env.close()


class ParallelCollector(_Collector):
    """The paper's single-environment loop over a PettingZoo parallel_env."""

    def __init__(self, agent, config: TrainConfig, address: Optional[str],
                 rng: np.random.Generator, timers: Timers, seed: int):
        super().__init__(agent, config, rng, timers, num_envs=1)
        self.env = multi_lunar_lander.parallel_env(address=address,
                                                   **config.env_config)
        self._seed: Optional[int] = seed
        self._obs: Dict[str, np.ndarray] = {}

    def _start_episode(self) -> None:
        # The first reset seeds the environment's generator; later resets
        # continue its stream.
        self._obs, _ = self._timed(self.env.reset, self._seed)
        self._seed = None
        self._returns = np.zeros(self._n)
        self._outcomes = [NO_OUTCOME] * self._n
        self._steps = 0

    def step(self, epsilon: float, during=None):
        if not self._obs:
            self._start_episode()
        agents = list(self._obs)
        start = time.perf_counter()
        batch = np.stack([self._obs[a] for a in agents])
        index = np.array([lander_index(a) for a in agents])
        actions = self._act(batch, index, epsilon)
        self._timers.add("act", time.perf_counter() - start)
        next_obs, rewards, terms, truncs, infos = self._timed(
            self.env.step, {a: int(act) for a, act in zip(agents, actions)},
            during=during)
        self._steps += 1
        self.env_steps += 1
        # Per-slot arrays for the n-step folder (slot i is lander_i).
        n = self._n
        mask = np.zeros(n, bool)
        mask[index] = True
        obs_s = np.zeros((n, OBS_SIZE), np.float32)
        obs_s[index] = batch
        next_s = np.zeros((n, OBS_SIZE), np.float32)
        next_s[index] = np.stack([next_obs[a] for a in agents])
        act_s = np.zeros(n, np.int64)
        act_s[index] = actions
        rew_s = np.zeros(n)
        rew_s[index] = [rewards[a] for a in agents]
        term_s = np.zeros(n, bool)
        term_s[index] = [terms[a] for a in agents]
        ended_s = term_s.copy()
        ended_s[index] |= [truncs[a] for a in agents]
        self._returns += rew_s
        self._ended(ended_s)
        for a, i in zip(agents, index):
            if ended_s[i]:
                self._outcomes[i] = outcome_name(infos.get(a, {}))
        transitions = self._folder.add(mask, obs_s, act_s, rew_s, next_s,
                                       term_s, ended_s)
        self._obs = {a: next_obs[a] for a in self.env.agents}
        episodes = []
        if not self._obs:
            episodes.append(EpisodeRecord(float(self._returns.sum()),
                                          self._returns.tolist(),
                                          list(self._outcomes), self._steps))
        return transitions, episodes


class VectorCollector(_Collector):
    """Many environments per call through the client's vector_env."""

    def __init__(self, agent, config: TrainConfig, address: Optional[str],
                 rng: np.random.Generator, timers: Timers, seed: int):
        super().__init__(agent, config, rng, timers, config.num_envs)
        self.env = multi_lunar_lander.vector_env(config.num_envs,
                                                 address=address,
                                                 **config.env_config)
        obs, _ = self._timed(self.env.reset, seed)
        streams = self._num_envs * self._n
        self._obs = np.asarray(obs, np.float32).reshape(streams, OBS_SIZE)
        self._active = np.ones(streams, bool)
        self._returns = np.zeros((self._num_envs, self._n))
        self._outcomes = [[NO_OUTCOME] * self._n for _ in range(self._num_envs)]
        self._steps = np.zeros(self._num_envs, np.int64)

    def step(self, epsilon: float, during=None):
        n_envs, n = self._num_envs, self._n
        start = time.perf_counter()
        actions = np.zeros(n_envs * n, np.int64)
        active = np.flatnonzero(self._active)
        actions[active] = self._act(self._obs[active], active, epsilon)
        self._timers.add("act", time.perf_counter() - start)
        result = self._timed(self.env.step, actions.reshape(n_envs, n),
                             during=during)
        next_obs, rewards, terms, truncs, reset_rows = (
            _vector_result(result, n_envs, n))
        next_obs = next_obs.reshape(-1, OBS_SIZE)
        rewards = rewards.reshape(-1).astype(np.float64)
        terms = terms.reshape(-1).astype(bool)
        ended = terms | truncs.reshape(-1).astype(bool)
        # Rows that carry a transition: landers active before a real step (not
        # the first observation of an auto-reset episode).
        real = self._active & ~np.repeat(reset_rows, n)
        self._ended(ended)
        transitions = self._folder.add(real, self._obs, actions, rewards,
                                       next_obs, terms, ended)
        self.env_steps += int((~reset_rows).sum())
        returns = self._returns.reshape(-1)
        returns[real] += rewards[real]
        episodes = []
        infos = result[-1]
        for e in range(n_envs):
            if reset_rows[e]:
                continue
            self._steps[e] += 1
            for i in range(n):
                if real[e * n + i] and ended[e * n + i]:
                    self._outcomes[e][i] = _vector_outcome(infos, e, i)
            if not (self._active[e * n:(e + 1) * n] & ~ended[e * n:(e + 1) * n]
                    ).any():
                episodes.append(EpisodeRecord(
                    float(self._returns[e].sum()), self._returns[e].tolist(),
                    list(self._outcomes[e]), int(self._steps[e])))
                self._returns[e] = 0.0
                self._outcomes[e] = [NO_OUTCOME] * n
                self._steps[e] = 0
        # After this step: landers still flying, and every lander of an env
        # whose new episode just began.
        self._active = (self._active & ~ended) | np.repeat(reset_rows, n)
        self._obs = next_obs
        return transitions, episodes


def _vector_result(result, n_envs: int, n: int):
    """Unpacks vector_env.step's result into numpy arrays.

    Returns next_obs [E, n, 12], rewards, terminations, truncations [E, n],
    and a bool [E] telling which rows are the first observation of an
    automatically reset episode.
    """
    obs, rewards, terms, truncs, _, infos = result
    reset_rows = np.asarray(infos.get("auto_reset", np.zeros(n_envs, bool)),
                            bool)
    return (np.asarray(obs, np.float32), np.asarray(rewards),
            np.asarray(terms), np.asarray(truncs), reset_rows)


def _vector_outcome(infos, env_index: int, lander: int) -> str:
    """The outcome name of a vector_env info's code (client's OUTCOMES)."""
    code = int(infos["outcome"][env_index, lander])
    return multi_lunar_lander.OUTCOMES[code] or NO_OUTCOME


def make_collector(agent, config: TrainConfig, address: Optional[str],
                   rng: np.random.Generator, timers: Timers, seed: int):
    kind = ParallelCollector if config.mode == "parallel" else VectorCollector
    return kind(agent, config, address, rng, timers, seed)
