"""What a server is and offers (the GetServerInfo RPC), and whether this client can use it.

Each Connection asks once, on first need, and keeps the answer. A server that answers
UNIMPLEMENTED is a release from before GetServerInfo: it is taken as protocol v1.0, whose
capabilities are unknown, and the client falls back to what it did before (it tries a feature
and reports the server's refusal). Policy: docs/server.md, "Versions and compatibility"."""

from __future__ import annotations

import dataclasses
import importlib.metadata
from typing import Any, Iterable, Sequence

import grpc

from ._errors import MLLError

# The wire protocol this client speaks: package mll.v1, up to minor 3 (1: GetServerInfo; 2:
# PackedSteps.handle; 3: ServerInfo.load).
PROTOCOL = (1, 3)


def client_version() -> str:
    """This package's release, e.g. "0.1.0" (the project's version)."""
    try:
        return importlib.metadata.version("multi_lunar_lander")
    except importlib.metadata.PackageNotFoundError:  # pragma: no cover - imported from a bare tree.
        return "unknown"


@dataclasses.dataclass(frozen=True)
class ServerLimits:
    """The limits a server enforces, from its flags (proto ServerLimits); 0 where unknown."""

    max_envs: int = 0  # --max_envs: environments hosted at once, all callers together.
    max_envs_per_token: int = 0  # Effective --max_envs_per_token; 0: unlimited (no tokens).
    max_message_bytes: int = 0  # --max_message_mb in bytes.
    idle_timeout_s: float = 0.0  # --idle_timeout_s.
    max_landers: int = 0  # Largest n_landers.
    threads: int = 0  # --threads stepping a StepBatch.
    shared_memory_sessions: int = 0  # --shared_memory_sessions; 0: none.


_LIMIT_FIELDS = dataclasses.fields(ServerLimits)


@dataclasses.dataclass(frozen=True)
class ServerLoad:
    """What a server carried when it answered (proto ServerLoad; capability "server_load"); all 0
    from a server that does not report it."""

    envs_hosted: int = 0  # Environments hosted, all callers together (bound: limits.max_envs).
    cpu_cores: float = 0.0  # CPU the server process used over the last 10 s, in cores.
    cores_available: float = 0.0  # Cores it may use: its CPU affinity, or its cgroup quota when lower.
    agent_steps_per_s: float = 0.0  # Agent-steps per second over the same 10 s.


_LOAD_FIELDS = dataclasses.fields(ServerLoad)


@dataclasses.dataclass(frozen=True)
class ServerInfo:
    """A server's release, wire protocol version, capabilities and limits (GetServerInfo).

    server_version: the mll_server release, e.g. "0.1.0"; "" for a server that predates
      GetServerInfo.
    protocol: (major, minor) of the wire protocol, e.g. (1, 1); (1, 0) for a server that predates
      GetServerInfo (its capabilities are then unknown and `capabilities` is empty).
    capabilities: the optional features it offers, e.g. "packed_step_batch", "auto_reset",
      "keep_alive", "shared_memory_sessions" (absent when run with --shared_memory_sessions=0).
    limits: ServerLimits.
    load: ServerLoad at the time of the answer ("server_load"; None gives zeros); not compared by ==, which tells
      servers apart by what they are, not by what they carry at a moment.
    """

    server_version: str
    protocol: tuple[int, int]
    capabilities: frozenset[str]
    limits: ServerLimits
    load: ServerLoad = dataclasses.field(default=None, compare=False)  # type: ignore[assignment]

    def __post_init__(self):
        if self.load is None:  # Not reported: zeros.
            object.__setattr__(self, "load", ServerLoad())

    @classmethod
    def from_proto(cls, message) -> "ServerInfo":
        limits = message.limits
        return cls(
            server_version=message.server_version,
            protocol=(int(message.protocol_major), int(message.protocol_minor)),
            capabilities=frozenset(message.capabilities),
            limits=ServerLimits(**{field.name: getattr(limits, field.name) for field in _LIMIT_FIELDS}),
            load=ServerLoad(**{field.name: getattr(message.load, field.name) for field in _LOAD_FIELDS}),
        )

    @classmethod
    def predating(cls) -> "ServerInfo":
        """What a server from before GetServerInfo is taken for: protocol v1.0, nothing known."""
        return cls(server_version="", protocol=(1, 0), capabilities=frozenset(), limits=ServerLimits())

    @property
    def lists_capabilities(self) -> bool:
        """Whether `capabilities` is the server's own list (protocol v1.1 and later)."""
        return self.protocol >= (1, 1)

    def lacks(self, capability: str) -> bool:
        """True when the server says it does not offer `capability`; False when it does, or when
        it predates GetServerInfo (unknown: the client tries, as before)."""
        return self.lists_capabilities and capability not in self.capabilities

    def as_dict(self) -> dict[str, Any]:
        """Plain types, for JSON and logs (capabilities as a sorted list)."""
        return {
            "server_version": self.server_version,
            "protocol": list(self.protocol),
            "capabilities": sorted(self.capabilities),
            "limits": dataclasses.asdict(self.limits),
            "load": dataclasses.asdict(self.load),
        }


def least_loaded(infos: Sequence[ServerInfo | None]) -> int | None:
    """The index of the server a new environment goes to, by what the servers report (None: one
    that did not answer): among those with room (envs_hosted below limits.max_envs, or no bound
    known), the lowest fill once it takes the env, (envs_hosted + 1) / max_envs (a bound of 0,
    unknown, counts as the largest known one); ties to the lower CPU use, cpu_cores /
    cores_available; then the lower index. None when no server has room. The one placement rule
    of both clients (docs/design.md, "Placement"; the C++ engine's PlanPlacement places a batch
    of envs one by one by it)."""
    known = [info.limits.max_envs for info in infos if info is not None and info.limits.max_envs > 0]
    largest = max(known, default=1)
    best, best_key = None, None
    for index, info in enumerate(infos):
        if info is None:
            continue
        hosted, bound = info.load.envs_hosted, info.limits.max_envs
        if bound > 0 and hosted >= bound:
            continue
        cores = info.load.cores_available
        key = ((hosted + 1) / (bound or largest), info.load.cpu_cores / cores if cores > 0 else 0.0, index)
        if best_key is None or key < best_key:
            best, best_key = index, key
    return best


def _describe_server(info: ServerInfo, address: str) -> str:
    release = info.server_version or "(a release without GetServerInfo)"
    return f"mll_server {release} at {address} (protocol v{info.protocol[0]}.{info.protocol[1]})"


def _describe_client() -> str:
    return f"this client (multi_lunar_lander {client_version()}, protocol v{PROTOCOL[0]}.{PROTOCOL[1]})"


def check_compatible(info: ServerInfo, address: str, needs: Iterable[str] = (), feature: str = "") -> None:
    """Raises MLLError FAILED_PRECONDITION, naming both versions and what to upgrade, unless this
    client can use the server `info` describes: its protocol major must be this client's, and,
    when it lists its capabilities, it must offer each of `needs` (which `feature` needs)."""
    major = info.protocol[0]
    if major != PROTOCOL[0]:
        newer = major > PROTOCOL[0]
        raise MLLError(
            grpc.StatusCode.FAILED_PRECONDITION,
            f"{_describe_server(info, address)} speaks {'a newer' if newer else 'an older'} wire protocol "
            f"than {_describe_client()}: "
            + (
                f"upgrade the client to a release of protocol v{major} (pip install ./client_py from a clone of "
                f"that release; the package is not on a package index), "
                f"or use a server of protocol v{PROTOCOL[0]}"
                if newer
                else f"upgrade the server to a release of protocol v{PROTOCOL[0]} "
                f"(e.g. mll_server {client_version()}), or use a client of protocol v{major}"
            ),
        )
    missing = sorted(capability for capability in needs if info.lacks(capability))
    if missing:
        raise MLLError(
            grpc.StatusCode.FAILED_PRECONDITION,
            f"{_describe_server(info, address)} lacks capability {', '.join(map(repr, missing))}, which "
            f"{feature or 'this call'} of {_describe_client()} needs (the server offers: "
            f"{', '.join(sorted(info.capabilities)) or 'none'}); upgrade the server (e.g. to mll_server "
            f"{client_version()}), or enable the capability if its flags turned it off",
        )


def fetch(connection, timeout: float | None = 30.0) -> ServerInfo:
    """Asks `connection`'s server (GetServerInfo); UNIMPLEMENTED gives ServerInfo.predating()."""
    from ._stubs import pb

    try:
        message = connection.call("GetServerInfo", pb.GetServerInfoRequest(), timeout=timeout)
    except MLLError as error:
        if error.code == grpc.StatusCode.UNIMPLEMENTED:
            return ServerInfo.predating()
        raise
    return ServerInfo.from_proto(message)


def fetch_all(connections: Sequence, timeout: float) -> list[ServerInfo | MLLError]:
    """GetServerInfo of every connection at once (deadline `timeout`): each one's answer, or its
    error (UNIMPLEMENTED gives ServerInfo.predating(), as fetch)."""
    from ._stubs import pb

    waits = [connection.future("GetServerInfo", pb.GetServerInfoRequest(), timeout) for connection in connections]
    answers: list[ServerInfo | MLLError] = []
    for wait in waits:
        try:
            answers.append(ServerInfo.from_proto(wait()))
        except MLLError as error:
            answers.append(ServerInfo.predating() if error.code == grpc.StatusCode.UNIMPLEMENTED else error)
    return answers
