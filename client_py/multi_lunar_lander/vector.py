"""Many environments stepped together: one StepBatch per server per step, arrays in and out,
in StepBatch's packed form (one actions array in, one array per result column out; no
per-environment messages to build or parse, no per-environment Python loop). Each StepBatch
travels as one request on a Session stream kept open to its server, which saves a unary call's
set-up on both sides; a server with "packed_batch_handles" gets each list of envs once, and then
only a handle (PackedSteps.handle) and the actions (_Handles): over the native library (_native.NativeSessionStream, gRPC C++ in the
calling thread) when it is available, else over grpcio (SessionStream); with a server on this
host the native stream's messages pass through shared memory instead; see docs/benchmarks.md.

Several servers (address= a list or "host:port,host:port"): env i lives on server i mod S for
its whole life (creation, reset, steps, deletion). Each step sends one StepBatch to every server
at once, each with that server's envs, and puts the results back in env order. Each env's
physics and generator are its own, so the results are the same bits as on one server.

Episode ends (auto-reset): the environments are created with the server's `auto_reset`. When
an environment's episode is over (no lander active), its NEXT step ignores the actions and
starts a new episode, continuing that environment's generator stream (no reseed): the result
holds the new episode's first observations, zero rewards, no terminations/truncations, and
`infos["auto_reset"][i]` is True. Those rows are not transitions, so `active[i]` is all False
for them. Observations of agents that are done (before the episode is over) are zero rows and
their `active` entries are False.
"""

from __future__ import annotations

import collections
import time
from typing import Any, NamedTuple, Sequence

import grpc
import numpy as np

from . import _arrays, _lease, _native, _record
from ._channel import Security, parse_addresses
from ._errors import MLLError, from_item_error, invalid_argument
from ._actions import _short, check_actions
from ._remote import (
    Connection,
    SessionStream,
    config_dict,
    make_config,
    rebuild,
    seed_value,
    space_from_proto,
)
from ._server_info import ServerInfo
from ._stubs import pb

# What a vector env needs of each server (GetServerInfo's capabilities): its steps are packed
# StepBatches, its envs reset themselves.
_NEEDS = ("packed_step_batch", "auto_reset")

# Result columns: (field of StepData / PackedStepData, wire dtype, numpy dtype of the result,
# trailing shape per env given n_landers). The per-agent ones are Arrays in both messages.
_AGENT_COLUMNS = (
    ("observations", pb.DTYPE_FLOAT32, np.float32, lambda n: (n, 12)),
    ("rewards", pb.DTYPE_FLOAT32, np.float32, lambda n: (n,)),
    ("terminations", pb.DTYPE_UINT8, bool, lambda n: (n,)),
    ("truncations", pb.DTYPE_UINT8, bool, lambda n: (n,)),
    ("stepped", pb.DTYPE_UINT8, bool, lambda n: (n,)),
    ("outcomes", pb.DTYPE_UINT8, np.uint8, lambda n: (n,)),
    ("episode_returns", pb.DTYPE_FLOAT32, np.float32, lambda n: (n,)),
    ("episode_lengths", pb.DTYPE_INT32, np.int32, lambda n: (n,)),
)
# The per-env ones, scalars in StepData, Arrays in PackedStepData (cycles is not returned).
_ENV_COLUMNS = (
    ("episode_over", pb.DTYPE_UINT8, bool, lambda n: ()),
    ("auto_reset", pb.DTYPE_UINT8, bool, lambda n: ()),
)


class _Server(NamedTuple):
    """One server's share of a vector env: env indices `rows` (ascending int array: env i starts
    on server i mod S, and moves on failover), built whenever the placement changes; each step
    sends them one packed StepBatch request on the server's Session stream."""

    connection: Connection
    index: int  # Into VectorEnv._connections.
    rows: np.ndarray
    count: int  # How many envs: rows of every array of the request and the response.
    columns: tuple  # _arrays.Column of every result column, shaped for this server's envs.
    stream: SessionStream


# PackedSteps.handle's range and how many envs a session's declared batches hold together (the
# wire contract's figures).
MAX_HANDLE = 64
MAX_DECLARED_ENVS = 65536


class _Handles:
    """The batch handles of one server's Session stream (PackedSteps.handle; the server has
    "packed_batch_handles"). Each list of envs stepped on it (by env indices; a new placement or
    new names forget them all) gets a handle: the first request of a list declares it (names and
    handle); once that request's answer came back OK, the list goes out as the handle alone with
    the actions. A failed receive or a closed stream forgets them too: a new stream is a new
    session, with no handles (redeclaring is always safe; a handle the session lacks is never
    sent)."""

    def __init__(self, stream: SessionStream):
        self._stream = stream
        self.forget()

    def forget(self) -> None:
        self._closes = self._stream.closes  # The stream's session these handles belong to.
        self._handle_of: dict[bytes, int] = {}  # Envs (their indices' bytes) -> handle.
        self._lists: dict[int, tuple[bytes, int, int]] = {}  # Handle -> (envs, count, version).
        self._answered: set[int] = set()  # Handles whose declaration the server answered.
        self._declaring: dict[int, tuple[int, int]] = {}  # Request sequence -> (handle, version).
        self._used: collections.OrderedDict[int, None] = collections.OrderedDict()  # Least recent first.
        self._envs = 0  # Envs of the declared lists together.
        self._version = 0

    def handle(self, envs: bytes, count: int) -> tuple[int, bool]:
        """(handle, answered) for the list `envs` of `count` envs: answered True when its
        declaration was answered (send the handle alone); handle 0 when it cannot have one."""
        if self._stream.closes != self._closes:  # Closed since: a new session.
            self.forget()
        handle = self._handle_of.get(envs)
        if handle is None:
            if len(self._lists) < MAX_HANDLE:
                handle = min(set(range(1, len(self._lists) + 2)) - self._lists.keys())
                held = self._envs
            else:  # The least recently used one is declared anew.
                handle = next(iter(self._used))
                held = self._envs - self._lists[handle][1]
            if held + count > MAX_DECLARED_ENVS:
                return 0, False
            if handle in self._lists:
                del self._handle_of[self._lists[handle][0]]
            self._version += 1
            self._lists[handle] = (envs, count, self._version)
            self._handle_of[envs] = handle
            self._answered.discard(handle)
            self._envs = held + count
        self._used[handle] = None
        self._used.move_to_end(handle)
        return handle, handle in self._answered

    def declaring(self, sequence: int, handle: int) -> None:
        """Request `sequence` (sent) declares `handle` as its current list."""
        self._declaring[sequence] = (handle, self._lists[handle][2])

    def answered(self, sequence: int) -> None:
        """Request `sequence` was answered OK: a declaration it made counts from now on."""
        handle, version = self._declaring.pop(sequence, (0, 0))
        if handle in self._lists and self._lists[handle][2] == version:
            self._answered.add(handle)


class VectorEnv:
    """`num_envs` Multi Lunar Lander environments with the same options, on the server(s) of
    `address` (env i on server i mod S; None: the embedded server). TLS and token: as for
    `parallel_env` (tls_root_cert=, tls_server_name=, token=).

    transport= how steps travel (creation, reset and deletion are grpcio calls either way):
      "shared_memory": through a shared-memory region that a server on this host (loopback
      address or Unix-domain socket) grants the Session stream: no socket, one futex wake-up
      each way, the fastest; FAILED_PRECONDITION with the server's reason when refused (or when
      the region cannot be mapped here: a server in another container).
      "native": over libmll_native_stream.so, gRPC C++ in the calling thread (built with the
      server; `pip install .` at the repository's root installs it beside the package, or set
      $MLL_NATIVE_LIBRARY to its path). Both raise FAILED_PRECONDITION when the library is
      not available.
      "grpc": over grpcio. "auto" (the default): shared memory where granted, else native when
      the library loads, else grpc.
      All give the same results and errors; the first two take less of the caller's CPU per step.
      The `transport` attribute says which is in use.

    reset(seed=None, options=None) -> (observations, infos): observations float32
      (num_envs, n_landers, 12); seed s gives env i the seed s + i (None continues each env's
      stream).
    step(actions) -> (observations, rewards, terminations, truncations, active, infos): actions
      int (num_envs, n_landers) or, continuous, float (num_envs, n_landers, 2); entries of done
      agents are ignored. rewards float32 (num_envs, n_landers); terminations, truncations and
      active bool (num_envs, n_landers): `active` marks the rows that carry a transition (the
      agent was active at the start of the step and this is not an auto-reset).
    step_async(actions), then step_wait() -> step()'s results: the same step split in two, so
      the caller can work (or step another vector env) while the servers step; one step at a
      time: step, reset or step_async while one is in flight raise FAILED_PRECONDITION.
    EnvPool's async API (batch_size=K, 1..num_envs; K = num_envs is the synchronous API above):
      async_reset(seed=None) resets every env and makes its first observations due; send(actions,
      env_id) sends one step of the envs env_id (each with no step in flight) and returns at once,
      one packed StepBatch per server pipelined on its stream; recv() returns the results of the
      first K envs whose steps are done, as step() returns them, with infos["env_id"] naming
      them; step(actions, env_id) is send then recv. K need not divide num_envs. Each env's
      results are the same bits as with the synchronous API for the same actions.
    infos: "auto_reset" bool (num_envs,), "episode_over" bool (num_envs,), "outcome" uint8
      (num_envs, n_landers) with codes indexing OUTCOMES, "episode_return" float32 and
      "episode_length" int32 (num_envs, n_landers) (so far in the episode, final once done).
      Every array is the caller's own (writable, not reused by the next step).
    Errors: when the step of some envs fails on the server (e.g. an env deleted behind this
      object's back: NOT_FOUND), step raises MLLError with the server's code and message for
      the first of them in env order, prefixed "env {i} ({name}): "; the other envs did step.
    """

    def __init__(
        self,
        num_envs: int,
        address: str | Sequence[str] | None = None,
        *,
        tls_root_cert: str | bytes | None = None,
        tls_server_name: str | None = None,
        token: str | None = None,
        transport: str = "auto",
        batch_size: int | None = None,
        failover: bool | None = None,
        **options: Any,
    ):
        native = _native.uses_native(transport)
        if int(num_envs) != num_envs or num_envs < 1:
            raise invalid_argument(f"num_envs is {num_envs!r}; expected an integer >= 1")
        self.num_envs = int(num_envs)
        batch_size = self.num_envs if batch_size is None else batch_size
        if isinstance(batch_size, bool) or int(batch_size) != batch_size or not 1 <= batch_size <= self.num_envs:
            raise invalid_argument(f"batch_size is {batch_size!r}; allowed: an integer in 1..num_envs = 1..{self.num_envs}")
        self.batch_size = int(batch_size)
        config = make_config(None, True, options)
        security = Security.from_options(tls_root_cert, tls_server_name, token)
        addresses = parse_addresses(address)
        # What a pickle carries (__reduce__): the arguments, never a connection or stream.
        self._init_kwargs = dict(
            options,
            num_envs=self.num_envs,
            address=list(addresses) or None,
            transport=transport,
            batch_size=self.batch_size,
            failover=failover,
            **security.as_options(),
        )
        self._transport = transport
        servers = addresses or (None,)  # None: the embedded server.
        # Failover (see failover's docs): on by default with several servers or the embedded one.
        self.failover = _record.failover_on(failover, addresses)
        self.failovers = 0  # Failover events so far.
        self._embedded = not addresses
        self._down: set[int] = set()  # Connections found unreachable or draining (probed again at each failover).
        self._names: list[str | None] = [None] * self.num_envs  # None: not created.
        self._step_in_flight = False  # From step_async until step_wait reads the answers.
        # The async API (send/recv): envs whose step (or async_reset) was sent and whose result
        # recv has not returned yet; the connection of each request in flight, in send order, and
        # per connection its requests in flight, oldest first, as (env indices, action rows:
        # uint8 (envs, row bytes), what failover sends again); results received and not yet
        # returned by recv, as (env indices, columns) chunks in the order they came.
        self._env_in_flight = np.zeros(self.num_envs, bool)
        self._send_order: collections.deque[int] = collections.deque()
        self._in_flight: list[collections.deque[tuple[np.ndarray, np.ndarray]]] = []
        self._ready: collections.deque[tuple[np.ndarray, dict]] = collections.deque()
        # The result columns of the async API's answers, by their number of envs.
        self._async_columns: dict[int, tuple] = {}
        # Packed StepBatch requests, by (server, envs, handle, answered), reused where they can be
        # (_packed_request).
        self._requests: dict[tuple[int, bytes, int, bool], "pb.SessionRequest"] = {}
        # Env i starts on server i mod S (failover moves it); servers beyond num_envs get no connection.
        self._connections: list[Connection] = []
        self._security, self._peers = security, addresses
        self._placement = np.arange(self.num_envs) % min(len(servers), self.num_envs)
        try:
            for server in servers[: self.num_envs]:
                self._connections.append(Connection(server, security, addresses))
            for connection in self._connections:  # GetServerInfo, once per connection.
                connection.check_server(_NEEDS, "vector_env")
            waits = [
                self._connection_of(index).future("CreateEnv", pb.CreateEnvRequest(config=config))
                for index in range(self.num_envs)
            ]
            envs, failure = [None] * self.num_envs, None
            for index, wait in enumerate(waits):  # All are awaited: close() deletes what was made.
                try:
                    envs[index] = wait()
                    self._names[index] = envs[index].name
                except MLLError as error:
                    failure = failure or error
            if failure is not None:
                raise failure
            for index, name in enumerate(self._names):
                _lease.hold(self._connection_of(index), name, envs[index].idle_timeout_s)
        except BaseException:
            self.close()
            raise
        spec = envs[0]
        self._idle_timeout_s = spec.idle_timeout_s
        self._spec_config = spec.config  # Filled in by the server: what failover recreates.
        self.config = config_dict(spec.config)
        self.continuous = bool(spec.config.continuous)
        self.n_landers = int(spec.config.n_landers)
        self.possible_agents = list(spec.possible_agents)
        self.single_observation_space = space_from_proto(spec.observation_space)
        self.single_action_space = space_from_proto(spec.action_space)
        self._action_dtype = pb.DTYPE_FLOAT32 if self.continuous else pb.DTYPE_INT32
        action_shape = (self.n_landers, 2) if self.continuous else (self.n_landers,)
        self._action_shape = action_shape
        self._row_bytes = 4 * int(np.prod(action_shape))
        # Each env's record (see _record): the seed of its last seeded reset, a prefix restored by
        # restore_env, and its operations in the shared log from row _start[i] on (send/recv
        # steps appended per env as their answers come).
        self._log = _record.GrowingLog(self.num_envs, self._row_bytes)
        self._seeds: list[int | None] = [None] * self.num_envs
        self._start = np.zeros(self.num_envs, np.int64)
        self._prefix: list[_record.EnvRecord | None] = [None] * self.num_envs
        self._last_observations = np.zeros((self.num_envs, self.n_landers, 12), np.float32)
        self._pending = np.zeros((self.num_envs, self._row_bytes), np.uint8)  # The step's action bytes.
        if native:
            shared_memory = {"auto": "try", "shared_memory": "require"}.get(transport, "off")

            def stream_type(connection):
                mode = shared_memory
                if mode == "try" and connection.server_info.lacks("shared_memory_sessions"):
                    mode = "off"  # The server says it grants none ("auto"): not asked.
                return _native.NativeSessionStream(connection, mode)
        else:
            stream_type = SessionStream
        self._stream_type = stream_type
        self._streams = [stream_type(connection) for connection in self._connections]
        self._handles = [self._new_handles(index) for index in range(len(self._connections))]
        self._in_flight = [collections.deque() for _ in self._connections]
        self._build_servers()
        if transport == "shared_memory":
            # Asked for by name: a refusal raises here, not at the first step.
            try:
                for server in self._servers:
                    server.stream.open()
            except BaseException:
                self.close()
                raise

    def _build_servers(self) -> None:
        """self._servers from the placement: one per connection that holds envs."""
        self._requests = {}  # Their names may have changed (failover, restore_env) ...
        for handles in self._handles:  # ... and so may the lists of envs behind the handles.
            if handles is not None:
                handles.forget()
        self._servers = []
        for index, connection in enumerate(self._connections):
            rows = np.flatnonzero(self._placement == index)
            if rows.size == 0:
                continue
            columns = tuple(
                _arrays.Column(field, wire, (rows.size,) + shape(self.n_landers), result)
                for field, wire, result, shape in _AGENT_COLUMNS + _ENV_COLUMNS
            )
            self._servers.append(_Server(connection, index, rows, int(rows.size), columns, self._streams[index]))

    def _new_handles(self, index: int) -> "_Handles | None":
        """The batch handles of connection `index`'s (new) stream, when its server has them."""
        if "packed_batch_handles" not in self._connections[index].server_info.capabilities:
            return None
        return _Handles(self._streams[index])

    def _send_packed(self, server: "_Server", envs: np.ndarray, actions: bytes, reusable: bool) -> None:
        """Sends one packed StepBatch of `envs` (on `server`) with the action bytes `actions`;
        `reusable`: the request of the same envs sent before has been answered."""
        handles = self._handles[server.index]
        key = envs.tobytes()
        handle, answered = handles.handle(key, envs.size) if handles is not None else (0, False)
        message = self._packed_request(server, envs, key, handle, answered, reusable)
        message.step_batch.packed.actions.data = actions
        server.stream.send(message)
        if handle and not answered:
            handles.declaring(message.sequence, handle)

    def _receive_packed(self, index: int):
        """The StepBatchResponse of the oldest request in flight on connection `index`'s stream;
        any failure forgets the stream's handles (redeclared with their next steps)."""
        handles = self._handles[index]
        try:
            response = self._streams[index].receive()
        except BaseException:
            if handles is not None:
                handles.forget()
            raise
        if handles is not None:
            handles.answered(response.sequence)
        return response.step_batch

    @property
    def transport(self) -> str:
        """The transport in use: "shared_memory" when every server's stream passes its messages
        through shared memory, "native" when they use the native library otherwise, "grpc"."""
        streams = [server.stream for server in self._servers]
        if not streams or not isinstance(streams[0], _native.NativeSessionStream):
            return "grpc"
        if all(connection.closed for connection in self._connections):
            return "native"  # Closed: no stream to look at (nor to open).
        for stream in streams:
            stream.open()
        return "shared_memory" if all(s.shared_memory_in_use for s in streams) else "native"

    def __reduce__(self):
        """Pickles as its arguments (num_envs, options, address, TLS/token settings), never a
        connection or stream: unpickling creates `num_envs` new environments on the same servers
        (address=None: on the unpickling process's embedded server)."""
        return rebuild, (type(self), self._init_kwargs)

    def _connection_of(self, index: int) -> Connection:
        return self._connections[self._placement[index]]

    @property
    def address(self) -> str:
        """The servers' addresses, comma-separated (a valid `address=` for another client)."""
        return ",".join(self.addresses)

    @property
    def addresses(self) -> list[str]:
        """The address of each server that holds environments, in server order."""
        return [connection.address for connection in self._connections]

    @property
    def server_info(self) -> ServerInfo:
        """GetServerInfo's answer of the (first) server: release, wire protocol version,
        capabilities and limits; `server_infos` has every server's."""
        return self._connections[0].server_info

    @property
    def server_infos(self) -> list[ServerInfo]:
        """GetServerInfo's answer of each server that holds environments, in `addresses` order:
        release, wire protocol version, capabilities and limits."""
        return [connection.server_info for connection in self._connections]

    @property
    def names(self) -> list[str]:
        """The server-side resource names, `envs/{id}`, in env order."""
        return list(self._names)

    @property
    def env_addresses(self) -> list[str]:
        """The address of the server of each environment, in env order (env i: server i mod S
        until a failover moves it)."""
        return [self._connection_of(index).address for index in range(self.num_envs)]

    def _result(self, columns: dict):
        """step()'s return value from the decoded columns (num_envs leading)."""
        active = columns["stepped"]
        active[columns["auto_reset"]] = False  # An auto-reset row is not a transition.
        infos = {
            "auto_reset": columns["auto_reset"],
            "episode_over": columns["episode_over"],
            "outcome": columns["outcomes"],
            "episode_return": columns["episode_returns"],
            "episode_length": columns["episode_lengths"],
        }
        return (
            columns["observations"],
            columns["rewards"],
            columns["terminations"],
            columns["truncations"],
            active,
            infos,
        )

    def reset(self, seed: int | None = None, options: dict | None = None):
        self._check_no_step_in_flight()
        seed = seed_value(seed)
        responses: list = [None] * self.num_envs
        todo = list(range(self.num_envs))
        for _attempt in range(len(self._connections) + 2):  # Each try after a failover.
            waits = []
            for index in todo:
                request = pb.ResetEnvRequest(name=self._names[index])
                if seed is not None:
                    request.seed = (seed + index) % 2**64
                waits.append((index, self._connection_of(index).future("ResetEnv", request)))
            lost, failure = self._gather(waits, responses)
            if failure is not None:
                raise failure
            if not lost:
                break
            self._fail_over(lost)
            todo = sorted(lost)
        else:
            raise _record.gave_up(len(self._connections) + 2)
        datas = [response.data for response in responses]
        columns = self._columns_of(datas)
        self._record_reset(responses, columns["observations"])
        return columns["observations"], self._result(columns)[-1]

    def _gather(self, waits, results: list):
        """Waits for every (env index, wait) into results[index]; returns (envs to fail over: an
        unreachable server's, or NOT_FOUND, when failover is on; the first other error)."""
        lost, failure = {}, None
        for index, wait in waits:
            try:
                results[index] = wait()
            except MLLError as error:
                if self._lost(error, index):
                    lost[index] = error
                else:
                    failure = failure or error
        return lost, failure

    def _lost(self, error: MLLError, index: int) -> bool:
        """Whether env `index`'s `error` is one failover handles."""
        return self.failover and _record.loses_env(error, self._names[index])

    def _columns_of(self, datas) -> dict:
        """Result columns (num_envs leading) from one StepData per env."""
        columns = {
            field: _arrays.stack_bytes(
                [getattr(data, field).data for data in datas], wire, (len(datas),) + shape(self.n_landers), result
            )
            for field, wire, result, shape in _AGENT_COLUMNS
        }
        for field, _, result, _ in _ENV_COLUMNS:
            columns[field] = np.fromiter((getattr(data, field) for data in datas), dtype=result, count=len(datas))
        return columns

    def _record_reset(self, responses, observations) -> None:
        """Every env's record after a reset: a new one where the server reseeded, else an
        unseeded reset operation."""
        reseeded = np.array([response.HasField("seed") for response in responses])
        if reseeded.all():
            self._log.clear()
            self._start[:] = 0
        for index in np.flatnonzero(reseeded):
            self._seeds[index] = int(responses[index].seed)
            self._prefix[index] = None
            self._start[index] = self._log.length
        if not reseeded.all():
            kinds = np.where(reseeded, 0, _record.RESET).astype(np.uint8)
            self._log.append(kinds, np.zeros((self.num_envs, self._row_bytes), np.uint8))
            self._start[reseeded] = self._log.length
        np.copyto(self._last_observations, observations)

    def _check_no_step_in_flight(self) -> None:
        if self._step_in_flight:
            raise MLLError(
                grpc.StatusCode.FAILED_PRECONDITION,
                "a step_async is in flight; call step_wait for its results first",
            )
        if self._env_in_flight.any():
            raise MLLError(
                grpc.StatusCode.FAILED_PRECONDITION,
                f"{int(self._env_in_flight.sum())} envs have a send (or async_reset) whose results recv "
                "has not returned; recv them first",
            )

    # ----------------------------------------------------------------- EnvPool's async API

    def async_reset(self, seed: int | None = None) -> None:
        """Resets every env (seed s gives env i the seed s + i, as reset) and makes their first
        observations the results of the next recv() calls, batch_size envs each."""
        observations, infos = self.reset(seed)
        columns = {
            "observations": observations,
            "rewards": np.zeros((self.num_envs, self.n_landers), np.float32),
            "terminations": np.zeros((self.num_envs, self.n_landers), bool),
            "truncations": np.zeros((self.num_envs, self.n_landers), bool),
            "stepped": np.zeros((self.num_envs, self.n_landers), bool),  # Not transitions.
            "outcomes": infos["outcome"],
            "episode_returns": infos["episode_return"],
            "episode_lengths": infos["episode_length"],
            "episode_over": infos["episode_over"],
            "auto_reset": infos["auto_reset"],
        }
        self._ready.append((np.arange(self.num_envs), columns))
        self._env_in_flight[:] = True

    def send(self, actions, env_id) -> None:
        """Sends one step of the envs `env_id` (distinct indices in 0..num_envs-1, none with a
        step in flight) with `actions` (int (len(env_id), n_landers) or, continuous, float
        (len(env_id), n_landers, 2)) and returns at once: one packed StepBatch per server
        concerned, pipelined on its Session stream behind the requests already in flight."""
        if self._step_in_flight:
            self._check_no_step_in_flight()
        ids = np.asarray(env_id)
        if ids.ndim != 1 or ids.size == 0 or ids.dtype.kind not in "iu":
            raise invalid_argument(
                f"env_id is {_short(env_id)}; expected a non-empty 1-D array of env indices in 0..{self.num_envs - 1}"
            )
        if ids.min() < 0 or ids.max() >= self.num_envs:
            bad = ids[(ids < 0) | (ids >= self.num_envs)]
            raise invalid_argument(f"env_id holds {int(bad[0])}; allowed: 0..{self.num_envs - 1}")
        if np.count_nonzero(np.bincount(ids, minlength=self.num_envs) > 1):
            values, counts = np.unique(ids, return_counts=True)
            raise invalid_argument(f"env_id holds {int(values[counts > 1][0])} more than once; each env at most once")
        busy = ids[self._env_in_flight[ids]]
        if busy.size:
            raise MLLError(
                grpc.StatusCode.FAILED_PRECONDITION,
                f"env {int(busy[0])} has a step in flight (sent, or reset by async_reset); recv its result "
                "before sending it another",
            )
        block = check_actions(actions, self.continuous, (ids.size, self.n_landers), "actions")
        self._send_steps(ids, _arrays.to_rows(block, self._action_dtype))
        self._env_in_flight[ids] = True

    def _send_steps(self, ids: np.ndarray, rows: np.ndarray) -> None:
        """Sends one step of the envs `ids` with action rows `rows` (uint8 (len(ids), row bytes)):
        one packed StepBatch per server concerned, kept in flight until _receive_one."""
        for server in self._servers:
            if len(self._servers) == 1:
                envs, actions = ids, rows
            else:
                mine = self._placement[ids] == server.index
                if not mine.any():
                    continue
                envs, actions = ids[mine], rows[mine]
            reusable = isinstance(server.stream, _native.NativeSessionStream)
            self._send_packed(server, envs, actions.tobytes(), reusable)
            self._in_flight[server.index].append((envs, actions))
            self._send_order.append(server.index)

    def _packed_request(
        self, server: "_Server", envs: np.ndarray, key: bytes, handle: int, answered: bool, reusable: bool
    ) -> "pb.SessionRequest":
        """A packed StepBatch request for `envs` (`key`: their indices' bytes) on `server`, its
        actions to be set: by `handle` alone when `answered`, else with the envs' names (and the
        handle, 0: none). A request whose last use has been answered is reused where `reusable`
        (the native stream encodes a request as it is sent; grpcio's encodes it later, on its own
        thread, so an async request there gets a new one each time)."""
        cache_key = (server.index, key, handle, answered)
        message = self._requests.get(cache_key) if reusable else None
        if message is None:
            message = pb.SessionRequest()
            packed = message.step_batch.packed
            if not answered:
                packed.names.extend(self._names[env] for env in envs)
            packed.handle = handle
            packed.actions.dtype = self._action_dtype
            packed.actions.shape.extend((envs.size,) + self._action_shape)
            if reusable:
                if len(self._requests) >= 4 * self.num_envs:  # Bounded: groups that keep changing.
                    self._requests.clear()
                self._requests[cache_key] = message
        return message

    def recv(self):
        """The results of the first batch_size envs whose steps are done (in the order their
        answers came), as step() returns them, with infos["env_id"] (int, (batch_size,)) naming
        the envs of each row. Waits for answers as needed; FAILED_PRECONDITION when fewer than
        batch_size envs have a step in flight."""
        waiting = np.count_nonzero(self._env_in_flight)
        if waiting < self.batch_size:
            raise MLLError(
                grpc.StatusCode.FAILED_PRECONDITION,
                f"recv needs batch_size = {self.batch_size} envs with a step in flight; {waiting} have one "
                "(send or async_reset first)",
            )
        while sum(chunk[0].size for chunk in self._ready) < self.batch_size:
            self._receive_one()
        taken, parts, left = [], [], self.batch_size
        while left:
            ids, columns = self._ready.popleft()
            if ids.size > left:  # Split: the rest stays first in line.
                self._ready.appendleft((ids[left:], {name: value[left:] for name, value in columns.items()}))
                ids, columns = ids[:left], {name: value[:left] for name, value in columns.items()}
            taken.append(ids)
            parts.append(columns)
            left -= ids.size
        if len(parts) == 1:
            env_id, merged = taken[0], parts[0]
        else:
            env_id = np.concatenate(taken)
            merged = {name: np.concatenate([part[name] for part in parts]) for name in parts[0]}
        self._env_in_flight[env_id] = False
        result = self._result(dict(merged))
        result[-1]["env_id"] = env_id
        return result

    def _receive_one(self) -> None:
        """Receives the answer to the oldest request in flight (its server's oldest) into the ready
        chunks and the envs' records. Envs lost with their server (or NOT_FOUND) are failed over
        and their steps sent again (recv returns those results later, the same bits); another
        failed env's error is raised as step raises it (its request's envs are then no longer in
        flight)."""
        index = self._send_order.popleft()
        envs, actions = self._in_flight[index].popleft()
        connection = self._connections[index]
        try:
            pack = self._packed_reply(connection, self._receive_packed(index))
        except MLLError as error:
            if not self._lost(error, int(envs[0])):
                self._env_in_flight[envs] = False
                raise
            requests, moving = [(envs, actions)], envs
            if error.code == grpc.StatusCode.UNAVAILABLE:
                # The server is lost with every request in flight on it; its envs move together.
                requests += self._in_flight[index]
                self._in_flight[index].clear()
                self._send_order = collections.deque(server for server in self._send_order if server != index)
                moving = np.flatnonzero(self._placement == index)
            self._fail_over_and_resend(dict.fromkeys(moving.tolist(), error), requests)
            return
        lost: dict[int, MLLError] = {}
        if pack.errors:
            try:
                failed = self._row_errors(connection, envs, pack.errors, lost)
                if failed:  # The first failed env in env order.
                    raise min(failed, key=lambda pair: pair[0])[1]
            except MLLError:
                self._env_in_flight[envs] = False
                raise
        decoders = self._async_columns.get(envs.size)
        if decoders is None:  # Worked out once per request size.
            decoders = self._async_columns[envs.size] = tuple(
                _arrays.Column(field, wire, (envs.size,) + shape(self.n_landers), result)
                for field, wire, result, shape in _AGENT_COLUMNS + _ENV_COLUMNS
            )
        columns = {column.name: column.decode(getattr(pack, column.name)) for column in decoders}
        if lost:  # Those rows hold no step: the others are received, the lost ones sent again.
            stepped = ~np.isin(envs, list(lost))
            columns = {name: value[stepped] for name, value in columns.items()}
            retry = (envs[~stepped], actions[~stepped])
            envs, actions = envs[stepped], actions[stepped]
        if envs.size:
            kinds = np.where(columns["auto_reset"], _record.AUTO_RESET, _record.STEP).astype(np.uint8)
            self._log.append_envs(envs, kinds, actions)
            self._last_observations[envs] = columns["observations"]
            self._ready.append((envs, columns))
        if lost:
            self._fail_over_and_resend(lost, [retry])

    def _fail_over_and_resend(self, lost: dict, requests: list) -> None:
        """Fails the `lost` envs over (replayed to their last results received), then sends the
        `requests` ((env indices, action rows) in flight where they were lost, oldest first) again
        on the envs' new servers, so recv returns their results as it would have. If failover
        fails, those envs are no longer in flight."""
        try:
            self._fail_over(lost)
        except BaseException:
            for envs, _ in requests:
                self._env_in_flight[envs] = False
            raise
        for envs, actions in requests:
            self._send_steps(envs, actions)

    @staticmethod
    def _packed_reply(connection: Connection, reply):
        """The packed results of a StepBatch reply; UNIMPLEMENTED from a server that predates them."""
        if not reply.HasField("packed"):
            raise MLLError(
                grpc.StatusCode.UNIMPLEMENTED,
                f"{connection.address} answered a packed StepBatch without packed results; "
                "its mll_server predates StepBatchRequest.packed: upgrade it",
            )
        return reply.packed

    def _set_actions(self, actions) -> None:
        """Checks `actions` and keeps their bytes (env-major rows) as the step's."""
        self._check_no_step_in_flight()
        block = check_actions(actions, self.continuous, (self.num_envs, self.n_landers), "actions")
        self._pending = _arrays.to_rows(block, self._action_dtype)

    def step(self, actions, env_id=None):
        """step(actions) steps every env (batch_size == num_envs: the synchronous API). With the
        async API, step(actions, env_id) is send(actions, env_id) then recv(); env_id None means
        every env."""
        if env_id is None and self.batch_size == self.num_envs and not self._env_in_flight.any():
            self.step_async(actions)
            return self.step_wait()
        self.send(actions, np.arange(self.num_envs) if env_id is None else env_id)
        return self.recv()

    def step_async(self, actions) -> None:
        """Sends step(actions) and returns at once; step_wait() returns its results. Between the
        two the caller is free to compute (e.g. a learning step) while the servers step."""
        self._set_actions(actions)
        # One StepBatch per server on its Session stream, all in flight at once; the requests of
        # the last step are answered, so they are reused.
        single = len(self._servers) == 1
        for server in self._servers:
            rows = self._pending if single else self._pending[server.rows]
            self._send_packed(server, server.rows, rows.tobytes(), reusable=True)
        self._step_in_flight = True

    def step_wait(self):
        """The results of the step sent by step_async, as step() returns them."""
        if not self._step_in_flight:
            raise MLLError(grpc.StatusCode.FAILED_PRECONDITION, "step_wait without a step_async in flight")
        self._step_in_flight = False
        replies, failure, lost = [], None, {}
        for server in self._servers:  # Every answer is read, so each stream is ready for the next step.
            try:
                replies.append(self._receive_packed(server.index))
            except MLLError as error:
                replies.append(None)
                if self._lost(error, int(server.rows[0])):
                    lost.update((int(row), error) for row in server.rows)
                else:
                    failure = failure or error
        if failure is not None:
            raise failure
        columns = self._collect(replies, lost)
        if lost:
            self._retry_step(lost, columns)
        kinds = np.where(columns["auto_reset"], _record.AUTO_RESET, _record.STEP).astype(np.uint8)
        self._log.append(kinds, self._pending)
        np.copyto(self._last_observations, columns["observations"])
        return self._result(columns)

    def _collect(self, replies, lost: dict) -> dict:
        """The result columns from each server's StepBatch reply (None: the server was lost);
        envs to fail over (failover on: NOT_FOUND rows) are added to `lost`, their rows unset."""
        servers = self._servers
        packs = []
        failed = []  # (env index, MLLError) of every env whose step failed.
        for server, reply in zip(servers, replies):
            if reply is None:
                packs.append(None)
                continue
            pack = self._packed_reply(server.connection, reply)
            packs.append(pack)
            if pack.errors:
                failed += self._row_errors(server.connection, server.rows, pack.errors, lost)
        if failed:  # The first failed env in env order, as on one server.
            raise min(failed, key=lambda pair: pair[0])[1]
        if len(servers) == 1 and packs[0] is not None:
            columns = servers[0].columns
            return {column.name: column.decode(getattr(packs[0], column.name)) for column in columns}
        columns = {  # Each server's rows scattered back to env order.
            column.name: np.zeros((self.num_envs,) + column.shape[1:], dtype=column.as_dtype)
            for column in servers[0].columns
        }
        for server, pack in zip(servers, packs):
            if pack is not None:
                for column in server.columns:
                    columns[column.name][server.rows] = column.decode(getattr(pack, column.name))
        return columns

    def _row_errors(self, connection: Connection, envs: np.ndarray, errors, lost: dict) -> list:
        """The errors of a packed StepBatch's rows (`envs`: the env of each row): envs to fail over
        go into `lost`, the others are returned as (env index, MLLError)."""
        failed = []
        for item in errors:
            if not 0 <= item.index < envs.size:
                raise MLLError(
                    grpc.StatusCode.INTERNAL,
                    f"{connection.address} reported an error for row {item.index} of a packed "
                    f"StepBatch of {envs.size} envs",
                )
            env = int(envs[item.index])
            error = from_item_error(item.error.code, item.error.message, f"env {env} ({self._names[env]}): ")
            if self._lost(error, env):
                lost[env] = error
            else:
                failed.append((env, error))
        return failed

    def _retry_step(self, lost: dict, columns: dict) -> None:
        """Fails the `lost` envs over, then steps them again with the step's actions (the step
        their server did not take) into `columns`."""
        datas: list = [None] * self.num_envs
        for _attempt in range(len(self._connections) + 2):
            self._fail_over(lost)
            waits = []
            for index in sorted(lost):
                request = pb.StepEnvRequest(name=self._names[index])
                request.actions.dtype = self._action_dtype
                request.actions.shape.extend(self._action_shape)
                request.actions.data = self._pending[index].tobytes()
                waits.append((index, self._connection_of(index).future("StepEnv", request)))
            done = sorted(lost)
            lost, failure = self._gather(waits, datas)
            if failure is not None:
                raise failure
            if not lost:
                break
        else:
            raise _record.gave_up(len(self._connections) + 2)
        rows = np.array(done)
        retried = self._columns_of([datas[index].data for index in done])
        for name, values in retried.items():
            columns[name][rows] = values

    def _env_record(self, index: int) -> _record.EnvRecord:
        """Env `index`'s record; FAILED_PRECONDITION when it cannot recreate the env."""
        why = None
        if self._seeds[index] is None:
            why = "it was never reset (no known seed)"
        elif self._log.full:
            why = f"its record passed {_record.MAX_RECORD_STEPS} operations since its last seeded reset"
        if why:
            raise MLLError(
                grpc.StatusCode.FAILED_PRECONDITION,
                f"env {index} ({self._names[index]}) cannot be recreated: {why}; reset(seed=...) starts a new record",
            )
        kinds, actions = self._log.of_env(index, int(self._start[index]))
        prefix = self._prefix[index]
        if prefix is not None:
            kinds = np.concatenate([prefix.kinds, kinds])
            actions = np.concatenate([prefix.actions, actions])
        return _record.EnvRecord(self._seeds[index], kinds, actions, self._last_observations[index].tobytes())

    def _usable_connections(self) -> list[int]:
        """Connections a failover may use (_record.usable_servers: those not found down, and those
        found down that answer again on a renewed connection; the embedded server restarted if it
        died)."""
        before = list(self._connections)
        usable = _record.usable_servers(self._connections, self._down)
        for index, (old, new) in enumerate(zip(before, self._connections)):
            if new is not old:  # Renewed (a server back, the embedded one restarted): a new stream.
                self._streams[index].close()
                self._streams[index] = self._stream_type(new)
                self._handles[index] = self._new_handles(index)
        return usable

    def _fail_over(self, lost: dict) -> None:
        """Recreates the `lost` envs (env index -> the error that lost it) on reachable servers
        and replays their records to the bits the client last saw; one failover event. A target
        that turns out unreachable during the replay (it began to drain, or died) is passed over
        for the next reachable one; UNAVAILABLE naming the servers tried when none is left."""
        began = time.monotonic()
        moving = sorted(lost)
        unreachable = sorted({int(self._placement[i]) for i in moving if lost[i].code == grpc.StatusCode.UNAVAILABLE})
        for index in unreachable:
            self._down.add(index)
            self._streams[index].close()
        records = {index: self._env_record(index) for index in moving}
        # NOT_FOUND on a server that answers: recreated there; the others go round robin over
        # the usable servers.
        pending = {
            index: int(self._placement[index])
            for index in moving
            if lost[index].code != grpc.StatusCode.UNAVAILABLE and int(self._placement[index]) not in self._down
        }
        homeless = [index for index in moving if index not in pending]
        refused: dict[int, MLLError] = {}  # Server index -> why the replay there failed.
        placement: dict[int, int] = {}  # Env index -> the server it was recreated on.
        draining: dict[int, list[str]] = {}  # Server index -> names of its moved envs, when it drains.
        while pending or homeless:
            if homeless:
                untried = len(refused) < len(self._connections)  # Else none is left to probe again.
                targets = [index for index in self._usable_connections() if index not in refused] if untried else []
                if not targets:
                    raise self._no_server_left(lost, refused)
                pending.update((index, targets[spread % len(targets)]) for spread, index in enumerate(homeless))
                homeless = []
            for target in sorted(set(pending.values())):
                envs = [index for index in moving if pending.get(index) == target]
                connection = self._connections[target]
                try:
                    created, _ = _record.replay(
                        connection,
                        self._spec_config,
                        [records[index] for index in envs],
                        [f"env {index} ({self._names[index]})" for index in envs],
                        self._action_dtype,
                        self._action_shape,
                    )
                except MLLError as error:
                    if error.code != grpc.StatusCode.UNAVAILABLE:
                        raise
                    refused[target] = error  # Its envs try the next server.
                    self._down.add(target)
                    homeless += envs
                    continue
                for index, env in zip(envs, created):
                    if "draining:" in lost[index].message:
                        draining.setdefault(int(self._placement[index]), []).append(self._names[index])
                    self._names[index] = env.name
                    self._placement[index] = target
                    placement[index] = target
                    _lease.hold(connection, env.name, env.idle_timeout_s)
            pending = {}
        self._build_servers()
        # A draining server exits once it holds no env: its copies of the moved envs go now.
        for index, names in draining.items():
            for name in names:
                _record.delete_quietly(self._connections[index], name)
        self.failovers += 1
        _record.log_failover(
            "vector_env",
            len(moving),
            lost[moving[0]],
            (self._connections[placement[index]].address for index in moving),
            sum(record.kinds.size for record in records.values()),
            began,
            self._refusals(refused),
        )

    @staticmethod
    def _refusals(refused: dict) -> str:
        """"; passed over" and the error of each server whose replay failed (server index -> its
        MLLError, whose message names the server), or ""."""
        return "".join(f"; passed over {error.message}" for _, error in sorted(refused.items()))

    def _no_server_left(self, lost: dict, refused: dict) -> MLLError:
        """UNAVAILABLE: no server is left to fail the `lost` envs over to."""
        first = lost[min(lost)]
        return MLLError(
            grpc.StatusCode.UNAVAILABLE,
            f"failover of {len(lost)} envs found no reachable server of {', '.join(self.addresses)}: "
            f"{first.message}{self._refusals(refused)}",
        )

    # ----------------------------------------------------------------- env snapshot

    def env_snapshot(self, index: int) -> bytes:
        """Env `index`'s snapshot: bytes that recreate it at this point to the same bits on any
        server of the same release (restore_env, parallel_env's restore). FAILED_PRECONDITION
        when its record cannot (see docs/python.md, "Failover and snapshots")."""
        self._check_no_step_in_flight()
        index = self._env_index(index)
        info = self._connection_of(index).server_info
        return _record.encode_snapshot(
            self._spec_config, info.protocol, info.server_version, self._env_record(index),
            self._action_dtype, self._row_bytes,
        )

    def restore_env(self, index: int, snapshot: bytes) -> np.ndarray:
        """Puts env `index` at the point `snapshot` (env_snapshot, parallel_env's snapshot)
        describes: a new env on the same server replays it, checked to the bits, then replaces the
        old one. Returns its observations (n_landers, 12). INVALID_ARGUMENT for a damaged snapshot
        or one of an env with other options; the env is untouched on any error."""
        self._check_no_step_in_flight()
        index = self._env_index(index)
        decoded = _record.decode_snapshot(snapshot)
        connection = self._connection_of(index)
        _record.check_restorable(decoded, self._spec_config, connection.server_info)
        (env,), _ = _record.replay(
            connection, self._spec_config, [decoded.record], [f"env {index} (restored)"],
            self._action_dtype, self._action_shape,
        )
        _record.delete_quietly(connection, self._names[index])
        self._names[index] = env.name
        _lease.hold(connection, env.name, env.idle_timeout_s)
        self._build_servers()
        self._seeds[index] = decoded.record.seed
        self._prefix[index] = decoded.record
        self._start[index] = self._log.ends()[index]
        observations = np.frombuffer(decoded.record.last_observations, "<f4").reshape(self.n_landers, 12)
        self._last_observations[index] = observations
        return observations.astype(np.float32)

    def _env_index(self, index) -> int:
        if isinstance(index, (bool, np.bool_)) or not isinstance(index, (int, np.integer)) or not (
            0 <= index < self.num_envs
        ):
            raise invalid_argument(f"env index is {index!r}; allowed: 0..{self.num_envs - 1}")
        return int(index)

    def close(self) -> None:
        """Deletes the environments on their servers and closes the connections. Idempotent."""
        if all(connection.closed for connection in self._connections):
            return
        for stream in getattr(self, "_streams", ()):
            stream.close()
        try:
            waits = [
                self._connection_of(index).future("DeleteEnv", pb.DeleteEnvRequest(name=name))
                for index, name in enumerate(self._names)
                if name is not None
            ]
            for wait in waits:
                try:
                    wait()
                except Exception:  # Already gone (e.g. reclaimed by the idle timeout).
                    pass
        finally:
            for connection in self._connections:
                connection.close()

    def __enter__(self) -> "VectorEnv":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
