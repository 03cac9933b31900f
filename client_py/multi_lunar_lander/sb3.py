"""Every lander as one environment of a Stable-Baselines3 `VecEnv` (parameter sharing), on
VectorEnv's packed batched step: SB3's PPO, A2C, DQN ... train on it without SuperSuit. Needs
the optional extra `multi_lunar_lander[sb3]` (stable-baselines3).

Layout and seeding as gym_vector_env: num_envs = envs x landers, row k is lander
k % n_landers of env k // n_landers; seed(s) then reset() gives env i the seed s + i.

SB3 resets a done environment within the step (its observation is the next episode's first,
the final one is in infos[k]["terminal_observation"]); the server resets an env one step after
its last lander is done. The rule that bridges the two, so that every transition SB3 stores is
either a real one or a zero-reward terminal step from the zero observation (nothing is
bootstrapped across an episode end, no idle reward reaches a real return):
  - the step a lander's episode ends: done True, its real final observation in
    "terminal_observation", "TimeLimit.truncated" when it was truncated (not terminated),
    "episode" {"r": return, "l": length} (SB3's ep_rew_mean reads it) and "outcome"; the
    returned observation is zeros (the lander is idle from now on);
  - each step while the lander waits for its env's other landers (action ignored), and its
    env's reset step: done True, reward 0, terminal_observation zeros, "idle" True; the returned
    observation is zeros while waiting and the new episode's first on the reset step.
SB3's logger (ep_rew_mean, ep_len_mean) reads the real episodes' "episode" entries directly, so
no VecMonitor is needed; a VecMonitor would count every idle step as a one-step episode.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np
from stable_baselines3.common.vec_env import VecEnv

from ._remote import rebuild
from .gym_vector import lander_step
from .vector import VectorEnv


class SB3VecEnv(VecEnv):
    """`num_envs` Multi Lunar Lander environments as an SB3 VecEnv of num_envs x n_landers
    environments (see the module docstring). Arguments as for `vector_env`. Pickles as its
    arguments (a new set of environments on the same servers)."""

    def __init__(self, num_envs: int, address: str | Sequence[str] | None = None, **kwargs: Any):
        self.vector = VectorEnv(num_envs, address=address, **kwargs)
        self.n_landers = self.vector.n_landers
        self.render_mode = None
        action_shape = (2,) if self.vector.continuous else ()
        self._action_shape = (self.vector.num_envs, self.n_landers) + action_shape
        self.num_envs = self.vector.num_envs * self.n_landers  # VecEnv.__init__ calls get_attr.
        super().__init__(
            self.num_envs,
            self.vector.single_observation_space,
            self.vector.single_action_space,
        )

    def __reduce__(self):
        return rebuild, (type(self), self.vector._init_kwargs)

    def reset(self) -> np.ndarray:
        observations, _ = self.vector.reset(seed=self._seeds[0])
        self._reset_seeds()
        self.reset_infos = [{} for _ in range(self.num_envs)]
        return observations.reshape(self.num_envs, -1)

    def step_async(self, actions: np.ndarray) -> None:
        self.vector.step_async(np.asarray(actions).reshape(self._action_shape))

    def step_wait(self):
        step = lander_step(self.vector.step_wait(), self.num_envs)
        observations = step.observations
        infos: list[dict] = [{} for _ in range(self.num_envs)]
        for k in np.flatnonzero(step.ended):
            infos[k] = {
                "terminal_observation": observations[k].copy(),
                "TimeLimit.truncated": bool(step.truncated[k] and not step.terminated[k]),
                "episode": {"r": float(step.infos["episode_return"][k]), "l": int(step.infos["episode_length"][k])},
                "outcome": int(step.infos["outcome"][k]),
            }
        observations[step.ended] = 0.0
        zeros = np.zeros_like(observations[0])
        for k in np.flatnonzero(step.idle):
            infos[k] = {"terminal_observation": zeros, "TimeLimit.truncated": False, "idle": True}
        return observations, step.rewards, step.ended | step.idle, infos

    def close(self) -> None:
        vector = getattr(self, "vector", None)  # None when __init__ failed.
        if vector is not None:
            vector.close()

    def get_attr(self, attr_name: str, indices=None) -> list:
        """An attribute shared by every lander (spaces, render_mode, ...), once per index."""
        return [getattr(self, attr_name)] * len(list(self._get_indices(indices)))

    def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
        raise AttributeError(f"set_attr({attr_name!r}): the landers' environments have no per-lander attributes")

    def env_method(self, method_name: str, *method_args, indices=None, **method_kwargs) -> list:
        raise AttributeError(f"env_method({method_name!r}): the landers' environments have no per-lander methods")

    def env_is_wrapped(self, wrapper_class, indices=None) -> list:
        return [False] * len(list(self._get_indices(indices)))
