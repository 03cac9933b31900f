"""The PettingZoo AEC (turn-by-turn) environment, a thin client of the server's StepAgent.

The server keeps PettingZoo's AEC bookkeeping (agent order, the dead-step rule, `rewards` and
`_cumulative_rewards`); after each call this class copies the returned `AecState` into the
attributes pettingzoo.AECEnv's own `last()`, `observe()` and `agent_iter()` read. Each turn is
recorded (AGENT_STEP or DEAD_STEP, see _record), so replaying the record gives the same agent
selection and bits: what failover and snapshot()/restore()/clone() use.
"""

from __future__ import annotations

import numpy as np
from pettingzoo import AECEnv

from . import _arrays, _record
from ._actions import check_actions
from ._base import RemoteEnvBase
from ._remote import Columns, seed_value
from ._stubs import pb


class MultiLunarLanderEnv(RemoteEnvBase, AECEnv):
    """Multi Lunar Lander, PettingZoo AEC: N landers (`lander_0` .. `lander_{N-1}`) in one
    Box2D world with Gymnasium's LunarLander-v3 physics. Agents take turns (`lander_0` first);
    the world steps once the last live lander has acted. The full reference, with every
    constant, is docs/environment.md in the repository.

    ## Action space
    Discrete(4): 0 nothing, 1 left orientation engine, 2 main engine, 3 right orientation
    engine. With continuous=True, Box(-1, 1, (2,), float32): [main, lateral]; main > 0 fires the
    main engine at 50-100%, |lateral| > 0.5 a side engine at 50-100%.

    ## Observation space
    Box(-inf, inf, (12,), float32): [0] x and [1] y relative to the pad, [2] [3] velocities,
    [4] angle, [5] angular velocity, [6] [7] leg contacts (1.0/0.0), [8] [9] and [10] [11] this
    lander's position relative to its nearest and second-nearest active neighbours ((0, 0) when
    there is none). All scaled as Gymnasium's LunarLander.

    ## Rewards
    Gymnasium's shaping (distance, speed, tilt, legs) plus 30 x the distance to each of the two
    nearest neighbours, minus 0.30 per frame of main engine and 0.03 of side engine; a damaged
    lander adds damage_reward + terminate_reward, a landed one successful_reward; with
    terminate_on_damage the others add terminate_reward; with shared_reward every lander
    stepped gets the mean.

    ## Episode end
    A lander terminates when it lands (body at rest on the ground, undamaged), crashes (its body
    touches anything, or a leg touches anything but the moon), leaves the screen
    (|x| >= 1), or, with terminate_on_damage, when another lander is damaged; every active
    lander is truncated after max_cycles steps. infos[agent] then holds "outcome" ("landed",
    "crashed", "out_of_bounds", "truncated", "aborted") with "episode_return" and
    "episode_length".

    ## Arguments
    n_landers (1..32, default 3), continuous (False), max_cycles (500), gravity (-10, in
    (-12, 0)), enable_wind (False), wind_power (15, [0, 20]), turbulence_power (1.5, [0, 2]),
    remove_on_damage, terminate_on_damage, shared_reward (True), damage_reward (-100),
    successful_reward (+100), terminate_reward (-100), render_mode (None, "rgb_array",
    "human"), and address (None: an embedded local mll_server), server_index, tls_root_cert,
    tls_server_name, token, failover (on by default with several servers, a host name or the embedded one:
    an env lost with its server is recreated on another from its record and the turn retried;
    `failovers` counts the events), step_timeout_s (5 s; 0: none: each call's deadline, past which
    the server counts as lost, or DEADLINE_EXCEEDED names it and the timeout).

    ## State
    state() -> float32 (n_landers * 12,), described by state_space: PettingZoo's global state,
    lander i's observe() at [12 i, 12 i + 12); zeros for landers no longer in `agents` (removed by
    their dead step).

    ## Snapshot
    snapshot() -> bytes, restore(snapshot), clone(): as the parallel env's, for AEC turns.
    """

    def _init_state(self) -> None:
        self.agents: list[str] = []
        self.rewards: dict[str, float] = {}
        self._cumulative_rewards: dict[str, float] = {}
        self.terminations: dict[str, bool] = {}
        self.truncations: dict[str, bool] = {}
        self.infos: dict[str, dict] = {}
        self.agent_selection = self.possible_agents[0]
        self._observations = np.zeros((len(self.possible_agents), self._observation_size), dtype=np.float32)

    def reset(self, seed: int | None = None, options: dict | None = None) -> None:
        request = pb.ResetEnvRequest()
        seed = seed_value(seed)
        if seed is not None:
            request.seed = seed
        response = self._call("ResetEnv", request)
        self._record_reset(response)
        self._apply(response.aec)
        self._show_if_human()

    def step(self, action) -> None:
        """Acts for agent_selection; `action` must be None for a terminated or truncated agent
        (PettingZoo's dead step). Server errors raise MLLError."""
        agent = self._agent_index[self.agent_selection]
        self._actions.fill(0)
        if action is None:
            kind = _record.DEAD_STEP
        else:
            kind = _record.AGENT_STEP
            self._actions[agent] = check_actions(action, self.continuous, (), f"the action of {self.agent_selection}")
        response = self._call("StepAgent", _record.agent_step_request(kind, self._actions, agent))
        self._record_step(kind, response)
        self._apply(response.aec)
        if response.aec.world_stepped:
            self._show_if_human()

    def restore(self, snapshot: bytes) -> None:
        """Puts this env at the point `snapshot` (another AEC env's snapshot()) describes,
        agent_selection and the PettingZoo attributes included: a new server-side env replays it,
        checked against the snapshot's last observations, then replaces this one's.
        INVALID_ARGUMENT for a damaged snapshot or one of an env with other options (or of a
        parallel or vector env, which steps with the other step API), DATA_LOSS when the replay
        gives other bits; on any error the env is untouched."""
        self._apply(self._restore(snapshot, _record.AEC_OPERATIONS).aec)

    def observe(self, agent: str) -> np.ndarray:
        return self._observations[self._agent_index[agent]].copy()

    def _observation_rows(self) -> np.ndarray:
        return self._observations

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
