"""Where a client connects and how: the `address=` forms, TLS and the bearer token, and the one
function that opens a gRPC channel from them (used by every connection and health check).

address= accepts "host:port", a comma-separated string of them, or a sequence of them. An entry
whose host is a name stands for every address the name resolves to (resolve_endpoints): a
Kubernetes headless Service's name is its ready pods.
tls_root_cert= (a PEM file's path, or its bytes) turns TLS on: grpc.secure_channel with those
root certificates; tls_server_name= overrides the name the server's certificate must carry
(for a certificate issued to a name other than the dialled host, e.g. an IP address).
token= is sent as `authorization: Bearer <token>` metadata on every call. Precedence: a
`token=` argument wins; token=None (the default) takes $MLL_TOKEN when set and non-empty;
token="" sends no token even when $MLL_TOKEN is set.
"""

from __future__ import annotations

import dataclasses
import ipaddress
import math
import numbers
import os
import socket
from dataclasses import dataclass, field
from typing import Sequence

import grpc

from ._errors import MLLError, invalid_argument

TOKEN_ENV = "MLL_TOKEN"

# HTTP/2 flow control as the C++ client's and the server's (proto/include/mll/http2_flow_control.h):
# BDP probing on (gRPC's default, on purpose) and an 8 MiB stream lookahead, so that many large
# requests in flight over a link with latency do not wait for window updates.
CHANNEL_OPTIONS = (
    ("grpc.max_receive_message_length", 64 * 1024 * 1024),
    ("grpc.max_send_message_length", 64 * 1024 * 1024),
    ("grpc.http2.bdp_probe", 1),
    ("grpc.http2.lookahead_bytes", 8 * 1024 * 1024),
    # Each channel its own subchannels: a new connection to a server found down (failover's
    # probe) must not inherit the reconnection backoff of the old channel's subchannel.
    ("grpc.use_local_subchannel_pool", 1),
    # HTTP/2 keepalive as the C++ client's, which the server's ping policy accepts
    # (proto/include/mll/http2_keepalive.h): a ping every 20 s, idle connections included, and
    # the connection closed when the server does not acknowledge within 10 s.
    ("grpc.keepalive_time_ms", 20000),
    ("grpc.keepalive_timeout_ms", 10000),
    ("grpc.keepalive_permit_without_calls", 1),
    ("grpc.http2.max_pings_without_data", 0),
)

# step_timeout_s's default: how long a server may take to answer one call before it counts as
# stalled (DEADLINE_EXCEEDED; failover moves the env). The C++ client's ClientOptions::step_timeout
# default; far above a loaded server's slowest answers (docs/benchmarks.md, "Step deadline").
DEFAULT_STEP_TIMEOUT_S = 5.0


def seconds_value(name: str, value, default: str, zero: str) -> float:
    """`value` as float when it is a finite number of seconds >= 0; else INVALID_ARGUMENT naming
    argument `name` and what it accepts (None: `default`; 0: `zero`)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value) or value < 0:
        raise invalid_argument(
            f"{name} is {value!r}; expected None (the default, {default}), 0 ({zero}) or a finite number of "
            "seconds > 0"
        )
    return float(value)


def step_timeout_value(step_timeout_s) -> float | None:
    """The deadline in seconds of a `step_timeout_s=` argument: None takes the default, 0 means no
    deadline (returned as None); INVALID_ARGUMENT for anything but a finite number >= 0."""
    if step_timeout_s is None:
        return DEFAULT_STEP_TIMEOUT_S
    return seconds_value("step_timeout_s", step_timeout_s, f"{DEFAULT_STEP_TIMEOUT_S:g} s", "no deadline") or None


def parse_addresses(address: str | Sequence[str] | None) -> tuple[str, ...]:
    """The server addresses of an `address=` argument, in order; () for None (the embedded
    server). An address listed twice gets twice the share of a vector env's environments."""
    if address is None:
        return ()
    if isinstance(address, str):
        parts = address.split(",")
    elif isinstance(address, Sequence) and all(isinstance(part, str) for part in address):
        parts = list(address)
    else:
        raise invalid_argument(
            f"address is {address!r}; expected None, 'host:port', 'host:port,host:port' or a "
            "sequence of 'host:port' strings"
        )
    addresses = tuple(part.strip() for part in parts)
    for part in addresses:
        if not part or any(c.isspace() for c in part):
            raise invalid_argument(
                f"address {address!r} has the entry {part!r}; every entry must be a non-empty "
                "'host:port' without spaces"
            )
    if not addresses:
        raise invalid_argument(f"address is {address!r}; expected at least one 'host:port'")
    return addresses


@dataclass(frozen=True)
class Endpoint:
    """One server an `address=` list stands for: `address` is what the client dials ("ip:port"
    for an address a name resolved to, else the entry as given); `name` the host name it was
    resolved from (None for an IP literal or a gRPC target), which TLS checks the server's
    certificate against."""

    address: str
    name: str | None = None


def _host_and_port(entry: str) -> tuple[str, str] | None:
    """(host, port) of a "host:port" or "[v6]:port" entry whose host is a name to resolve; None
    for an IP literal or a gRPC target with a scheme ("unix:PATH", "dns:...", "ipv4:...")."""
    host, colon, port = entry.rpartition(":")
    if not colon or not port.isdigit():
        return None
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    elif ":" in host:
        return None  # A scheme ("dns:host:50051") or a bare IPv6 address: gRPC's to read.
    try:
        ipaddress.ip_address(host)
        return None
    except ValueError:
        return host, port


def is_name(entry: str) -> bool:
    """Whether the `address=` entry's host is a name (resolve_endpoints expands it)."""
    return _host_and_port(entry) is not None


def resolve_endpoints(addresses: Sequence[str]) -> list[Endpoint]:
    """The servers `addresses` (parse_addresses' entries) stand for, in entry order: an IP literal
    or a gRPC target is itself; a name is every address it resolves to now (getaddrinfo, TCP, IPv4
    and IPv6), sorted. Each address once: the first entry that yields it keeps it. A name that
    resolves to nothing is left out; UNAVAILABLE naming the entries when nothing is left. The C++
    client resolves the same way (client_cpp/src/discovery.h)."""
    endpoints: list[Endpoint] = []
    seen: set[str] = set()
    failures = []
    for entry in addresses:
        parsed = _host_and_port(entry)
        if parsed is None:
            found = [Endpoint(entry)]
        else:
            host, port = parsed
            try:
                infos = socket.getaddrinfo(host, int(port), type=socket.SOCK_STREAM)
            except (OSError, UnicodeError) as error:
                failures.append(f"{entry!r} resolves to no address ({error})")
                continue
            ips = sorted({info[4][0] for info in infos if info[0] in (socket.AF_INET, socket.AF_INET6)})
            found = [Endpoint(f"[{ip}]:{port}" if ":" in ip else f"{ip}:{port}", host) for ip in ips]
        for endpoint in found:
            if endpoint.address not in seen:
                seen.add(endpoint.address)
                endpoints.append(endpoint)
    if not endpoints:
        raise MLLError(
            grpc.StatusCode.UNAVAILABLE,
            f"address {', '.join(addresses)} stands for no server now: {'; '.join(failures)}",
        )
    return endpoints


def _read_root_cert(value) -> bytes:
    if isinstance(value, (bytes, bytearray)):
        pem = bytes(value)
        source = "the given bytes"
    elif isinstance(value, (str, os.PathLike)):
        try:
            with open(value, "rb") as file:
                pem = file.read()
        except OSError as error:
            raise invalid_argument(
                f"tls_root_cert is {os.fspath(value)!r}: cannot read it ({error.strerror}); "
                "expected the path of a PEM file or its bytes"
            ) from None
        source = repr(os.fspath(value))
    else:
        raise invalid_argument(f"tls_root_cert is {value!r}; expected None, a PEM file's path or PEM bytes")
    if b"-----BEGIN CERTIFICATE-----" not in pem:
        raise invalid_argument(f"tls_root_cert {source} holds no PEM certificate ('-----BEGIN CERTIFICATE-----')")
    return pem


def _token_value(token: str | None) -> str | None:
    if token is None:
        token = os.environ.get(TOKEN_ENV) or None
        where = f"${TOKEN_ENV}"
    else:
        where = "token"
    if not isinstance(token, (str, type(None))):
        raise invalid_argument(f"token is a {type(token).__name__}; expected a str or None")
    token = (token or "").strip()  # As the server reads its token file: surrounding whitespace is not part of it.
    if not token:
        return None
    # The server's rule for tokens; the value itself is never echoed.
    if not all("!" <= c <= "~" for c in token):
        raise invalid_argument(
            f"{where} has a character outside printable ASCII or a space (allowed: '!'..'~', "
            f"{len(token)} characters given)"
        )
    return token


@dataclass(frozen=True)
class Security:
    """TLS and token settings of a client; the default is plaintext without a token."""

    root_certificates: bytes | None = None
    server_name: str | None = None
    token: str | None = field(default=None, repr=False)  # Never in logs.

    @classmethod
    def from_options(cls, tls_root_cert=None, tls_server_name: str | None = None, token: str | None = None) -> "Security":
        """Checks and loads the tls_root_cert=, tls_server_name= and token= arguments."""
        if tls_server_name is not None:
            if tls_root_cert is None:
                raise invalid_argument(
                    f"tls_server_name is {tls_server_name!r} but tls_root_cert is None; the name "
                    "override only applies to TLS, which tls_root_cert turns on"
                )
            if not isinstance(tls_server_name, str) or not tls_server_name:
                raise invalid_argument(f"tls_server_name is {tls_server_name!r}; expected a non-empty host name")
        return cls(
            root_certificates=None if tls_root_cert is None else _read_root_cert(tls_root_cert),
            server_name=tls_server_name,
            token=_token_value(token),
        )

    def as_options(self) -> dict:
        """The tls_root_cert=, tls_server_name= and token= arguments that give these settings
        again (what a pickled environment carries): the PEM bytes rather than a file's path (the
        file may not exist where the copy is unpickled), and token="" for none, so the $MLL_TOKEN
        of the unpickling process does not change them."""
        return {
            "tls_root_cert": self.root_certificates,
            "tls_server_name": self.server_name,
            "token": self.token or "",
        }

    @property
    def tls(self) -> bool:
        return self.root_certificates is not None

    @property
    def metadata(self) -> tuple[tuple[str, str], ...] | None:
        """The per-call metadata: the bearer token, if any. Sent on plaintext and TLS channels
        alike, so one code path covers both (gRPC's call credentials refuse plaintext)."""
        return (("authorization", f"Bearer {self.token}"),) if self.token else None

    def for_endpoint(self, endpoint: Endpoint) -> "Security":
        """These settings for a server dialled at an address its name resolved to: with TLS, the
        certificate is checked against that name (unless tls_server_name says otherwise)."""
        if self.tls and endpoint.name and not self.server_name:
            return dataclasses.replace(self, server_name=endpoint.name)
        return self

    def describe(self) -> str:
        """How the client connects, for error messages (never the token itself)."""
        parts = ["TLS" if self.tls else "plaintext"]
        if self.server_name:
            parts.append(f"server name {self.server_name!r}")
        parts.append("with a token" if self.token else "without a token")
        return ", ".join(parts)


def open_channel(address: str, security: Security) -> grpc.Channel:
    """A channel to `address`: TLS with the root certificates when set, else plaintext."""
    # The process id is a channel argument so that a forked child's channels never share a
    # connection (gRPC's subchannel pool is keyed by address and arguments) with its parent's.
    options = [*CHANNEL_OPTIONS, ("mll.client_pid", os.getpid())]
    if not security.tls:
        return grpc.insecure_channel(address, options=options)
    if security.server_name:
        options.append(("grpc.ssl_target_name_override", security.server_name))
    credentials = grpc.ssl_channel_credentials(root_certificates=security.root_certificates)
    return grpc.secure_channel(address, credentials, options=options)
