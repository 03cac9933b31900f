"""The PettingZoo AEC (turn-by-turn) environment, a thin client of the server's StepAgent.

The server keeps PettingZoo's AEC bookkeeping (agent order, the dead-step rule, `rewards` and
`_cumulative_rewards`); after each call this class copies the returned `AecState` into the
attributes pettingzoo.AECEnv's own `last()`, `observe()` and `agent_iter()` read.
"""

from __future__ import annotations

import numpy as np
from pettingzoo import AECEnv

from . import _arrays
from ._base import RemoteEnvBase
from ._remote import Columns, encode_agent_action, seed_value
from ._stubs import pb


class MultiLunarLanderEnv(RemoteEnvBase, AECEnv):
    """N landers taking turns (`lander_0` first); the world steps once the last live lander has
    acted. Observations Box(-inf, inf, (12,), float32); actions Discrete(4) or, with
    continuous=True, Box(-1, 1, (2,), float32). Options: docs/environment.md.

    infos[agent] holds "outcome" ("landed", "crashed", "out_of_bounds", "truncated", "aborted")
    once the lander is done, with "episode_return" and "episode_length".
    """

    def _init_state(self) -> None:
        self.agents: list[str] = []
        self.rewards: dict[str, float] = {}
        self._cumulative_rewards: dict[str, float] = {}
        self.terminations: dict[str, bool] = {}
        self.truncations: dict[str, bool] = {}
        self.infos: dict[str, dict] = {}
        self.agent_selection = self.possible_agents[0]
        self._observations = np.zeros((len(self.possible_agents), 12), dtype=np.float32)

    def reset(self, seed: int | None = None, options: dict | None = None) -> None:
        request = pb.ResetEnvRequest(name=self._name)
        seed = seed_value(seed)
        if seed is not None:
            request.seed = seed
        self._apply(self._connection.call("ResetEnv", request).aec)
        self._show_if_human()

    def step(self, action) -> None:
        """Acts for agent_selection; `action` must be None for a terminated or truncated agent
        (PettingZoo's dead step). Server errors raise MLLError."""
        request = pb.StepAgentRequest(name=self._name, agent=self._agent_index[self.agent_selection])
        if action is not None:
            encode_agent_action(action, self.continuous, self.agent_selection, request.action)
        aec = self._connection.call("StepAgent", request).aec
        self._apply(aec)
        if aec.world_stepped:
            self._show_if_human()

    def observe(self, agent: str) -> np.ndarray:
        return self._observations[self._agent_index[agent]].copy()

    def _apply(self, aec: "pb.AecState") -> None:
        """Copies the server's AEC state into PettingZoo's attributes."""
        columns = Columns.decode(aec)
        self._observations = columns.observations
        names = self.possible_agents
        indices = list(aec.agents)
        self.agents = [names[i] for i in indices]
        if aec.agent_selection >= 0:
            self.agent_selection = names[aec.agent_selection]
        cumulative = _arrays.to_list(aec.cumulative_rewards)
        self.rewards = {names[i]: columns.rewards[i] for i in indices}
        self._cumulative_rewards = {names[i]: cumulative[i] for i in indices}
        self.terminations = {names[i]: columns.terminations[i] for i in indices}
        self.truncations = {names[i]: columns.truncations[i] for i in indices}
        self.infos = {names[i]: columns.info(i) for i in indices}
