"""The PettingZoo parallel environment: one StepEnv call per step."""

from __future__ import annotations

import weakref
from collections.abc import Mapping

import grpc
import numpy as np
from pettingzoo import ParallelEnv

from . import _arrays, _lease, _record
from ._base import RemoteEnvBase, _delete_env
from ._errors import MLLError, invalid_argument
from ._actions import check_actions, check_agents
from ._remote import Columns, rebuild, seed_value
from ._stubs import pb


def decode_step(data: "pb.StepData", names: list[str]):
    """(observations, rewards, terminations, truncations, infos) dicts of the agents stepped."""
    columns = Columns.decode(data)
    stepped = [i for i, flag in enumerate(_arrays.to_list(data.stepped)) if flag]
    return (
        {names[i]: columns.observations[i] for i in stepped},
        {names[i]: columns.rewards[i] for i in stepped},
        {names[i]: columns.terminations[i] for i in stepped},
        {names[i]: columns.truncations[i] for i in stepped},
        {names[i]: columns.info(i) for i in stepped},
    )


class MultiLunarLanderParallelEnv(RemoteEnvBase, ParallelEnv):
    """All active landers act at once. Spaces, options and infos as in MultiLunarLanderEnv.

    step(actions) needs an action for every agent in `agents`; it returns dicts over those
    agents, and afterwards `agents` is the previous list minus the agents just terminated or
    truncated. Once the episode is over (`agents` empty), step({}) returns five empty dicts, as
    PettingZoo's own parallel envs do (SuperSuit's black_death_v3 relies on it); a step with
    actions after the end, or any step before the first reset, raises FAILED_PRECONDITION.

    state() -> bytes, restore(state), clone(): the env at this point, as bytes that recreate it
    to the same bits on any server of the same release (see _record and docs/python.md).
    """

    def _init_state(self) -> None:
        self.agents: list[str] = []
        self._was_reset = False
        n = len(self.possible_agents)
        self._actions = np.zeros((n, 2) if self.continuous else (n,), np.float32 if self.continuous else np.int32)
        self._dtype = pb.DTYPE_FLOAT32 if self.continuous else pb.DTYPE_INT32
        self._log = _record.GrowingLog(1, self._actions.nbytes)  # Operations since the seeded reset.
        self._seed: int | None = None
        self._last_observations = b""

    def reset(self, seed: int | None = None, options: dict | None = None):
        request = pb.ResetEnvRequest(name=self._name)
        seed = seed_value(seed)
        if seed is not None:
            request.seed = seed
        response = self._connection.call("ResetEnv", request)
        data = response.data
        if response.HasField("seed"):
            self._seed = int(response.seed)
            self._log.clear()
        else:
            self._log.append(np.array([_record.RESET], np.uint8), np.zeros((1, self._actions.nbytes), np.uint8))
        self._last_observations = _arrays.to_numpy(data.observations).astype("<f4").tobytes()
        observations, _, _, _, infos = decode_step(data, self.possible_agents)
        self.agents = list(self.possible_agents)
        self._was_reset = True
        self._show_if_human()
        return observations, infos

    def step(self, actions: dict):
        if not actions and not self.agents and self._was_reset:
            return {}, {}, {}, {}, {}
        if not isinstance(actions, Mapping):
            raise invalid_argument(
                f"actions is a {type(actions).__name__}; expected a dict from agent name to action"
            )
        check_agents(actions, self._agent_index, self.agents)
        missing = [agent for agent in self.agents if agent not in actions]
        if missing:
            raise invalid_argument(f"actions has no entry for active agent(s) {missing}")
        self._actions.fill(0)
        self._actions[[self._agent_index[agent] for agent in self.agents]] = check_actions(
            [actions[agent] for agent in self.agents], self.continuous, (len(self.agents),),
            f"the actions of {self.agents}", labels=self.agents,
        )
        request = pb.StepEnvRequest(name=self._name)
        _arrays.to_proto(self._actions, pb.DTYPE_FLOAT32 if self.continuous else pb.DTYPE_INT32, request.actions)
        data = self._connection.call("StepEnv", request).data
        self._log.append(np.array([_record.STEP], np.uint8), request.actions.data)
        self._last_observations = _arrays.to_numpy(data.observations).astype("<f4").tobytes()
        result = decode_step(data, self.possible_agents)
        terminations, truncations = result[2], result[3]
        self.agents = [a for a in self.agents if not (terminations.get(a) or truncations.get(a))]
        self._show_if_human()
        return result

    # ----------------------------------------------------------------- env state

    def state(self) -> bytes:
        """This env's state: bytes that recreate it at this point (restore, clone, or a vector
        env's restore_env) to the same bits on any server of the same release. FAILED_PRECONDITION
        before the first reset or past the record's limit (docs/python.md)."""
        if self._seed is None or self._log.full:
            raise MLLError(
                grpc.StatusCode.FAILED_PRECONDITION,
                f"{self._name} has no state to give: "
                + ("it was never reset" if self._seed is None else
                   f"its record passed {_record.MAX_RECORD_STEPS} operations since its last seeded reset")
                + "; reset(seed=...) starts a new record",
            )
        kinds, actions = self._log.of_env(0)
        record = _record.EnvRecord(self._seed, kinds, actions, self._last_observations)
        info = self.server_info
        return _record.encode_state(
            self._env_config, info.protocol, info.server_version, record, self._dtype, self._actions.nbytes
        )

    def restore(self, state: bytes) -> dict:
        """Puts this env at the point `state` describes: a new server-side env replays it, checked
        against the state's last observations, then replaces this one's. Returns the observations
        of the agents active then. INVALID_ARGUMENT for a damaged state or one of an env with other
        options, DATA_LOSS when the replay gives other bits; on any error the env is untouched."""
        decoded = _record.decode_state(state)
        _record.check_config(decoded.config, self._env_config, decoded.row_bytes, decoded.dtype)
        (env,), (data,) = _record.replay(
            self._connection, self._env_config, [decoded.record], [f"{self._name} (restored)"],
            self._dtype, self._actions.shape,
        )
        old = self._name
        self._deleter.detach()  # The old env goes; the connection stays.
        try:
            self._connection.call("DeleteEnv", pb.DeleteEnvRequest(name=old), timeout=2.0)
        except MLLError:
            pass
        self._name = env.name
        self._deleter = weakref.finalize(self, _delete_env, self._connection, env.name)
        _lease.hold(self._connection, env.name, env.idle_timeout_s)
        record = decoded.record
        self._seed = record.seed
        self._log.clear()
        for kind, row in zip(record.kinds, record.actions):
            self._log.append(np.array([kind], np.uint8), row[None])
        self._last_observations = record.last_observations
        # Active now: every agent after a reset, else those that stepped and are not done.
        if record.kinds.size == 0 or record.kinds[-1] != _record.STEP:
            self.agents = list(self.possible_agents)
        else:
            done = np.logical_or(_arrays.to_numpy(data.terminations), _arrays.to_numpy(data.truncations))
            stepped = _arrays.to_numpy(data.stepped).astype(bool)
            self.agents = [a for i, a in enumerate(self.possible_agents) if stepped[i] and not done[i]]
        self._was_reset = True
        observations = np.frombuffer(record.last_observations, "<f4").reshape(len(self.possible_agents), 12)
        return {agent: observations[self._agent_index[agent]].astype(np.float32) for agent in self.agents}

    def clone(self) -> "MultiLunarLanderParallelEnv":
        """A new env on the same server at this same point (state() restored into it)."""
        state = self.state()
        other = rebuild(type(self), self._init_kwargs)
        try:
            other.restore(state)
        except BaseException:
            other.close()
            raise
        return other
