"""The PettingZoo parallel environment: one StepEnv call per step."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from pettingzoo import ParallelEnv

from . import _arrays, _record
from ._base import RemoteEnvBase
from ._errors import invalid_argument
from ._actions import check_actions, check_agents
from ._remote import Columns, seed_value
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

    state() -> float32 (n_landers * 12,), described by state_space: PettingZoo's global state,
    lander i's latest observation at [12 i, 12 i + 12); zeros for landers not in `agents`.

    snapshot() -> bytes, restore(snapshot), clone(): the env at this point, as bytes that recreate
    it to the same bits on any server of the same release (see _record and docs/python.md).
    failover (on by default with several servers, a host name or the embedded one): an env lost with its
    server is recreated on another from that record and the step retried; `failovers` counts.
    step_timeout_s (default 5, 0: none): the deadline of each call; a server that misses it counts
    as lost (failover), or the call raises DEADLINE_EXCEEDED naming the server and the timeout.
    """

    def _init_state(self) -> None:
        self.agents: list[str] = []
        self._was_reset = False

    def reset(self, seed: int | None = None, options: dict | None = None):
        request = pb.ResetEnvRequest()
        seed = seed_value(seed)
        if seed is not None:
            request.seed = seed
        response = self._call("ResetEnv", request)
        self._record_reset(response)
        observations, _, _, _, infos = decode_step(response.data, self.possible_agents)
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
        request = pb.StepEnvRequest()
        _arrays.to_proto(self._actions, self._dtype, request.actions)
        response = self._call("StepEnv", request)
        self._record_step(_record.STEP, response)
        result = decode_step(response.data, self.possible_agents)
        terminations, truncations = result[2], result[3]
        self.agents = [a for a in self.agents if not (terminations.get(a) or truncations.get(a))]
        self._show_if_human()
        return result

    def restore(self, snapshot: bytes) -> dict:
        """Puts this env at the point `snapshot` (snapshot(), or a vector env's env_snapshot)
        describes: a new server-side env replays it, checked against the snapshot's last
        observations, then replaces this one's. Returns the observations of the agents active then.
        INVALID_ARGUMENT for a damaged snapshot or one of an env with other options (or an AEC
        env's), DATA_LOSS when the replay gives other bits; on any error the env is untouched."""
        answer = self._restore(snapshot, _record.STEP_OPERATIONS)
        # Active now: every agent after a reset, else those that stepped and are not done.
        if isinstance(answer, pb.ResetEnvResponse):
            self.agents = list(self.possible_agents)
        else:
            data = answer.data
            done = np.logical_or(_arrays.to_numpy(data.terminations), _arrays.to_numpy(data.truncations))
            stepped = _arrays.to_numpy(data.stepped).astype(bool)
            self.agents = [a for i, a in enumerate(self.possible_agents) if stepped[i] and not done[i]]
        self._was_reset = True
        observations = self._observation_rows()
        return {agent: observations[self._agent_index[agent]].astype(np.float32) for agent in self.agents}

    def _observation_rows(self) -> np.ndarray:
        """The observations of the latest reset, step or restore, all landers' (the record's)."""
        return np.frombuffer(self._last_observations, "<f4").reshape(len(self.possible_agents), -1)
