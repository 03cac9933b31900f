"""An environment's record: what recreates it to the same bits on any server of the same release,
and the failover that uses it.

An env is deterministic to the bit: it is fully described by its config, the seed of its last
seeded reset and every operation since (steps with their actions, auto-reset steps, unseeded
resets, which continue the generator's stream). The AEC and parallel envs keep this record to fail
over (an env lost with its server is recreated elsewhere and replayed) and to give `snapshot()` /
restore; vector envs keep theirs in the C++ engine (client_cpp/src/env_record.cc), in the same
snapshot format.

Operations (one byte each) and their action row (the wire bytes of the step's actions: int32
[n_landers] or float32 [n_landers, 2]; zeros where ignored):
  STEP: a step with these actions; AUTO_RESET: a step that started a new episode (actions
  ignored; replayed as a step on an auto-reset env, as an unseeded ResetEnv on another);
  RESET: an unseeded ResetEnv (the generator's stream continues).
  The AEC env's turns (StepAgent), each acting for the agent_selection of the answer before it
  (so the record needs no agent index: replay reads it from that answer):
  AGENT_STEP: the action at the acting agent's slot of the row; DEAD_STEP: a dead step (no
  action; the row is zeros).
A record holds StepEnv operations (STEP, AUTO_RESET) or StepAgent ones, never both: the server
refuses to mix the two step APIs within an episode, so each env kind restores only snapshots of
its own operations (and RESET).

A record holds at most MAX_RECORD_STEPS operations since its seeded reset; past it the env
cannot be recreated (failover raises FAILED_PRECONDITION naming the env) until its next seeded
reset starts a new record.

Snapshot format (env.snapshot(), all integers little-endian): b"MLLS", u16 format version (1: operations
STEP, AUTO_RESET, RESET; 2: the same layout, AGENT_STEP and DEAD_STEP allowed too. A snapshot is
written with the lowest version that holds its operations, so the snapshots of vector and parallel
envs stay readable by version-1 clients, which refuse an AEC env's by its version), u16 and
u16 the wire protocol (major, minor) of the server that ran the env, u16 length + the server's
release string, u32 length + the EnvConfig message (the server's filled-in config), u64 seed,
u8 action wire dtype, u32 action row bytes, u32 operation count n, n operation bytes, n action
rows, u32 length + the last observations (float32 [n_landers, 12]), u32 CRC-32 of all before.
"""

from __future__ import annotations

import logging
import struct
import time
import zlib
from typing import Iterable, Sequence

import grpc
import numpy as np

from . import _arrays
from ._channel import is_name
from ._errors import MLLError, invalid_argument
from ._remote import Connection, encode_agent_action
from ._stubs import pb

STEP, AUTO_RESET, RESET, AGENT_STEP, DEAD_STEP = 1, 2, 3, 4, 5
# The operations each env kind records and restores: vector and parallel envs step with StepEnv
# (StepBatch), the AEC env with StepAgent.
STEP_OPERATIONS = (STEP, AUTO_RESET, RESET)
AEC_OPERATIONS = (AGENT_STEP, DEAD_STEP, RESET)

# Operations kept per env since its seeded reset (see the module docstring).
MAX_RECORD_STEPS = 100_000

MAGIC = b"MLLS"
# The operations each format version may hold (see the module docstring); the newest version.
VERSION_OPERATIONS = {1: STEP_OPERATIONS, 2: STEP_OPERATIONS + (AGENT_STEP, DEAD_STEP)}
FORMAT_VERSION = max(VERSION_OPERATIONS)

_LOG = logging.getLogger("multi_lunar_lander")


class EnvRecord:
    """One env's record: seed (None: never seeded, so not recoverable), operations and their
    action rows, and the observations the client last saw (bytes)."""

    __slots__ = ("seed", "kinds", "actions", "last_observations")

    def __init__(self, seed: int | None, kinds: np.ndarray, actions: np.ndarray, last_observations: bytes):
        self.seed, self.kinds, self.actions, self.last_observations = seed, kinds, actions, last_observations


class GrowingLog:
    """Operations of one or more envs that act together: row r holds each env's operation kind
    (0: none) and action bytes. Grows by doubling; past MAX_RECORD_STEPS rows it stops growing
    and is `full` (the records are incomplete)."""

    def __init__(self, num_envs: int, row_bytes: int):
        self.num_envs, self.row_bytes = num_envs, row_bytes
        self.kinds = np.zeros((64, num_envs), np.uint8)
        self.actions = np.zeros((64, num_envs, row_bytes), np.uint8)
        self.length = 0
        self.full = False

    def clear(self) -> None:
        self.length = 0
        self.full = False

    def append(self, kinds, actions) -> None:
        """One row: kinds (num_envs,) uint8, actions (num_envs, row_bytes) uint8 or bytes."""
        if self.length >= MAX_RECORD_STEPS:
            self.full = True
            return
        if self.length == self.kinds.shape[0]:  # Doubled, up to MAX_RECORD_STEPS rows.
            capacity = min(2 * self.length, MAX_RECORD_STEPS)
            self.kinds = np.resize(self.kinds, (capacity, self.num_envs))
            self.actions = np.resize(self.actions, (capacity, self.num_envs, self.row_bytes))
        self.kinds[self.length] = kinds
        if isinstance(actions, (bytes, bytearray, memoryview)):
            actions = np.frombuffer(actions, np.uint8).reshape(self.num_envs, self.row_bytes)
        self.actions[self.length] = actions
        self.length += 1

    def of_env(self, env: int, start: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Env `env`'s operations from row `start` on: (kinds, action rows)."""
        kinds = self.kinds[start : self.length, env]
        used = kinds != 0
        return kinds[used].copy(), self.actions[start : self.length, env][used].copy()


def encode_snapshot(
    config: "pb.EnvConfig", protocol: Sequence[int], release: str, record: EnvRecord, dtype: int, row_bytes: int
) -> bytes:
    config_bytes = config.SerializeToString(deterministic=True)
    release_bytes = release.encode("utf-8")[:65535]
    kinds = np.ascontiguousarray(record.kinds, np.uint8)
    version = min(v for v, operations in VERSION_OPERATIONS.items() if np.isin(kinds, operations).all())
    parts = [
        MAGIC,
        struct.pack("<HHHH", version, int(protocol[0]), int(protocol[1]), len(release_bytes)),
        release_bytes,
        struct.pack("<I", len(config_bytes)),
        config_bytes,
        struct.pack("<QBII", record.seed, dtype, row_bytes, kinds.size),
        kinds.tobytes(),
        np.ascontiguousarray(record.actions, np.uint8).tobytes(),
        struct.pack("<I", len(record.last_observations)),
        record.last_observations,
    ]
    body = b"".join(parts)
    return body + struct.pack("<I", zlib.crc32(body))


class DecodedSnapshot:
    __slots__ = ("protocol", "release", "config", "record", "dtype", "row_bytes")


def decode_snapshot(snapshot, operations: Sequence[int] = STEP_OPERATIONS) -> DecodedSnapshot:
    """Parses and checks a snapshot for an env that replays `operations` (STEP_OPERATIONS: vector
    and parallel envs; AEC_OPERATIONS: the AEC env); INVALID_ARGUMENT naming what is wrong."""
    if not isinstance(snapshot, (bytes, bytearray, memoryview)):
        raise invalid_argument(f"snapshot is a {type(snapshot).__name__}; expected the bytes of env.snapshot()")
    data = bytes(snapshot)
    if len(data) < 8 or data[:4] != MAGIC:
        raise invalid_argument("snapshot does not start with b'MLLS': not an env snapshot (or truncated)")
    body, (crc,) = data[:-4], struct.unpack("<I", data[-4:])
    if zlib.crc32(body) != crc:
        raise invalid_argument(
            f"snapshot is damaged: its CRC-32 is {crc:#010x}, its contents' {zlib.crc32(body):#010x}"
        )
    offset = 4

    def take(size: int, what: str) -> bytes:
        nonlocal offset
        if offset + size > len(body):
            raise invalid_argument(f"snapshot is truncated in its {what}")
        chunk = body[offset : offset + size]
        offset += size
        return chunk

    version, major, minor, release_len = struct.unpack("<HHHH", take(8, "header"))
    if version not in VERSION_OPERATIONS:
        raise invalid_argument(
            f"snapshot has format version {version}; this client reads versions 1 to {FORMAT_VERSION} "
            "(upgrade the client)"
        )
    decoded = DecodedSnapshot()
    decoded.protocol = (major, minor)
    decoded.release = take(release_len, "release").decode("utf-8", "replace")
    (config_len,) = struct.unpack("<I", take(4, "config length"))
    decoded.config = pb.EnvConfig()
    try:
        decoded.config.ParseFromString(take(config_len, "config"))
    except Exception as error:  # google.protobuf.message.DecodeError
        raise invalid_argument(f"snapshot's config does not parse: {error}") from None
    seed, dtype, row_bytes, count = struct.unpack("<QBII", take(17, "seed and sizes"))
    if dtype not in (pb.DTYPE_INT32, pb.DTYPE_FLOAT32):
        raise invalid_argument(f"snapshot's action dtype is {dtype}; expected int32 or float32")
    if count > MAX_RECORD_STEPS:
        raise invalid_argument(f"snapshot holds {count} operations; at most {MAX_RECORD_STEPS}")
    kinds = np.frombuffer(take(count, "operations"), np.uint8)
    if not np.isin(kinds, VERSION_OPERATIONS[version]).all():
        raise invalid_argument(f"snapshot holds an operation code unknown to format version {version}")
    if not np.isin(kinds, operations).all():
        raise invalid_argument(
            "snapshot holds steps of the other step API (StepAgent: an AEC env's; StepEnv: a vector or parallel "
            "env's), which this env does not replay"
        )
    actions = np.frombuffer(take(count * row_bytes, "actions"), np.uint8).reshape(count, row_bytes)
    (obs_len,) = struct.unpack("<I", take(4, "observations length"))
    last = take(obs_len, "observations")
    if offset != len(body):
        raise invalid_argument(f"snapshot has {len(body) - offset} bytes after its end")
    decoded.record = EnvRecord(seed, kinds, actions, last)
    decoded.dtype, decoded.row_bytes = dtype, row_bytes
    return decoded


def check_config(snapshot_config: "pb.EnvConfig", config: "pb.EnvConfig", row_bytes: int, dtype: int) -> None:
    """INVALID_ARGUMENT unless the snapshot's env has the options of `config` (render_mode and
    auto_reset aside: they do not change the physics)."""
    mine, theirs = pb.EnvConfig(), pb.EnvConfig()
    mine.CopyFrom(config)
    theirs.CopyFrom(snapshot_config)
    for message in (mine, theirs):
        message.ClearField("render_mode")
        message.ClearField("auto_reset")
    if mine != theirs:
        raise invalid_argument(
            f"snapshot is of an env with other options ({str(theirs).strip() or 'defaults'}) than this one's "
            f"({str(mine).strip() or 'defaults'})".replace("\n", ", ")
        )
    n_landers = int(config.n_landers)
    expected = n_landers * (8 if config.continuous else 4)
    if row_bytes != expected or dtype != (pb.DTYPE_FLOAT32 if config.continuous else pb.DTYPE_INT32):
        raise invalid_argument(f"snapshot's actions are {row_bytes} bytes a step; this env's are {expected}")


def check_restorable(decoded: DecodedSnapshot, config: "pb.EnvConfig", server) -> None:
    """INVALID_ARGUMENT unless `decoded` can be replayed into an env of `config` on the server
    `server` (its ServerInfo): the same options (check_config) and the same wire protocol major
    version (another major may change the physics or the operations). Another release of the same
    major is tried: the replay's bit check then decides (DATA_LOSS)."""
    check_config(decoded.config, config, decoded.row_bytes, decoded.dtype)
    major, minor = decoded.protocol
    if major != server.protocol[0]:
        raise invalid_argument(
            f"snapshot is from a server of wire protocol {major}.{minor} (release {decoded.release or 'unknown'}); "
            f"this server speaks {server.protocol[0]}.{server.protocol[1]} (release {server.server_version}): "
            f"restore it on a server of protocol {major}.x"
        )


def observations_of(response) -> bytes:
    """The observations of a ResetEnv, StepEnv or StepAgent answer (StepAgent's in its AecState,
    the others' in its StepData) as float32 little-endian bytes: a record's last_observations."""
    message = response.aec if isinstance(response, pb.StepAgentResponse) else response.data
    return _arrays.to_numpy(message.observations).astype("<f4").tobytes()


def agent_step_request(kind: int, actions: np.ndarray, agent: int) -> "pb.StepAgentRequest":
    """The StepAgent request (its name to be set) of an AGENT_STEP or DEAD_STEP operation of
    `agent`, with the agent's action at its row of `actions` (int32 [n_landers] or float32
    [n_landers, 2]); the agent is sent for the server to check against agent_selection."""
    request = pb.StepAgentRequest(agent=agent)
    if kind == AGENT_STEP:
        encode_agent_action(actions[agent], actions.dtype == np.float32, f"lander_{agent}", request.action)
    return request


def replay(
    connection,
    config: "pb.EnvConfig",
    records: Sequence[EnvRecord],
    labels: Sequence[str],
    dtype: int,
    action_shape: tuple,
) -> list:
    """Creates one env per record on `connection`'s server (with `config`), replays each
    record's operations (all envs a round at a time, concurrently) and checks each replayed
    observation equals the record's last seen; returns the created Env messages and each env's
    last answer (ResetEnvResponse, StepEnvResponse or StepAgentResponse). On any error the envs
    created here are deleted; DATA_LOSS names the env whose bits differ."""
    for record, label in zip(records, labels):
        if record.seed is None:
            raise MLLError(
                grpc.StatusCode.FAILED_PRECONDITION,
                f"{label} cannot be recreated: it was never reset with a known seed, or its record passed "
                f"{MAX_RECORD_STEPS} operations since its last seeded reset (reset it with a seed)",
            )
    waits = [connection.future("CreateEnv", pb.CreateEnvRequest(config=config)) for _ in records]
    envs, failure = [], None
    for wait in waits:
        try:
            envs.append(wait())
        except MLLError as error:
            failure = failure or error
    try:
        if failure is not None:
            raise failure
        auto_reset = bool(config.auto_reset)
        element = "<f4" if dtype == pb.DTYPE_FLOAT32 else "<i4"
        answers = [
            wait()
            for wait in [
                connection.future("ResetEnv", pb.ResetEnvRequest(name=env.name, seed=record.seed))
                for env, record in zip(envs, records)
            ]
        ]
        rounds = max((record.kinds.size for record in records), default=0)
        for t in range(rounds):
            waits = []
            for index, (env, record) in enumerate(zip(envs, records)):
                if t >= record.kinds.size:
                    continue
                kind = record.kinds[t]
                if kind == RESET or (kind == AUTO_RESET and not auto_reset):
                    waits.append((index, connection.future("ResetEnv", pb.ResetEnvRequest(name=env.name))))
                elif kind in (AGENT_STEP, DEAD_STEP):
                    actions = np.frombuffer(record.actions[t].tobytes(), element).reshape(action_shape)
                    request = agent_step_request(kind, actions, answers[index].aec.agent_selection)
                    request.name = env.name
                    waits.append((index, connection.future("StepAgent", request)))
                else:
                    request = pb.StepEnvRequest(name=env.name)
                    request.actions.dtype = dtype
                    request.actions.shape.extend(action_shape)
                    request.actions.data = record.actions[t].tobytes()
                    waits.append((index, connection.future("StepEnv", request)))
            for index, wait in waits:
                answers[index] = wait()
        for record, label, answer in zip(records, labels, answers):
            if observations_of(answer) != record.last_observations:
                raise MLLError(
                    grpc.StatusCode.DATA_LOSS,
                    f"{label}: replaying its {record.kinds.size} operations since seed {record.seed} on "
                    f"{connection.address} gave other observations than the last ones seen; the server's "
                    "release (physics) differs from the one that ran it, or the record is wrong",
                )
    except BaseException:
        for env in envs:
            delete_quietly(connection, env.name)
        raise
    return envs, answers


def delete_quietly(connection, name: str) -> None:
    """Deletes env `name` on `connection`'s server, ignoring errors: the env, or the server, may
    be gone already; either way the server holds it no more."""
    try:
        connection.call("DeleteEnv", pb.DeleteEnvRequest(name=name), timeout=2.0)
    except MLLError:
        pass


# ----------------------------------------------------------------- failover


def failover_on(failover: bool | None, addresses: Sequence[str]) -> bool:
    """The `failover=` argument resolved: None is on with several servers, a host name (which
    stands for every address it resolves to, now and later) or the embedded one (no address),
    off with one IP address."""
    if failover is not None:
        return bool(failover)
    return len(addresses) != 1 or is_name(addresses[0])


def loses_server(error: MLLError) -> bool:
    """Whether `error` says the server is lost: unreachable (UNAVAILABLE, a draining server's
    "draining: ..." included) or stalled (it missed the call's deadline, step_timeout_s:
    DEADLINE_EXCEEDED; gRPC cancelled the call, so a late answer is never taken)."""
    return error.code in (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.DEADLINE_EXCEEDED)


def loses_env(error: MLLError, name: str) -> bool:
    """Whether `error`, of a call on env `name`, is one failover handles: the server lost
    (loses_server), or the env gone from a server that answers (NOT_FOUND naming it)."""
    return loses_server(error) or (error.code == grpc.StatusCode.NOT_FOUND and name in error.message)


def gave_up(tries: int) -> MLLError:
    """The error of a call still failing over after `tries` tries (each server found down)."""
    return MLLError(grpc.StatusCode.UNAVAILABLE, f"failover gave up after {tries} tries")


def usable_servers(connections: list[Connection], down: set[int], skip: set[int] = frozenset()) -> list[int]:
    """Indices of `connections` a failover may move envs to: those not in `down` (found
    unreachable or draining), and those in `down` whose server answers GetServerInfo again on a
    renewed connection (Connection.renewed: a host name resolved again, the embedded server
    restarted if it died), which then replaces the old one in `connections` and leaves `down`. So
    a server replaced at the same address (a StatefulSet pod in a rolling update) takes envs again
    at the next failover, rather than only after every other server is lost. Those in `skip` (in
    `down` too: servers that just missed a deadline, whose probe would wait out its own) are not
    probed."""
    for index in sorted(down - set(skip)):
        fresh = connections[index].renewed()
        try:
            fresh.call("GetServerInfo", pb.GetServerInfoRequest(), timeout=2.0)
        except MLLError:  # Still unreachable, or draining (it refuses GetServerInfo).
            fresh.close()
            continue
        connections[index].close()
        connections[index] = fresh
        down.discard(index)
    return [index for index in range(len(connections)) if index not in down]


def log_failover(
    client: str, moved: int, cause: MLLError, targets: Iterable[str], operations: int, began: float, detail: str = ""
) -> None:
    """The one warning of a failover event of `client` (e.g. "MultiLunarLanderEnv"): `moved` envs lost to
    `cause`, recreated on `targets` (addresses) with `operations` replayed since `began`
    (time.monotonic()); `detail` is appended."""
    _LOG.warning(
        "%s failover: %d env(s) lost (%s: %s); recreated on %s and replayed (%d steps) in %.3f s%s",
        client,
        moved,
        cause.code.name,
        cause.message,
        ", ".join(sorted(set(targets))),
        operations,
        time.monotonic() - began,
        detail,
    )
