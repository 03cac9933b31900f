"""Many environments stepped together, arrays in and out: a thin adapter over the C++ client's
VectorEnv (client_cpp/include/mll/vector_env.h) through its C interface
(client_cpp/native/vector_c_api.h) in the native library (_native). Placement over servers, the
Session streams (shared memory with a server on this host), batch handles, pipelined send/recv,
failover by replay and the snapshot format are that engine's; this module keeps Python's part:
arguments, spaces, arrays the caller owns, infos, exceptions and the log.

Several servers (address= a list or "host:port,host:port", or a host name standing for every
address it resolves to): the envs are placed on the least-loaded servers (until failover or
rebalancing moves them). Each step sends one packed StepBatch to every server at once, each
with that server's envs, and puts the results back in env order. Each env's physics and
generator are its own, so the results are the same bits as on one server.

Episode ends (auto-reset): the environments are created with the server's `auto_reset`. When
an environment's episode is over (no lander active), its NEXT step ignores the actions and
starts a new episode, continuing that environment's generator stream (no reseed): the result
holds the new episode's first observations, zero rewards, no terminations/truncations, and
`infos["auto_reset"][i]` is True. Those rows are not transitions, so `active[i]` is all False
for them. Observations of agents that are done (before the episode is over) are zero rows and
their `active` entries are False.
"""

from __future__ import annotations

import ctypes
import logging
import os
import sys
import sysconfig
import weakref
from typing import Any, NamedTuple, Sequence

import grpc
import numpy as np

from . import _arrays, _native, _record
from ._actions import _short, check_actions
from ._channel import Security, parse_addresses, seconds_value, step_timeout_value
from ._errors import MLLError, from_call_status, invalid_argument
from ._remote import (
    check_process,
    config_dict,
    describe_server,
    embedded_lease,
    make_config,
    rebuild,
    seed_value,
    space_from_proto,
)
from ._server_info import ServerInfo
from ._stubs import pb

_LOG = logging.getLogger("multi_lunar_lander")

# transport= values, as MLL_NATIVE_TRANSPORT_* of client_cpp/native/vector_c_api.h.
TRANSPORTS = {"auto": 0, "shared_memory": 1, "native": 2}

# Where the engine's result columns (mll_vector_env_column_name) go in Python's results: the
# first ones are step()'s arrays, in order; the others are infos, under these keys (a column not
# named here keeps its own name there). Flags (uint8 0/1) are returned as bool.
_RETURNED = ("observations", "rewards", "terminations", "truncations", "active")
_INFO_KEYS = {
    "outcomes": "outcome",
    "episode_returns": "episode_return",
    "episode_lengths": "episode_length",
    "env_ids": "env_id",
}
_FLAGS = frozenset(("terminations", "truncations", "active", "auto_reset", "episode_over"))


class _Column(NamedTuple):
    """One result column of the engine's table (vector_c_api.h)."""

    index: int
    name: str
    dtype: np.dtype
    per_agent: bool
    width: int


_columns_of: dict[int, tuple[_Column, ...]] = {}  # id(library) -> its column table.


def columns(lib: ctypes.CDLL) -> tuple[_Column, ...]:
    """The result columns as the library describes them (mll_vector_env_column_*)."""
    table = _columns_of.get(id(lib))
    if table is None:
        table = _columns_of[id(lib)] = tuple(
            _Column(
                index,
                lib.mll_vector_env_column_name(index).decode(),
                _arrays.wire_dtype_to_numpy(lib.mll_vector_env_column_dtype(index)),
                bool(lib.mll_vector_env_column_per_agent(index)),
                int(lib.mll_vector_env_column_width(index)),
            )
            for index in range(lib.mll_vector_env_column_count())
        )
    return table


# copy=True: the records of one block (_Results), so that a call finds one whose arrays nobody holds.
_RECORDS_PER_BLOCK = 4
# A reference count tells whether anything outside the adapter refers to an array (not in a
# free-threaded build, whose counts are not exact).
_COUNTS_ARE_EXACT = not sysconfig.get_config_var("Py_GIL_DISABLED")


class _Results:
    """Where the engine writes the results of `rows`-row calls, in place, and what a call hands out.

    The results of one call are one record: a NumPy structured record of one field per result
    column (shape and element type from the column table; flags as bool). The adapter binds a
    block of records to the handle (mll_vector_env_bind_results), with an offset the library
    reads at each call (mll_vector_env_bind_results_offset), so that a call that makes results
    writes them into the current record before it returns. Each record's arrays are made with
    its block.

    copy=False: one record, written by every call. copy=True: every call's arrays are the
    caller's own, never written again while anything refers to them. After each call the offset
    moves on to a record of the block whose arrays nothing outside the adapter refers to any more
    (their reference counts say so: no variable, container, view, buffer or tensor of the caller's
    holds them), as NumPy reuses the memory of temporaries; when every record is still held, a
    new block is made and bound, and the old one lives on as long as its arrays do. A trainer
    that lets go of a step's results within a few calls is handed the same memory again, with no
    copy and no new array per call; one that keeps them all gets new arrays every call."""

    def __init__(self, lib: ctypes.CDLL, handle: int, table: tuple[_Column, ...], rows: int, n_landers: int,
                 copy: bool):
        names, formats, offsets, offset = [], [], [], 0
        for column in table:
            offset = -(-offset // 16) * 16
            shape = (rows,) + ((n_landers,) if column.per_agent else ()) + ((column.width,) if column.width > 1 else ())
            element = np.dtype(bool) if column.name in _FLAGS else column.dtype
            names.append(column.name)
            formats.append((element, shape))
            offsets.append(offset)
            offset += int(np.prod(shape)) * element.itemsize
        self.dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets,
                               "itemsize": -(-offset // 16) * 16})
        self._offsets, self._lib, self._handle, self._rows = offsets, lib, handle, rows
        self._reuse = copy and _COUNTS_ARE_EXACT
        self._fresh = copy and not _COUNTS_ARE_EXACT  # Then a new block (of one record) every call.
        self._records = _RECORDS_PER_BLOCK if self._reuse else 1
        infos = [name for name in names if name not in _RETURNED and name != "env_ids"]
        self._info_keys = [_INFO_KEYS.get(name, name) for name in infos]
        self._order = _RETURNED + tuple(infos)
        self._offset = ctypes.c_int64(0)  # Bytes past the block's first record; read by the library.
        # The per-call part (take: the current record as step() returns it, the offset moved on).
        self.records = _native.fast_calls().Records(
            offset_address=ctypes.addressof(self._offset),
            record_bytes=self.dtype.itemsize,
            returned=len(_RETURNED),
            info_keys=tuple(self._info_keys),
            reuse=self._reuse,
            new_block=_weak_method(self._new_block) if self._reuse or self._fresh else None,
            env_id_dtype=np.dtype(np.int64),  # NumPy's and torch's index type (the engine's is int32).
        )
        self._new_block()
        code = lib.mll_vector_env_bind_results_offset(handle, rows, ctypes.addressof(self._offset))
        if code:
            raise from_call_status(code, lib.mll_vector_env_message(handle).decode(errors="replace"))

    def _new_block(self) -> None:
        """A new block of records, bound to the handle, the offset at its first record."""
        block = np.zeros(self._records * self.dtype.itemsize, np.uint8)
        made = [self._record_arrays(block, record) for record in range(self._records)]
        self._pointers = np.array([block.ctypes.data + offset for offset in self._offsets], np.uint64)
        code = self._lib.mll_vector_env_bind_results(self._handle, self._rows, self._pointers.ctypes.data)
        if code:
            raise from_call_status(code, self._lib.mll_vector_env_message(self._handle).decode(errors="replace"))
        # With the reference counts of a record's members while only the block holds them.
        self.records.set_block(tuple(made), tuple(map(sys.getrefcount, made[0])))

    def _record_arrays(self, block: np.ndarray, record: int) -> tuple:
        """Record `record` of `block`: step()'s arrays, the infos' arrays, env_ids, then their owner,
        a one-record array over a memoryview of the record's bytes. NumPy makes a view's base the
        array it is a view of, or that array's base while that is an array too: here every view
        of the record's arrays, a view of a view included, refers to the owner and stops there,
        so that the owner's reference count tells whether anything still refers to the record."""
        size = self.dtype.itemsize
        owner = np.frombuffer(memoryview(block)[record * size:(record + 1) * size], self.dtype, count=1)
        return tuple(owner[name][0] for name in self._order + ("env_ids",)) + (owner,)

    def arrays(self, with_env_ids: bool) -> tuple:
        """step()'s return value of the call that just wrote the current record, as the class
        says; infos is a new dict either way, with infos["env_id"] (int64) when `with_env_ids`."""
        return self.records.take(with_env_ids)


def _weak_method(method):
    """`method` as a function that refers to its object weakly: handed to the object's own
    extension Records, it makes no reference cycle, so the results' block goes with the vector
    env, not at the next cyclic garbage collection."""
    ref = weakref.WeakMethod(method)
    return lambda: ref()()


def rediscover_interval_value(rediscover_interval_s) -> float:
    """The engine's argument of a `rediscover_interval_s=` argument: -1 (its default, 10 s) for
    None, else a finite number of seconds >= 0 (0: never); INVALID_ARGUMENT for anything else."""
    if rediscover_interval_s is None:
        return -1.0
    return seconds_value("rediscover_interval_s", rediscover_interval_s, "10 s", "never")


def _fill(block: np.ndarray, actions, continuous: bool) -> None:
    """Puts `actions` into `block`, a buffer of the adapter's in the wire's type (int32, or float32
    when continuous) whose address the library reads. An array of the block's shape and element
    type is copied as it is (256 bytes for 64 envs, cheaper than reading the array's own address);
    anything else goes through check_actions first."""
    if not (type(actions) is np.ndarray and actions.dtype is block.dtype and actions.shape == block.shape):
        actions = check_actions(actions, continuous, block.shape[:2], "actions")
    block[...] = actions


# Every open VectorEnv of this process: a forked child turns their fast paths off (_disown), so that
# the per-call paths need no process check (os.getpid() is a system call).
_OPEN: weakref.WeakSet = weakref.WeakSet()


def _disown() -> None:
    for env in list(_OPEN):
        env._fast = env._fast_send = env._fast_recv = None


os.register_at_fork(after_in_child=_disown)


def _free(lib: ctypes.CDLL, handle: int, lease, pid: int, keep: list) -> None:
    """Frees a handle (deleting its envs) and then releases the embedded server it used. `keep`:
    memory the handle writes into (its event flag), kept alive until then."""
    if os.getpid() != pid:  # A forked child's copy: the handle and the lease are the parent's.
        return
    lib.mll_vector_env_free(handle)
    if lease is not None:
        lease.release()


class VectorEnv:
    """`num_envs` Multi Lunar Lander environments with the same options, on the server(s) of
    `address` (placed on the least-loaded servers; None: the embedded server). TLS and token: as for
    `parallel_env` (tls_root_cert=, tls_server_name=, token=). Needs the native library
    (libmll_native_stream.so: in the binary wheel and `pip install .`; see _native), whose C++
    VectorEnv does the work; FAILED_PRECONDITION saying how to get it when it is missing.

    transport= how the Session streams travel:
      "shared_memory": through a shared-memory region that a server on this host (loopback
      address or Unix-domain socket) grants the stream: no socket, one futex wake-up each way,
      the fastest; FAILED_PRECONDITION with the server's reason when refused (or when the region
      cannot be mapped here: a server in another container).
      "native": over gRPC C++'s HTTP/2 stream (any server).
      "auto" (the default): shared memory where granted, else the stream.
      All give the same results and errors. The `transport` attribute says which is in use.
      ("grpc", a grpcio path, is gone: INVALID_ARGUMENT; see docs/design.md.)

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
    copy= (default True) how results are handed out: the engine writes each call's results in
      place into arrays the adapter owns. True: every call returns arrays of the caller's own,
      which no later call writes while anything refers to them (a variable, a list, a view, a
      memoryview, a tensor sharing their memory), as Gymnasium's vector envs (copy=True), SB3's
      VecEnvs and EnvPool do, so that a trainer may keep them (e.g. append observations to a
      list); the memory of results nothing refers to any more is written again, with no copy.
      False: every call returns the same arrays, overwritten by the next call that makes results
      of as many rows (reset, step, step_wait: num_envs; recv: batch_size), as Gymnasium's
      copy=False. infos is a new dict each call either way; infos["env_id"] is a new array.
    Errors: when the step of some envs fails on the server (e.g. an env deleted behind this
      object's back: NOT_FOUND), step raises MLLError with the server's code and message for
      the first of them in env order, prefixed "env {i} ({name}): "; the other envs did step.
    step_timeout_s= how long a request may wait for its answer before its server counts as lost
      (None: 5 s; 0: no deadline).
    address= entries may be host names: a name stands for every address it resolves to (a
      Kubernetes headless Service's pods), each one server; envs go to the least-loaded servers.
      rediscover_interval_s= how often the names are resolved again (None: 10 s; 0: never; also
      at every failover): envs move onto servers that join (`rebalances` counts the events);
      servers gone from a name keep their envs while they answer, and get no new ones.
    Failover (failover=; None: on with several servers or the embedded one, off with one
      address): envs lost with their server are recreated on another and replayed to the same
      bits; each event counts in `failovers` and is logged as a warning on the
      "multi_lunar_lander" logger.
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
        step_timeout_s: float | None = None,
        rediscover_interval_s: float | None = None,
        copy: bool = True,
        **options: Any,
    ):
        if transport == "grpc":
            raise invalid_argument(
                "transport is 'grpc': vector envs no longer step over grpcio; their one engine is the C++ client's "
                "in the native library, which ships with the package (binary wheel, pip install .); use "
                "transport='auto' (shared memory where granted, else gRPC C++), or env()/parallel_env() for "
                "pure-Python grpcio calls"
            )
        if transport not in TRANSPORTS:
            raise invalid_argument(f"transport is {transport!r}; allowed: {', '.join(map(repr, TRANSPORTS))}")
        if isinstance(num_envs, bool) or int(num_envs) != num_envs or num_envs < 1:
            raise invalid_argument(f"num_envs is {num_envs!r}; expected an integer >= 1")
        self.num_envs = int(num_envs)
        batch_size = self.num_envs if batch_size is None else batch_size
        if isinstance(batch_size, bool) or int(batch_size) != batch_size or not 1 <= batch_size <= self.num_envs:
            raise invalid_argument(
                f"batch_size is {batch_size!r}; allowed: an integer in 1..num_envs = 1..{self.num_envs}"
            )
        self.batch_size = int(batch_size)
        config = make_config(None, True, options)
        security = Security.from_options(tls_root_cert, tls_server_name, token)
        step_timeout = step_timeout_value(step_timeout_s)
        addresses = parse_addresses(address)
        # What a pickle carries (__reduce__): the arguments, never a connection or stream.
        self._init_kwargs = dict(
            options,
            num_envs=self.num_envs,
            address=list(addresses) or None,
            transport=transport,
            batch_size=self.batch_size,
            failover=failover,
            step_timeout_s=step_timeout_s,
            rediscover_interval_s=rediscover_interval_s,
            copy=copy,
            **security.as_options(),
        )
        if not isinstance(copy, (bool, np.bool_)):
            raise invalid_argument(f"copy is {copy!r}; expected True or False")
        self._copy = bool(copy)
        lib = self._lib = _native.library("vector_env")
        self._columns = columns(lib)
        self._transport = "native"  # The last one `transport` saw (what it says once closed).
        self._interrupted = False  # An interrupted step() left its step in flight (_finish_interrupted).
        lease = None if addresses else embedded_lease(security)
        root = security.root_certificates
        config_bytes = config.SerializeToString()
        handle = lib.mll_vector_env_new(
            ",".join(addresses or [lease.address]).encode(),
            root,
            len(root or b""),
            (security.server_name or "").encode(),
            (security.token or "").encode(),
            TRANSPORTS[transport],
            config_bytes,
            len(config_bytes),
            self.num_envs,
            self.batch_size,
            # -1: the engine decides one address (on for a host name, off for an IP address).
            -1 if failover is None and len(addresses) == 1 else int(_record.failover_on(failover, addresses)),
            -1.0 if step_timeout_s is None else step_timeout or 0.0,  # -1: the engine's default.
            rediscover_interval_value(rediscover_interval_s),
        )
        # How an UNAVAILABLE error names each server (as the AEC and parallel envs' do).
        self._descriptions = {
            server: describe_server(server, security, addresses, embedded=lease is not None)
            for server in addresses or [lease.address]
        }
        self._handle, self._pid = handle, os.getpid()
        self._events = ctypes.c_int32(0)  # The handle's flag of events to take (_check).
        self._finalizer = weakref.finalize(self, _free, lib, handle, lease, self._pid, [self._events])
        code = lib.mll_vector_env_create_status(handle)
        if code:
            error = self._error(code)
            self.close()
            raise error
        spec = pb.Env.FromString(self._bytes(lib.mll_vector_env_spec))
        self.config = config_dict(spec.config)
        self.continuous = bool(lib.mll_vector_env_continuous(handle))
        self.n_landers = int(lib.mll_vector_env_n_landers(handle))
        self.possible_agents = list(spec.possible_agents)
        self.single_observation_space = space_from_proto(spec.observation_space)
        self.single_action_space = space_from_proto(spec.action_space)
        self._observation_width = next(column.width for column in self._columns if column.name == "observations")
        # Where results are written in place: num_envs rows (reset, step), batch_size rows (recv).
        self._results_of = {rows: _Results(lib, handle, self._columns, rows, self.n_landers, self._copy)
                            for rows in {self.num_envs, self.batch_size}}
        self._action_blocks: dict[int, tuple] = {}  # Row count -> (buffer for actions, its address, size).
        self._action_dtype = np.dtype(np.float32 if self.continuous else np.int32)
        self._action_shape = (self.n_landers, 2) if self.continuous else (self.n_landers,)
        # What step(), send() and recv() need on every call, made once: the calls of the
        # library's step and recv with their arguments bound (_native.fast_calls: one call of the
        # interpreter each, the results' record taken in it), send's function without argument
        # conversion (_native.bare) and its arguments as ctypes values, the actions' buffer.
        # None once closed.
        bare, self._bare_handle = _native.bare(lib), ctypes.c_void_p(handle)
        lib.mll_vector_env_bind_event_flag(handle, ctypes.addressof(self._events))
        fast_calls, events_address = _native.fast_calls(), ctypes.addressof(self._events)
        self._fast = None  # step() with batch_size == num_envs.
        if self.batch_size == self.num_envs:
            block = np.zeros((self.num_envs,) + self._action_shape, self._action_dtype)
            self._fast = (block, fast_calls.Call(
                function_address=_native.address_of(bare.mll_vector_env_step), handle=handle,
                timeout_ms=_native.READ_SLICE_MS, events_address=events_address,
                records=self._results_of[self.num_envs].records, actions_address=block.ctypes.data,
                count=block.size, continuous=self.continuous,
            ))
        self._fast_send = (bare.mll_vector_env_send, self._bare_handle, int(self.continuous), self._events)
        self._fast_recv = fast_calls.Call(
            function_address=_native.address_of(bare.mll_vector_env_recv), handle=handle,
            timeout_ms=_native.READ_SLICE_MS, events_address=events_address,
            records=self._results_of[self.batch_size].records, with_env_ids=True,
        )
        _OPEN.add(self)
        self._send_of: dict[int, tuple] = {}  # len(env_id) -> send()'s buffers (_send_buffers).

    # ----------------------------------------------------------------- calls into the engine

    def _bytes(self, function, *args) -> bytes:
        """The bytes a `(handle, *args, &data, &size)` call of the library returns."""
        data, size = ctypes.c_void_p(), ctypes.c_size_t()
        self._check(function(self._live(), *args, ctypes.byref(data), ctypes.byref(size)))
        return ctypes.string_at(data, size.value)

    def _live(self) -> int:
        """The handle; FAILED_PRECONDITION once closed, or in a forked child (gRPC C++ does not
        survive a fork)."""
        check_process(self._pid, "this vector env's streams")
        if not self._finalizer.alive:
            raise MLLError(grpc.StatusCode.FAILED_PRECONDITION, "this vector env is closed")
        return self._handle

    def _error(self, code: int) -> MLLError:
        """The MLLError of a failed call; UNAVAILABLE from the transport (the server not reached)
        names the server it concerns, as the AEC and parallel envs' errors do."""
        message = self._lib.mll_vector_env_message(self._handle).decode(errors="replace")
        context = ""
        if not message.startswith(("mll_server ", "embedded mll_server ")):
            named = [server for server in self._descriptions if server in message]
            if len(named) == 1 or len(self._descriptions) == 1:
                context = self._descriptions[(named or list(self._descriptions))[0]]
        return from_call_status(code, message, context)

    def _check(self, code: int) -> None:
        """Logs the engine's failover events, then raises the call's error if it failed."""
        events = self._lib.mll_vector_env_take_events(self._handle) if self._events.value else None
        if events:
            for line in events.decode(errors="replace").splitlines():
                _LOG.warning("%s", line)
        if code:
            raise self._error(code)

    def _wait(self, function) -> None:
        """Calls a waiting function of the library in slices of READ_SLICE_MS until it is done, so
        that Ctrl-C (KeyboardInterrupt) and other signals are handled while a server is slow
        (an interrupted wait loses nothing: calling again goes on waiting)."""
        handle = self._live()
        code = _native.PENDING
        while code == _native.PENDING:
            code = function(handle, _native.READ_SLICE_MS)
        self._check(code)

    def _put_actions(self, actions, rows: int) -> tuple[int, int]:
        """`actions` (a block of `rows` envs' actions) put into the adapter's buffer for `rows`
        rows (_fill): that buffer's address and item count."""
        entry = self._action_blocks.get(rows)
        if entry is None:
            block = np.empty((rows,) + self._action_shape, self._action_dtype)
            entry = self._action_blocks[rows] = (block, block.ctypes.data, block.size)
        _fill(entry[0], actions, self.continuous)
        return entry[1:]

    # ----------------------------------------------------------------- the synchronous API

    def reset(self, seed: int | None = None, options: dict | None = None):
        self._finish_interrupted()
        seed = seed_value(seed)
        self._check(self._lib.mll_vector_env_reset(self._live(), seed is not None, seed or 0))
        observations, *_, infos = self._results_of[self.num_envs].arrays(False)
        return observations, infos

    def step(self, actions, env_id=None):
        """step(actions) steps every env (batch_size == num_envs: the synchronous API). With the
        async API, step(actions, env_id) is send(actions, env_id) then recv(); env_id None means
        every env."""
        fast = self._fast
        if fast is not None and env_id is None and not self._interrupted:
            # One call into the library: the step sent, waited for and its results written in place
            # (the fewest Python operations: this path is most of a trainer's client CPU).
            block, call = fast
            _fill(block, actions, self.continuous)
            done = call()
            if type(done) is tuple:
                return done
            if done == _native.PENDING:  # A slow server: wait on in slices, as step_wait.
                try:
                    self._wait(self._lib.mll_vector_env_step_wait)
                except BaseException as error:
                    # E.g. Ctrl-C while a server is slow: this step's results are the caller's no more.
                    self._interrupted = not isinstance(error, MLLError)
                    raise
            else:
                self._check(done)
            return self._results_of[self.num_envs].arrays(False)
        self._finish_interrupted()
        if env_id is None and self.batch_size == self.num_envs:  # Closed, or in a forked child: raises.
            self._live()
        self.send(actions, np.arange(self.num_envs) if env_id is None else env_id)
        return self.recv()

    def _finish_interrupted(self) -> None:
        """Waits for the step an interrupted step() left in flight, and drops its results (or its
        error: the step is lost), so that the envs can step again."""
        if self._interrupted:
            self._interrupted = False
            try:
                self._wait(self._lib.mll_vector_env_step_wait)
            except MLLError:
                pass

    def step_async(self, actions) -> None:
        """Sends step(actions) and returns at once; step_wait() returns its results. Between the
        two the caller is free to compute (e.g. a learning step) while the servers step."""
        self._finish_interrupted()
        handle = self._live()
        address, count = self._put_actions(actions, self.num_envs)
        self._check(self._lib.mll_vector_env_step_async(handle, address, count, self.continuous))

    def step_wait(self):
        """The results of the step sent by step_async, as step() returns them."""
        self._wait(self._lib.mll_vector_env_step_wait)
        return self._results_of[self.num_envs].arrays(False)

    # ----------------------------------------------------------------- EnvPool's async API

    def async_reset(self, seed: int | None = None) -> None:
        """Resets every env (seed s gives env i the seed s + i, as reset) and makes their first
        observations the results of the next recv() calls, batch_size envs each."""
        self._finish_interrupted()
        seed = seed_value(seed)
        self._check(self._lib.mll_vector_env_async_reset(self._live(), seed is not None, seed or 0))

    def send(self, actions, env_id) -> None:
        """Sends one step of the envs `env_id` (distinct indices in 0..num_envs-1, none with a
        step in flight) with `actions` (int (len(env_id), n_landers) or, continuous, float
        (len(env_id), n_landers, 2)) and returns at once: one packed StepBatch per server
        concerned, pipelined on its Session stream behind the requests already in flight."""
        if self._interrupted:
            self._finish_interrupted()
        fast = self._fast_send
        if fast is None:
            self._live()  # Closed, or in a forked child: raises.
        # An integer array is checked by the library (range, repeats, in flight); anything else here.
        if not (type(env_id) is np.ndarray and env_id.ndim == 1 and 0 < env_id.size <= self.num_envs
                and env_id.dtype.kind in "iu"):
            env_id = self._env_ids(env_id)
        call, handle, continuous, events = fast
        ids, ids_address, ids_count, block, address, count = self._send_of.get(env_id.size) or self._send_buffers(
            env_id.size
        )
        ids[...] = env_id
        _fill(block, actions, self.continuous)
        code = call(handle, address, count, continuous, ids_address, ids_count)
        if code == grpc.StatusCode.INVALID_ARGUMENT.value[0]:
            self._env_ids(env_id)  # A bad env_id in Python's words (as a list's would be).
        if code or events.value:
            self._check(code)

    def _env_ids(self, env_id) -> np.ndarray:
        """`env_id` as an int64 array after checking it names distinct envs; INVALID_ARGUMENT
        saying what is wrong otherwise."""
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
        return ids.astype(np.int64)  # In range: exact.

    def _send_buffers(self, rows: int) -> tuple:
        """send()'s buffers for `rows` envs, made once: the env indices (int64) and the actions,
        each with its address and item count as ctypes values."""
        ids = np.zeros(rows, np.int64)
        block = np.zeros((rows,) + self._action_shape, self._action_dtype)
        entry = self._send_of[rows] = (
            ids, ctypes.c_void_p(ids.ctypes.data), ctypes.c_size_t(rows),
            block, ctypes.c_void_p(block.ctypes.data), ctypes.c_size_t(block.size),
        )
        return entry

    def recv(self):
        """The results of the first batch_size envs whose steps are done (in the order their
        answers came), as step() returns them, with infos["env_id"] (int64, (batch_size,))
        naming the envs of each row. Waits for answers as needed; FAILED_PRECONDITION when fewer
        than batch_size envs have a step in flight."""
        call = self._fast_recv
        if call is None:
            self._live()  # Closed, or in a forked child: raises.
        done = call()
        if type(done) is tuple:
            return done
        if done == _native.PENDING:  # Nothing due yet: wait on in slices.
            self._wait(self._lib.mll_vector_env_recv)
        else:
            self._check(done)
        return self._results_of[self.batch_size].arrays(True)

    # ----------------------------------------------------------------- env snapshot

    def env_snapshot(self, index: int) -> bytes:
        """Env `index`'s snapshot: bytes that recreate it at this point to the same bits on any
        server of the same release (restore_env, parallel_env's restore). FAILED_PRECONDITION
        when its record cannot (see docs/python.md, "Failover and snapshots")."""
        self._finish_interrupted()
        return self._bytes(self._lib.mll_vector_env_snapshot, self._env_index(index))

    def restore_env(self, index: int, snapshot: bytes) -> np.ndarray:
        """Puts env `index` at the point `snapshot` (env_snapshot, parallel_env's snapshot)
        describes: a new env on the same server replays it, checked to the bits, then replaces the
        old one. Returns its observations (n_landers, 12). INVALID_ARGUMENT for a damaged snapshot
        or one of an env with other options; the env is untouched on any error."""
        self._finish_interrupted()
        index = self._env_index(index)
        if not isinstance(snapshot, (bytes, bytearray, memoryview)):
            raise invalid_argument(f"snapshot is a {type(snapshot).__name__}; expected the bytes of env.snapshot()")
        data = bytes(snapshot)
        observations = np.empty((self.n_landers, self._observation_width), np.float32)
        self._check(
            self._lib.mll_vector_env_restore(self._live(), index, data, len(data), observations.ctypes.data)
        )
        return observations

    def _env_index(self, index) -> int:
        if isinstance(index, (bool, np.bool_)) or not isinstance(index, (int, np.integer)) or not (
            0 <= index < self.num_envs
        ):
            raise invalid_argument(f"env index is {index!r}; allowed: 0..{self.num_envs - 1}")
        return int(index)

    # ----------------------------------------------------------------- what it is

    @property
    def failover(self) -> bool:
        """Whether failover is on."""
        return bool(self._lib.mll_vector_env_failover(self._live()))

    @property
    def failovers(self) -> int:
        """Failover events so far."""
        return int(self._lib.mll_vector_env_failovers(self._live()))

    @property
    def rebalances(self) -> int:
        """Rebalancing events so far: envs moved onto a server that joined a host name of
        `address` (docs/python.md, "Elastic fleets")."""
        return int(self._lib.mll_vector_env_rebalances(self._live()))

    @property
    def transport(self) -> str:
        """The transport in use: "shared_memory" when every server's stream passes its messages
        through shared memory, else "native"."""
        if self._finalizer.alive:
            self._transport = self._lib.mll_vector_env_transport(self._live()).decode()
            self._check(0)
        return self._transport

    def __reduce__(self):
        """Pickles as its arguments (num_envs, options, address, TLS/token settings), never a
        connection or stream: unpickling creates `num_envs` new environments on the same servers
        (address=None: on the unpickling process's embedded server)."""
        return rebuild, (type(self), self._init_kwargs)

    @property
    def address(self) -> str:
        """The servers' addresses, comma-separated (a valid `address=` for another client)."""
        return ",".join(self.addresses)

    @property
    def addresses(self) -> list[str]:
        """The address of each server the vector env knows (those of `address=`, a name's as it
        resolved, and those that joined a name since), in server order; `env_addresses` says
        which hold environments."""
        handle = self._live()
        return [
            self._lib.mll_vector_env_server_address(handle, server).decode()
            for server in range(self._lib.mll_vector_env_server_count(handle))
        ]

    @property
    def server_info(self) -> ServerInfo:
        """GetServerInfo's answer of the (first) server: release, wire protocol version,
        capabilities and limits; `server_infos` has every server's."""
        return self.server_infos[0]

    @property
    def server_infos(self) -> list[ServerInfo]:
        """GetServerInfo's answer of each server of `addresses`, in that order:
        release, wire protocol version, capabilities and limits."""
        count = self._lib.mll_vector_env_server_count(self._live())
        return [
            ServerInfo.from_proto(pb.ServerInfo.FromString(self._bytes(self._lib.mll_vector_env_server_info, server)))
            for server in range(count)
        ]

    @property
    def names(self) -> list[str]:
        """The server-side resource names, `envs/{id}`, in env order."""
        handle = self._live()
        return [self._lib.mll_vector_env_name(handle, index).decode() for index in range(self.num_envs)]

    @property
    def env_addresses(self) -> list[str]:
        """The address of the server of each environment, in env order (as placed by load,
        until failover or rebalancing moves it)."""
        handle = self._live()
        return [self._lib.mll_vector_env_env_address(handle, index).decode() for index in range(self.num_envs)]

    def close(self) -> None:
        """Deletes the environments on their servers and closes the streams. Idempotent."""
        self._fast = self._fast_send = self._fast_recv = None
        self._finalizer()

    def __enter__(self) -> "VectorEnv":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
