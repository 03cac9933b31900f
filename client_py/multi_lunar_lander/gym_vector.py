"""Every lander as one sub-environment of a `gymnasium.vector.VectorEnv`: parameter sharing for
single-agent trainers (CleanRL-style PPO, Gymnasium's vector wrappers). Built on VectorEnv's
packed batched step, so a step is one StepBatch per server whatever the number of landers.

Layout: `num_envs` = envs x landers; sub-environment k is lander k % n_landers of env
k // n_landers (row-major reshape of VectorEnv's (envs, landers) arrays, no copy).

Autoreset: Gymnasium's NEXT_STEP, which is what the server does (metadata["autoreset_mode"]).
The step on which a lander's episode ends returns its real final observation, reward and
terminated/truncated; its final observation IS that step's observation (NEXT_STEP needs no
"final_obs" entry). Once every lander of an env is done, that env's next step ignores the
actions and returns the new episode's first observations with reward 0, not done: the reset
step, as Gymnasium's own NEXT_STEP vector envs do.

Landers that finish before their env does (a crashed lander while the others fly) are idle
until the env resets: their actions are ignored, observation zeros, reward 0, terminated and
truncated False, infos["idle"] True. A lander reports its end exactly once. So the real
transitions (rows with infos["idle"] False that are not the reset step after a done) carry
exact rewards and termination: nothing of an idle wait is added to a real episode's return, and
no value is bootstrapped across an episode end. A trainer that drops rows with infos["idle"]
(examples/ppo_cleanrl.py) trains on real transitions only; one that does not sees idle rows as
zero-reward steps from the zero observation. Gymnasium's RecordEpisodeStatistics counts the
idle wait into the length of the lander's next episode (returns are exact); the exact per-lander
statistics are in infos["episode_return"] / infos["episode_length"].

infos (Gymnasium's vector convention: a value array and a "_key" bool mask, num_envs rows):
  "episode_return", "episode_length", "outcome" (codes indexing OUTCOMES): set on the step a
    lander's episode ends, masked by "_episode_return" etc.
  "idle": True where the row's action was ignored (idle landers and the env's reset step).

Needs gymnasium >= 1.0 (the VectorEnv API of 1.0: step() returns the whole batch, autoreset on
the next step); with gymnasium 0.29 this module imports (the rest of the package works) and
creating a GymVectorEnv raises ImportError saying what to install. metadata["autoreset_mode"]
is set from gymnasium 1.1 on, which added the key; 1.0 knows NEXT_STEP only.
"""

from __future__ import annotations

from typing import Any, NamedTuple, Sequence

import gymnasium
import numpy as np
from gymnasium.vector.utils import batch_space

try:  # gymnasium >= 1.1
    from gymnasium.vector import AutoresetMode
except ImportError:  # gymnasium 1.0 (NEXT_STEP is its only mode) or 0.29 (see _require_vector_api)
    AutoresetMode = None

from ._errors import invalid_argument
from ._remote import rebuild
from .vector import VectorEnv


class LanderStep(NamedTuple):
    """One step of a VectorEnv seen lander by lander (arrays of envs x landers rows)."""

    observations: np.ndarray  # float32 (N, 12); zeros for idle landers.
    rewards: np.ndarray  # float32 (N,); 0 where idle.
    terminated: np.ndarray  # bool (N,), True only on the step a lander's episode ends.
    truncated: np.ndarray
    idle: np.ndarray  # bool (N,): the action was ignored (done lander, or its env's reset step).
    ended: np.ndarray  # bool (N,): terminated | truncated.
    reset: np.ndarray  # bool (N,): the env's reset step (observation is the new episode's first).
    infos: dict  # VectorEnv's infos, flattened to (N,) where per lander.


def lander_step(result, n: int) -> LanderStep:
    """VectorEnv.step()'s result, flattened to one row per lander (views, no copies)."""
    observations, rewards, terminations, truncations, active, infos = result
    idle = ~active.reshape(n)
    terminated = terminations.reshape(n) & ~idle
    truncated = truncations.reshape(n) & ~idle
    rewards = rewards.reshape(n)
    rewards[idle] = 0.0  # The server already sends 0 there; this keeps the rule in one place.
    n_landers = active.shape[1]
    return LanderStep(
        observations.reshape(n, -1),
        rewards,
        terminated,
        truncated,
        idle,
        terminated | truncated,
        np.repeat(infos["auto_reset"], n_landers),
        {
            "outcome": infos["outcome"].reshape(n),
            "episode_return": infos["episode_return"].reshape(n),
            "episode_length": infos["episode_length"].reshape(n),
        },
    )


# gymnasium 0.29's VectorEnv is the older API (step_async/step_wait, reset_wait, a constructor
# taking the spaces), which 1.0 removed; this class is written for 1.0's.
_VECTOR_API_1 = not hasattr(gymnasium.vector.VectorEnv, "step_wait")


def _require_vector_api() -> None:
    if not _VECTOR_API_1:
        raise ImportError(
            f"gym_vector_env / GymVectorEnv needs gymnasium >= 1.0 (its VectorEnv API); this "
            f"environment has gymnasium {gymnasium.__version__}: pip install 'gymnasium>=1.0'. "
            "env, parallel_env and vector_env work with gymnasium 0.29 too."
        )


class GymVectorEnv(gymnasium.vector.VectorEnv):
    """`num_envs` Multi Lunar Lander environments as a gymnasium.vector.VectorEnv of
    num_envs x n_landers sub-environments, one per lander (see the module docstring for the
    layout, NEXT_STEP autoreset and the idle-lander rule). Arguments as for `vector_env`,
    transport= included (how the steps travel: "auto", "shared_memory" or "native").

    reset(seed=None, options=None): seed s gives env i the seed s + i (the same bits as
      vector_env(...).reset(seed=s)); None continues each env's generator stream.
    step(actions): actions (num_envs,) ints or, continuous, (num_envs, 2) floats ->
      (observations float32 (num_envs, 12), rewards float32, terminations, truncations, infos).
    Pickles as its arguments (a new set of environments on the same servers).
    """

    metadata = {"render_modes": []}
    if AutoresetMode is not None:
        metadata["autoreset_mode"] = AutoresetMode.NEXT_STEP

    def __init__(self, num_envs: int, address: str | Sequence[str] | None = None, **kwargs: Any):
        _require_vector_api()
        self.vector = VectorEnv(num_envs, address=address, **kwargs)
        self.n_landers = self.vector.n_landers
        self.continuous = self.vector.continuous
        self.num_envs = self.vector.num_envs * self.n_landers
        self.single_observation_space = self.vector.single_observation_space
        self.single_action_space = self.vector.single_action_space
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.render_mode = None
        action_shape = (2,) if self.continuous else ()
        self._action_shape = (self.vector.num_envs, self.n_landers) + action_shape

    def __reduce__(self):
        return rebuild, (type(self), self.vector._init_kwargs)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is not None and not isinstance(seed, (int, np.integer)):
            raise invalid_argument(
                f"seed is {seed!r}; expected None or one integer (env i gets seed + i; its landers share it)"
            )
        super().reset(seed=seed)
        observations, _ = self.vector.reset(seed=seed)
        return observations.reshape(self.num_envs, -1), {}

    def step(self, actions):
        actions = np.asarray(actions)
        if actions.shape != self.action_space.shape:
            raise invalid_argument(
                f"actions have shape {actions.shape}; expected {self.action_space.shape}: one action per "
                f"lander ({self.vector.num_envs} envs x {self.n_landers} landers)"
            )
        step = lander_step(self.vector.step(actions.reshape(self._action_shape)), self.num_envs)
        ended = step.ended
        infos = {"idle": step.idle, "_idle": step.idle}
        if ended.any():
            for key, value in step.infos.items():
                infos[key] = value
                infos["_" + key] = ended
        return step.observations, step.rewards, step.terminated, step.truncated, infos

    def close_extras(self, **kwargs: Any) -> None:
        vector = getattr(self, "vector", None)  # None when __init__ failed (gymnasium's __del__ closes).
        if vector is not None:
            vector.close()
