"""What the AEC and parallel environments share beyond their step: creating the server-side
environment, spaces (PettingZoo's state() and state_space too), rendering, deletion, and the
env's record (see _record) with what it gives: snapshot() / restore / clone(), and failover (an
env lost with its server is recreated on another and replayed, and the call retried)."""

from __future__ import annotations

import time
import weakref
from typing import Any, Sequence

import grpc
import gymnasium
import numpy as np

from . import _arrays, _lease, _record
from ._errors import MLLError
from ._channel import Security, is_name, parse_addresses, resolve_endpoints, step_timeout_value
from ._remote import (
    Connection, config_dict, connect_endpoint, create_single, make_config, place, rebuild, space_from_proto,
)
from ._server_info import ServerInfo
from ._stubs import pb
from ._viewer import Viewer

METADATA = {
    "render_modes": ["human", "rgb_array"],
    "render_fps": 50,
    "name": "multi_lunar_lander_v0",
    "is_parallelizable": True,
}


def _delete_env(connection: Connection, name: str) -> None:
    """Deletes the server-side env and closes the connection (on close() or garbage collection).
    The server may already be gone (e.g. at interpreter exit): then there is nothing to delete."""
    try:
        _record.delete_quietly(connection, name)
    finally:
        connection.close()


class RemoteEnvBase:
    """Mixed into pettingzoo.AECEnv / ParallelEnv: one environment on a server."""

    metadata = METADATA

    def __init__(
        self,
        address: str | Sequence[str] | None = None,
        render_mode: str | None = None,
        *,
        server_index: int | None = None,
        tls_root_cert: str | bytes | None = None,
        tls_server_name: str | None = None,
        token: str | None = None,
        failover: bool | None = None,
        step_timeout_s: float | None = None,
        **options: Any,
    ):
        """Creates the environment on one server of `address` (see the package docstring for
        address lists, server_index, TLS and token); `options` are the EnvConfig options.
        failover: None is on with several servers, a host name or the embedded one (docs/python.md).
        step_timeout_s: the deadline of each call (None: 5 s; 0: none); a server that misses it
        counts as lost (failover) or raises DEADLINE_EXCEEDED."""
        super().__init__()  # pettingzoo.AECEnv / ParallelEnv, next in the subclass's MRO.
        security = Security.from_options(tls_root_cert, tls_server_name, token)
        step_timeout = step_timeout_value(step_timeout_s)
        config = make_config(render_mode, False, options)
        addresses = parse_addresses(address)

        def create(connection: Connection):
            connection.check_server()  # GetServerInfo, once per connection.
            return connection.call("CreateEnv", pb.CreateEnvRequest(config=config))

        connection, env = create_single(addresses or None, server_index, security, step_timeout, create)
        # What a pickle carries (__reduce__): the arguments that make the same environment on the
        # same server again (the one it lives on now), never the connection.
        self._init_kwargs = dict(
            options,
            render_mode=render_mode,
            failover=failover,
            step_timeout_s=step_timeout_s,
            **security.as_options(),
        )
        self.failover = _record.failover_on(failover, addresses)
        self.failovers = 0  # Failover events so far.
        self._security, self._addresses, self._step_timeout = security, addresses, step_timeout
        # Addresses of servers found unreachable or draining (probed again at each failover).
        self._down: set[str] = set()
        self._servers_seen = max(len(addresses), 1)  # Servers `address` stood for at the last resolution.
        self._pin_pickles_to(connection.address)
        self._adopt(connection, env)
        self.render_mode = render_mode
        self.config = config_dict(env.config)
        self._env_config = env.config  # Filled in by the server (what a snapshot carries).
        self.continuous = bool(env.config.continuous)
        self.possible_agents = list(env.possible_agents)
        self._agent_index = {agent: index for index, agent in enumerate(self.possible_agents)}
        # One space object per agent, returned by every call (seeding one agent's space must
        # not reseed another's).
        self.observation_spaces = {a: space_from_proto(env.observation_space) for a in self.possible_agents}
        self.action_spaces = {a: space_from_proto(env.action_space) for a in self.possible_agents}
        # PettingZoo's state_space: every lander's observation in lander order, flat, with the
        # observation space's bounds (state()).
        observation_space = self.observation_spaces[self.possible_agents[0]]
        self._observation_size = int(observation_space.shape[0])
        self.state_space = gymnasium.spaces.Box(
            np.tile(observation_space.low, len(self.possible_agents)),
            np.tile(observation_space.high, len(self.possible_agents)),
            dtype=np.float32,
        )
        self.metadata = dict(METADATA, render_fps=env.render_fps or METADATA["render_fps"])
        self._viewer: Viewer | None = None
        # The record (see _record): the seed of the last seeded reset, the operations since, each
        # with its action row (the step's actions in _actions, zeros where ignored), and the
        # observations last seen.
        n = len(self.possible_agents)
        self._dtype = pb.DTYPE_FLOAT32 if self.continuous else pb.DTYPE_INT32
        self._actions = np.zeros((n, 2) if self.continuous else (n,), np.float32 if self.continuous else np.int32)
        self._log = _record.GrowingLog(1, self._actions.nbytes)
        self._seed: int | None = None
        self._last_observations = b""
        self._init_state()

    def __reduce__(self):
        """Pickles as its arguments: options, address (the server it lives on; None stays None,
        the embedded server of the unpickling process) and TLS/token settings (the token
        itself included). Unpickling creates a new, not yet reset environment on that server,
        so copies made by cloudpickle or sent to worker processes (SuperSuit's
        concat_vec_envs_v1, Ray) each have their own."""
        return rebuild, (type(self), self._init_kwargs)

    def _pin_pickles_to(self, server: str) -> None:
        """Makes pickles (and clones) go to `server`, where the env lives now, with the same
        servers to fail over to: `address=` as given and `server`'s index when the entries are no
        names, else `server` first, then the entries (server_index counts the servers the
        entries stand for, which a name's resolution may reorder)."""
        if not self._addresses:
            self._init_kwargs.update(address=None, server_index=None)
        elif server in self._addresses and not any(map(is_name, self._addresses)):
            self._init_kwargs.update(address=list(self._addresses), server_index=self._addresses.index(server))
        else:
            self._init_kwargs.update(address=[server, *self._addresses], server_index=0)

    def _init_state(self) -> None:
        """The subclass's own attributes, set once the server-side env exists."""
        raise NotImplementedError

    def _adopt(self, connection: Connection, env: "pb.Env") -> None:
        """Makes the server-side `env` on `connection`'s server this object's: its name, its
        deletion on close() or garbage collection, its lease."""
        self._connection, self._name = connection, env.name
        self._deleter = weakref.finalize(self, _delete_env, connection, env.name)
        _lease.hold(connection, env.name, env.idle_timeout_s)

    def _call(self, method: str, request):
        """Calls `method` with `request` on this env (its `name` set here). With failover on, when
        the server is unreachable or has lost the env, the env is recreated on a reachable
        server from its record and the call is made again there."""
        tries = self._servers_seen + 2
        for _ in range(tries):
            request.name = self._name
            try:
                return self._connection.call(method, request)
            except MLLError as error:
                if not (self.failover and _record.loses_env(error, self._name)):
                    raise
                self._fail_over(error)
        raise _record.gave_up(tries)

    def _record_reset(self, response: "pb.ResetEnvResponse") -> None:
        """The record after a reset: a new one when the server reseeded, else an unseeded reset."""
        if response.HasField("seed"):
            self._seed = int(response.seed)
            self._log.clear()
        else:
            self._log.append(np.array([_record.RESET], np.uint8), np.zeros((1, self._actions.nbytes), np.uint8))
        self._last_observations = _record.observations_of(response)

    def _record_step(self, kind: int, response) -> None:
        """The record after a step of `kind` with the actions in _actions and its `response`."""
        self._log.append(np.array([kind], np.uint8), self._actions.view(np.uint8).reshape(1, -1))
        self._last_observations = _record.observations_of(response)

    def _env_record(self) -> _record.EnvRecord:
        """This env's record; FAILED_PRECONDITION when it cannot recreate the env."""
        if self._seed is None or self._log.full:
            why = (
                "it was never reset" if self._seed is None
                else f"its record passed {_record.MAX_RECORD_STEPS} operations since its last seeded reset"
            )
            raise MLLError(
                grpc.StatusCode.FAILED_PRECONDITION,
                f"{self._name} cannot be recreated: {why}; reset(seed=...) starts a new record",
            )
        kinds, actions = self._log.of_env(0)
        return _record.EnvRecord(self._seed, kinds, actions, self._last_observations)

    def _fail_over(self, cause: MLLError) -> None:
        """Recreates this env, lost to `cause`, from its record: on its own server when that
        answers (NOT_FOUND), else on the least-loaded reachable server of `address`, resolved
        again (a name finds the servers that joined it and drops those gone; the embedded server
        is restarted); one that turns out unreachable or draining is passed over. One failover
        event, logged; UNAVAILABLE when no server is left. (A draining server serves the envs it
        holds until its drain ends: this env moves when the server refuses it.)"""
        began = time.monotonic()
        record = self._env_record()
        old_connection, old_name = self._connection, self._name
        # One connection per server, to pick from; the env's own among them (first when its
        # server is no longer among those `address` stands for).
        endpoints = resolve_endpoints(self._addresses) if self._addresses else []
        self._servers_seen = max(len(endpoints), 1)
        connections = [
            old_connection if endpoint.address == old_connection.address
            else connect_endpoint(endpoint, self._security, self._addresses, self._step_timeout)
            for endpoint in endpoints
        ]
        if old_connection not in connections:
            connections.insert(0, old_connection)
        old_index = connections.index(old_connection)
        listed = {endpoint.address for endpoint in endpoints} or {old_connection.address}
        # Servers gone from the name: envs do not move there (nor are they probed).
        gone = {i for i, c in enumerate(connections) if c.address not in listed}
        down = gone | {i for i, c in enumerate(connections) if c.address in self._down}
        unreachable = _record.loses_server(cause)
        # Servers that missed a deadline in this event: not probed while others can take the env.
        stalled = {old_index} if cause.code == grpc.StatusCode.DEADLINE_EXCEEDED else set()
        target, adopted = old_index, None
        try:
            for _ in range(len(connections) + 1):
                if unreachable:
                    down.add(target)
                    usable = _record.usable_servers(connections, down, stalled | gone) or _record.usable_servers(
                        connections, down, gone
                    )
                    choice, answers = place([connections[i] for i in usable]) if usable else (None, [])
                    for i, answer in zip(usable, answers):
                        if isinstance(answer, MLLError):
                            down.add(i)
                    if choice is None:
                        raise MLLError(
                            grpc.StatusCode.UNAVAILABLE,
                            f"failover of {old_name} found no reachable server of {', '.join(self._addresses)}"
                            + (f" ({', '.join(endpoint.address for endpoint in endpoints)})" if endpoints else "")
                            + f": {cause.message}",
                        )
                    target = usable[choice]
                try:
                    connections[target].check_server()
                    (env,), _ = _record.replay(
                        connections[target], self._env_config, [record], [old_name], self._dtype,
                        self._actions.shape,
                    )
                except MLLError as error:
                    if not _record.loses_server(error):
                        raise
                    unreachable = True  # It went too (or drains, or stalls): the next one.
                    if error.code == grpc.StatusCode.DEADLINE_EXCEEDED:
                        stalled.add(target)
                    continue
                adopted = connections[target]
                break
            else:
                raise _record.gave_up(len(connections) + 1)
        finally:
            self._down = {connections[i].address for i in down if connections[i].address in listed}
            for connection in connections:
                if connection is not adopted and connection is not old_connection:
                    connection.close()
        # The old env went with its server (or, NOT_FOUND, is gone from it): nothing to delete.
        self._deleter.detach()
        if adopted is not old_connection:
            old_connection.close()
        self._adopt(adopted, env)
        self._pin_pickles_to(adopted.address)
        self.failovers += 1
        _record.log_failover(type(self).__name__, 1, cause, [adopted.address], record.kinds.size, began)

    @property
    def address(self) -> str:
        """The address of the server this environment lives on (one of the `address=` list; the
        embedded server's when created with address=None)."""
        return self._connection.address

    @property
    def name(self) -> str:
        """The server-side resource name, `envs/{id}`."""
        return self._name

    @property
    def server_info(self) -> ServerInfo:
        """The release, wire protocol version, capabilities and limits of this environment's server
        (GetServerInfo, asked when the environment was created or moved there by failover)."""
        return self._connection.server_info

    # ----------------------------------------------------------------- PettingZoo's global state

    def state(self) -> np.ndarray:
        """PettingZoo's global state (for centralized critics): float32 (n_landers * 12,), lander
        i's 12 observation values at [12 i, 12 i + 12), the same bits as its latest observation
        (observe(agent); the parallel env's latest returned observation). Rows of landers not in
        `agents` (done: after the parallel step that ended them, after the AEC dead step that
        removed them; all of them before the first reset) are zeros. Described by `state_space`.
        Made on the client from the observations it holds: no server call."""
        state = np.zeros((len(self.possible_agents), self._observation_size), np.float32)
        present = [self._agent_index[agent] for agent in self.agents]
        if present:
            state[present] = self._observation_rows()[present]
        return state.reshape(-1)

    def _observation_rows(self) -> np.ndarray:
        """float32 (n_landers, 12): each lander's latest observation, as the subclass holds it."""
        raise NotImplementedError

    # ----------------------------------------------------------------- snapshot

    def snapshot(self) -> bytes:
        """This env's snapshot: bytes that recreate it at this point (restore, clone) to the same
        bits on any server of the same release. FAILED_PRECONDITION before the first reset or past
        the record's limit (docs/python.md)."""
        info = self.server_info
        return _record.encode_snapshot(
            self._env_config, info.protocol, info.server_version, self._env_record(), self._dtype,
            self._actions.nbytes,
        )

    def _restore(self, snapshot: bytes, operations: Sequence[int]):
        """Puts this env at the point `snapshot` describes (its steps among `operations`): a new
        server-side env replays it, checked against the snapshot's last observations, then replaces
        this one's. Returns the replay's last answer. INVALID_ARGUMENT for a damaged snapshot or one
        of an env with other options or steps, DATA_LOSS when the replay gives other bits; on any
        error the env is untouched."""
        decoded = _record.decode_snapshot(snapshot, operations)
        _record.check_restorable(decoded, self._env_config, self.server_info)
        (env,), (answer,) = _record.replay(
            self._connection, self._env_config, [decoded.record], [f"{self._name} (restored)"],
            self._dtype, self._actions.shape,
        )
        self._deleter.detach()  # The old env goes; the connection stays.
        _record.delete_quietly(self._connection, self._name)
        self._adopt(self._connection, env)
        record = decoded.record
        self._seed = record.seed
        self._log.clear()
        for kind, row in zip(record.kinds, record.actions):
            self._log.append(np.array([kind], np.uint8), row[None])
        self._last_observations = record.last_observations
        return answer

    def clone(self):
        """A new env of this class on the same server with the same arguments, at this same point
        (snapshot() restored into it)."""
        snapshot = self.snapshot()
        other = rebuild(type(self), self._init_kwargs)
        try:
            other.restore(snapshot)
        except BaseException:
            other.close()
            raise
        return other

    def observation_space(self, agent: str) -> gymnasium.spaces.Space:
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> gymnasium.spaces.Space:
        return self.action_spaces[agent]

    def _frame(self) -> np.ndarray:
        frame = self._call("RenderEnv", pb.RenderEnvRequest(format=pb.FRAME_FORMAT_RGB))
        return _arrays.from_bytes(frame.data, pb.DTYPE_UINT8, (frame.height, frame.width, 3))

    def _show_if_human(self) -> None:
        """In "human" mode every reset and world step is shown, as Gymnasium's envs do."""
        if self.render_mode == "human":
            if self._viewer is None:
                self._viewer = Viewer(self.metadata["name"], self.metadata["render_fps"])
            self._viewer.show(self._frame())

    def render(self) -> np.ndarray | None:
        """rgb_array: the current frame, uint8 (400, 600, 3). human: frames are already shown on
        every reset and world step, so this returns None (and draws nothing more, since each
        drawn frame ages the exhaust particles). None: warns and returns None."""
        if self.render_mode is None:
            gymnasium.logger.warn(
                "render() called without a render mode; create the env with render_mode='rgb_array' or 'human'"
            )
            return None
        if self.render_mode == "rgb_array":
            return self._frame()
        return None

    def close(self) -> None:
        """Deletes the server-side environment, closes the connection (stopping the embedded
        server when this was its last user) and the window. Idempotent."""
        if self._viewer is not None:
            self._viewer.close()
            self._viewer = None
        deleter = getattr(self, "_deleter", None)
        if deleter is not None:
            deleter()
