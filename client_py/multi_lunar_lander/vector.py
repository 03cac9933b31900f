"""Many environments stepped together: one StepBatch call per step, arrays in and out.

Episode ends (auto-reset): the environments are created with the server's `auto_reset`. When
an environment's episode is over (no lander active), its NEXT step ignores the actions and
starts a new episode, continuing that environment's generator stream (no reseed): the result
holds the new episode's first observations, zero rewards, no terminations/truncations, and
`infos["auto_reset"][i]` is True. Those rows are not transitions, so `active[i]` is all False
for them. Observations of agents that are done (before the episode is over) are zero rows and
their `active` entries are False.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from . import _arrays
from ._errors import from_item_error, invalid_argument
from ._remote import Connection, action_array, config_dict, make_config, seed_value, space_from_proto
from ._stubs import pb

# (StepData field, wire dtype, per-env trailing shape given n_landers).
_COLUMNS = (
    ("observations", pb.DTYPE_FLOAT32, lambda n: (n, 12)),
    ("rewards", pb.DTYPE_FLOAT32, lambda n: (n,)),
    ("terminations", pb.DTYPE_UINT8, lambda n: (n,)),
    ("truncations", pb.DTYPE_UINT8, lambda n: (n,)),
    ("stepped", pb.DTYPE_UINT8, lambda n: (n,)),
    ("outcomes", pb.DTYPE_UINT8, lambda n: (n,)),
    ("episode_returns", pb.DTYPE_FLOAT32, lambda n: (n,)),
    ("episode_lengths", pb.DTYPE_INT32, lambda n: (n,)),
)


class VectorEnv:
    """`num_envs` Multi Lunar Lander environments with the same options.

    reset(seed=None, options=None) -> (observations, infos): observations float32
      (num_envs, n_landers, 12); seed s gives env i the seed s + i (None continues each env's
      stream).
    step(actions) -> (observations, rewards, terminations, truncations, active, infos): actions
      int (num_envs, n_landers) or, continuous, float (num_envs, n_landers, 2); entries of done
      agents are ignored. rewards float32 (num_envs, n_landers); terminations, truncations and
      active bool (num_envs, n_landers): `active` marks the rows that carry a transition (the
      agent was active at the start of the step and this is not an auto-reset).
    infos: "auto_reset" bool (num_envs,), "episode_over" bool (num_envs,), "outcome" uint8
      (num_envs, n_landers) with codes indexing OUTCOMES, "episode_return" float32 and
      "episode_length" int32 (num_envs, n_landers) (so far in the episode, final once done).
    """

    def __init__(self, num_envs: int, address: str | None = None, **options: Any):
        if int(num_envs) != num_envs or num_envs < 1:
            raise invalid_argument(f"num_envs is {num_envs!r}; expected an integer >= 1")
        self.num_envs = int(num_envs)
        config = make_config(None, True, options)
        self._connection = Connection(address)
        self._names: list[str] = []
        try:
            waits = [
                self._connection.future("CreateEnv", pb.CreateEnvRequest(config=config))
                for _ in range(self.num_envs)
            ]
            envs = []
            for wait in waits:
                envs.append(wait())
                self._names.append(envs[-1].name)
        except BaseException:
            self.close()
            raise
        spec = envs[0]
        self.config = config_dict(spec.config)
        self.continuous = bool(spec.config.continuous)
        self.n_landers = int(spec.config.n_landers)
        self.possible_agents = list(spec.possible_agents)
        self.single_observation_space = space_from_proto(spec.observation_space)
        self.single_action_space = space_from_proto(spec.action_space)
        # The batch request is built once; each step only replaces the action bytes.
        self._request = pb.StepBatchRequest()
        self._action_dtype = action_dtype = pb.DTYPE_FLOAT32 if self.continuous else pb.DTYPE_INT32
        action_shape = (self.n_landers, 2) if self.continuous else (self.n_landers,)
        for name in self._names:
            step = self._request.steps.add(name=name)
            step.actions.dtype = action_dtype
            step.actions.shape.extend(action_shape)
        self._steps = list(self._request.steps)

    @property
    def address(self) -> str:
        return self._connection.address

    @property
    def names(self) -> list[str]:
        """The server-side resource names, `envs/{id}`, in env order."""
        return list(self._names)

    def _stack(self, datas: list, auto_reset: np.ndarray, episode_over: np.ndarray):
        columns = {
            field: _arrays.stack_bytes(
                [getattr(data, field).data for data in datas], dtype, (self.num_envs,) + shape(self.n_landers)
            )
            for field, dtype, shape in _COLUMNS
        }
        active = columns["stepped"].astype(bool)
        active[auto_reset] = False
        infos = {
            "auto_reset": auto_reset,
            "episode_over": episode_over,
            "outcome": columns["outcomes"],
            "episode_return": columns["episode_returns"],
            "episode_length": columns["episode_lengths"],
        }
        return (
            columns["observations"],
            columns["rewards"],
            columns["terminations"].astype(bool),
            columns["truncations"].astype(bool),
            active,
            infos,
        )

    def reset(self, seed: int | None = None, options: dict | None = None):
        seed = seed_value(seed)
        waits = []
        for index, name in enumerate(self._names):
            request = pb.ResetEnvRequest(name=name)
            if seed is not None:
                request.seed = (seed + index) % 2**64
            waits.append(self._connection.future("ResetEnv", request))
        datas = [wait().data for wait in waits]
        no = np.zeros(self.num_envs, dtype=bool)
        observations, _, _, _, _, infos = self._stack(datas, no, no.copy())
        return observations, infos

    def step(self, actions):
        block = action_array(actions, self.continuous, (self.num_envs, self.n_landers), "actions")
        for step, data in zip(self._steps, _arrays.row_bytes(block, self._action_dtype)):
            step.actions.data = data
        results = self._connection.call("StepBatch", self._request).results
        datas = []
        for index, result in enumerate(results):
            if result.HasField("error"):
                raise from_item_error(result.error.code, result.error.message, f"env {index} ({self._names[index]}): ")
            datas.append(result.data)
        auto_reset = np.fromiter((data.auto_reset for data in datas), dtype=bool, count=self.num_envs)
        episode_over = np.fromiter((data.episode_over for data in datas), dtype=bool, count=self.num_envs)
        return self._stack(datas, auto_reset, episode_over)

    def close(self) -> None:
        """Deletes the environments on the server and closes the connection. Idempotent."""
        if self._connection.closed:
            return
        try:
            waits = [self._connection.future("DeleteEnv", pb.DeleteEnvRequest(name=n)) for n in self._names]
            for wait in waits:
                try:
                    wait()
                except Exception:  # Already gone (e.g. reclaimed by the idle timeout).
                    pass
        finally:
            self._connection.close()

    def __enter__(self) -> "VectorEnv":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
