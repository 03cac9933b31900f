"""What every client class shares: the connection to a server (embedded or given), the
config message built from keyword arguments, gymnasium spaces from the server's spec, action
encoding and the per-agent info dicts."""

from __future__ import annotations

import numbers
import os
import weakref
import threading
from typing import Any, Callable, NamedTuple, Sequence

import grpc
import numpy as np
from gymnasium import spaces

from . import _arrays, _server_info
from ._actions import check_actions
from ._channel import DEFAULT_STEP_TIMEOUT_S, Endpoint, Security, open_channel, parse_addresses, resolve_endpoints
from ._errors import MLLError, from_rpc_error, invalid_argument
from ._server import acquire_embedded
from ._stubs import pb, pb_grpc


def _outcome_names() -> tuple:
    """info["outcome"] by code, from the proto's Outcome enum (OUTCOME_LANDED -> "landed"); code
    0, OUTCOME_UNSPECIFIED, is a lander still flying: None."""
    values = pb.Outcome.DESCRIPTOR.values
    names: list = [None] * (max(value.number for value in values) + 1)
    for value in values:
        if value.number:
            names[value.number] = value.name.removeprefix("OUTCOME_").lower()
    return tuple(names)


# StepData.outcomes / AecState.outcomes codes -> info["outcome"] (None while flying).
OUTCOMES = _outcome_names()

# The options an environment takes as keyword arguments: EnvConfig's fields with presence (an
# unset one takes the server's default), in field order. render_mode and auto_reset are set
# by the classes themselves.
CONFIG_OPTIONS = tuple(field.name for field in pb.EnvConfig.DESCRIPTOR.fields if field.has_presence)

RENDER_MODES = ("human", "rgb_array")


def make_config(render_mode: str | None, auto_reset: bool, options: dict[str, Any]) -> "pb.EnvConfig":
    """EnvConfig from keyword arguments; unset options take the server's defaults. Values are
    only type-checked here: their ranges are the server's to check (one place for the rules)."""
    unknown = sorted(set(options) - set(CONFIG_OPTIONS))
    if unknown:
        raise TypeError(f"unknown option(s) {unknown}; the options are {list(CONFIG_OPTIONS)}")
    if render_mode is not None and render_mode not in RENDER_MODES:
        raise invalid_argument(
            f"render_mode is {render_mode!r}; allowed: None, {', '.join(map(repr, RENDER_MODES))}"
        )
    config = pb.EnvConfig(
        render_mode=pb.RENDER_MODE_RGB_ARRAY if render_mode else pb.RENDER_MODE_NONE,
        auto_reset=auto_reset,
    )
    fields = pb.EnvConfig.DESCRIPTOR.fields_by_name
    for key, value in options.items():
        kind = fields[key].cpp_type
        if kind == fields[key].CPPTYPE_BOOL:
            if not isinstance(value, (bool, np.bool_)):
                raise invalid_argument(f"{key} is {value!r}; expected True or False")
            setattr(config, key, bool(value))
        elif kind == fields[key].CPPTYPE_INT32:
            if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral):
                raise invalid_argument(f"{key} is {value!r}; expected an integer")
            if not -(2**31) <= int(value) < 2**31:
                raise invalid_argument(f"{key} is {value}; expected a 32-bit integer")
            setattr(config, key, int(value))
        else:
            if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
                raise invalid_argument(f"{key} is {value!r}; expected a number")
            setattr(config, key, float(value))
    return config


def config_dict(config: "pb.EnvConfig") -> dict[str, Any]:
    """The server's filled-in config as keyword arguments."""
    return {key: getattr(config, key) for key in CONFIG_OPTIONS}


def space_from_proto(space: "pb.Space") -> spaces.Space:
    if space.kind == pb.Space.KIND_DISCRETE:
        return spaces.Discrete(int(space.n))
    if space.kind == pb.Space.KIND_BOX:
        dtype = _arrays.wire_dtype_to_numpy(space.dtype)
        shape = tuple(space.shape)
        low = np.asarray(space.low, dtype=np.float64).reshape(shape)
        high = np.asarray(space.high, dtype=np.float64).reshape(shape)
        return spaces.Box(low=low.astype(dtype), high=high.astype(dtype), shape=shape, dtype=dtype)
    raise MLLError(grpc.StatusCode.INTERNAL, f"server sent a Space of unknown kind {space.kind}")


def seed_value(seed) -> int | None:
    if seed is None:
        return None
    if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, numbers.Integral) or not 0 <= seed < 2**64:
        raise invalid_argument(f"seed is {seed!r}; expected None or an integer in [0, 2**64)")
    return int(seed)


class Columns(NamedTuple):
    """The per-agent columns that StepData and AecState share, decoded: observations as a
    float32 [n, 12] array, the rest as Python lists indexed by agent."""

    observations: np.ndarray
    rewards: list
    terminations: list
    truncations: list
    outcomes: list
    episode_returns: list
    episode_lengths: list

    @classmethod
    def decode(cls, message) -> "Columns":
        return cls(
            _arrays.to_numpy(message.observations),
            _arrays.to_list(message.rewards),
            [flag != 0 for flag in _arrays.to_list(message.terminations)],
            [flag != 0 for flag in _arrays.to_list(message.truncations)],
            _arrays.to_list(message.outcomes),
            _arrays.to_list(message.episode_returns),
            _arrays.to_list(message.episode_lengths),
        )

    def info(self, i: int) -> dict:
        """infos[agent i]: "outcome" once decided; "episode_return"/"episode_length" when done."""
        info: dict[str, Any] = {}
        outcome = self.outcomes[i]
        if outcome:
            info["outcome"] = OUTCOMES[outcome] if outcome < len(OUTCOMES) else f"outcome_{outcome}"
        if self.terminations[i] or self.truncations[i]:
            info["episode_return"] = float(self.episode_returns[i])
            info["episode_length"] = int(self.episode_lengths[i])
        return info


def encode_agent_action(action, continuous: bool, agent: str, out: "pb.AgentAction") -> None:
    """Fills an AEC AgentAction from one agent's action."""
    values = check_actions(action, continuous, (), f"the action of {agent}")
    if continuous:
        _arrays.to_proto(values, pb.DTYPE_FLOAT32, out.continuous)
    else:
        out.discrete = int(values)


# How long placement waits for the servers' GetServerInfo answers; one that has not answered by
# then takes no new environment this time.
PLACEMENT_TIMEOUT_S = 2.0


def check_server_index(server_index, count: int) -> int | None:
    """`server_index` checked against the `count` servers an address list stands for."""
    if server_index is None:
        return None
    if (
        isinstance(server_index, (bool, np.bool_))
        or not isinstance(server_index, numbers.Integral)
        or not 0 <= server_index < count
    ):
        raise invalid_argument(
            f"server_index is {server_index!r}; expected None or an integer in [0, {count}) "
            f"(address stands for {count} server(s))"
        )
    return int(server_index)


def connect_endpoint(
    endpoint: Endpoint, security: Security, peers: Sequence[str], step_timeout_s: float | None
) -> "Connection":
    """A connection to `endpoint` (TLS checking the name it was resolved from)."""
    return Connection(endpoint.address, security.for_endpoint(endpoint), peers, step_timeout_s)


def place(connections: Sequence["Connection"], timeout: float = PLACEMENT_TIMEOUT_S) -> tuple[int | None, list]:
    """Where a new environment goes among `connections`: the least-loaded server by their
    GetServerInfo answers, asked at once (_server_info.least_loaded), and every answer (an
    MLLError for a server that did not answer). A connection's answer is kept as its
    server_info."""
    answers = _server_info.fetch_all(connections, timeout)
    for connection, answer in zip(connections, answers):
        if isinstance(answer, _server_info.ServerInfo):
            connection.keep_server_info(answer)
    infos = [answer if isinstance(answer, _server_info.ServerInfo) else None for answer in answers]
    return _server_info.least_loaded(infos), answers


def create_single(
    address,
    server_index: int | None,
    security: Security,
    step_timeout_s: float | None,
    create: Callable[["Connection"], Any],
) -> tuple["Connection", Any]:
    """The connection of one AEC or parallel environment and what `create` made on it, on one of
    the servers `address` stands for (address=None: the embedded server): `server_index`'s,
    else the least-loaded one; a server that refuses the environment (RESOURCE_EXHAUSTED: full,
    or this token's quota there) or stops answering meanwhile (UNAVAILABLE) is passed over for
    the next least-loaded, and the last refusal raised when none is left."""
    addresses = parse_addresses(address)
    if not addresses:
        if server_index not in (None, 0):
            raise invalid_argument(f"server_index is {server_index!r} but address is None (one embedded server)")
        return _create_on(Connection(None, security, step_timeout_s=step_timeout_s), create)
    endpoints = resolve_endpoints(addresses)
    index = check_server_index(server_index, len(endpoints))
    if index is None and len(endpoints) == 1:
        index = 0
    if index is not None:
        return _create_on(connect_endpoint(endpoints[index], security, addresses, step_timeout_s), create)
    connections = [connect_endpoint(endpoint, security, addresses, step_timeout_s) for endpoint in endpoints]
    usable = list(range(len(connections)))
    chosen = None
    try:
        while True:
            choice, answers = place([connections[i] for i in usable])
            if choice is None:
                raise no_server_takes(addresses, [connections[i] for i in usable], answers)
            try:
                created = create(connections[usable[choice]])
            except MLLError as error:
                if error.code not in (grpc.StatusCode.RESOURCE_EXHAUSTED, grpc.StatusCode.UNAVAILABLE):
                    raise
                del usable[choice]
                if not usable:
                    raise
                continue
            chosen = usable[choice]
            return connections[chosen], created
    finally:
        for i, connection in enumerate(connections):
            if i != chosen:
                connection.close()


def _create_on(connection: "Connection", create: Callable[["Connection"], Any]) -> tuple["Connection", Any]:
    try:
        return connection, create(connection)
    except BaseException:
        connection.close()
        raise


def no_server_takes(addresses: Sequence[str], connections: Sequence["Connection"], answers: Sequence) -> MLLError:
    """The error naming each server of `addresses` and why it takes no new environment:
    RESOURCE_EXHAUSTED when those that answered are full, UNAVAILABLE when none answered."""
    reasons = [
        f"{connection.address}: {answer.message}" if isinstance(answer, MLLError)
        else f"{connection.address}: full ({answer.load.envs_hosted} of --max_envs={answer.limits.max_envs})"
        for connection, answer in zip(connections, answers)
    ]
    answered = any(not isinstance(answer, MLLError) for answer in answers)
    return MLLError(
        grpc.StatusCode.RESOURCE_EXHAUSTED if answered else grpc.StatusCode.UNAVAILABLE,
        f"no server of address {', '.join(addresses)} takes a new environment: {'; '.join(reasons)}",
    )


def rebuild(cls, kwargs: dict):
    """Unpickles a client object: a new one made from its constructor's arguments."""
    return cls(**kwargs)


def check_process(pid: int, what: str) -> None:
    """FAILED_PRECONDITION in a forked child of process `pid`, which opened `what` (e.g. "this
    environment's connection to host:port"): a child must not use its parent's connections."""
    if os.getpid() != pid:
        raise MLLError(
            grpc.StatusCode.FAILED_PRECONDITION,
            f"{what} was opened by process {pid}, not this one ({os.getpid()}); a forked process must make its "
            "own environments (pickle the environment object, as SuperSuit and multiprocessing do, or create a "
            "new one)",
        )


def describe_server(address: str, security: Security, peers: Sequence[str] = (), embedded: bool = False) -> str:
    """The server at `address` as an error that did not reach it names it: how the client connects
    (TLS, token), the other servers given (`peers`) and what to try."""
    if embedded:
        return f"embedded mll_server at {address}"
    others = [peer for peer in peers if peer != address]
    hint = (
        "the server's certificate must be signed by tls_root_cert and name the host or tls_server_name"
        if security.tls
        else "a TLS server needs tls_root_cert="
    )
    return (
        f"mll_server at {address} ({security.describe()}"
        + (f"; the servers given: {', '.join(peers)}" if others else "")
        + f"; start one with `mll_server --address={address}`, or pass address=None for an "
        f"embedded server; {hint})"
    )


def embedded_lease(security: Security):
    """A lease on this process's embedded server (address=None), which speaks plaintext:
    INVALID_ARGUMENT when `security` asks for TLS."""
    if security.tls:
        raise invalid_argument(
            "tls_root_cert is set but address is None; the embedded server speaks "
            "plaintext on loopback, so pass address='host:port' of a TLS server"
        )
    return acquire_embedded()


class Connection:
    """A channel and stub to one server. `address=None` leases the shared embedded server.

    `peers` are all the addresses the caller was given (this one among them), named in the
    message of a server that cannot be reached. Every call carries `security`'s token metadata,
    and a deadline: its `timeout`, else `step_timeout_s` (None: none); a server that misses it
    raises DEADLINE_EXCEEDED naming the server and the timeout (gRPC cancels the call, so its late
    answer is never taken).
    """

    def __init__(
        self,
        address: str | None,
        security: Security = Security(),
        peers: Sequence[str] = (),
        step_timeout_s: float | None = DEFAULT_STEP_TIMEOUT_S,
    ):
        self.step_timeout_s = step_timeout_s
        self._lease = None
        if address is None:
            self._lease = embedded_lease(security)
            address = self._lease.address
        self._what = describe_server(address, security, peers, embedded=self._lease is not None)
        self.address = address
        self.security = security
        self._peers = tuple(peers)
        self.channel = open_channel(address, security)
        self.stub = pb_grpc.MultiLunarLanderStub(self.channel)
        self._metadata = security.metadata
        self._pid = os.getpid()
        self._server_info: _server_info.ServerInfo | None = None
        self._server_info_lock = threading.Lock()
        # Closing on garbage collection too, without referencing self.
        self._finalizer = weakref.finalize(self, Connection._close, self.channel, self._lease, self._pid)

    def renewed(self) -> "Connection":
        """A new connection made as this one was: a new channel to the same address (which
        resolves a host name again and keeps none of this channel's reconnection backoff), or for
        the embedded server a new lease, which restarts the server if it died."""
        return Connection(
            None if self._lease is not None else self.address, self.security, self._peers, self.step_timeout_s
        )

    def check_process(self) -> None:
        """A forked child inherits its parent's objects but must not use their connections: the
        socket is the parent's. Raises FAILED_PRECONDITION there, before any byte is sent."""
        check_process(self._pid, f"this environment's connection to {self.address}")

    @property
    def server_info(self) -> _server_info.ServerInfo:
        """The server's GetServerInfo answer, asked on first use and kept for the connection's
        life (protocol v1.0 for a server from before GetServerInfo)."""
        with self._server_info_lock:
            if self._server_info is None:
                self._server_info = _server_info.fetch(self)
            return self._server_info

    def keep_server_info(self, info: _server_info.ServerInfo) -> None:
        """Keeps `info`, an answer of this connection's server asked elsewhere (placement), as its
        server_info."""
        with self._server_info_lock:
            self._server_info = info

    def check_server(self, needs: Sequence[str] = (), feature: str = "") -> None:
        """Raises FAILED_PRECONDITION (naming both versions and what to upgrade) unless this client
        speaks the server's protocol and the server offers `needs`, which `feature` needs."""
        _server_info.check_compatible(self.server_info, self.address, needs, feature)

    def call(self, method: str, request, timeout: float | None = None):
        """Calls a unary method (deadline: `timeout`, else step_timeout_s); a failure raises MLLError
        with the server's code and message."""
        self.check_process()
        deadline = self.step_timeout_s if timeout is None else timeout
        try:
            return getattr(self.stub, method)(request, timeout=deadline, metadata=self._metadata)
        except grpc.RpcError as error:
            raise self._error(error, method, deadline, timeout is None) from None

    def future(self, method: str, request, timeout: float | None = None) -> Callable[[], Any]:
        """Starts a unary call (deadline: `timeout`, else step_timeout_s); the returned function
        waits for it (raising MLLError)."""
        self.check_process()
        deadline = self.step_timeout_s if timeout is None else timeout
        call = getattr(self.stub, method).future(request, timeout=deadline, metadata=self._metadata)

        def result():
            try:
                return call.result()
            except grpc.RpcError as error:
                raise self._error(error, method, deadline, timeout is None) from None

        return result

    def _error(self, error: grpc.RpcError, method: str, deadline: float | None, step: bool) -> MLLError:
        """The MLLError of a failed call of `method`; a missed `deadline` says which server missed
        what timeout (`step`: step_timeout_s's)."""
        if deadline is not None and error.code() == grpc.StatusCode.DEADLINE_EXCEEDED:
            return MLLError(
                grpc.StatusCode.DEADLINE_EXCEEDED,
                f"mll_server at {self.address} did not answer {method} within {deadline:g} s"
                + (" (step_timeout_s)" if step else "")
                + "; the call is cancelled (a late answer is never taken)",
            )
        return from_rpc_error(error, self._what)

    @staticmethod
    def _close(channel, lease, pid: int) -> None:
        if os.getpid() != pid:  # A forked child's copy: the channel and the lease are the parent's.
            return
        channel.close()
        if lease is not None:
            lease.release()

    def close(self) -> None:
        self._finalizer()

    @property
    def closed(self) -> bool:
        return not self._finalizer.alive
