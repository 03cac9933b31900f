"""Python client of the Multi Lunar Lander server: PettingZoo AEC and parallel environments and
a batched vector environment, each a thin client of an `mll_server`.

    import multi_lunar_lander as mll
    env = mll.env(n_landers=3)                  # AEC; an embedded server is started
    penv = mll.parallel_env(address="127.0.0.1:50051", continuous=True)
    venv = mll.vector_env(64, n_landers=3)
    genv = mll.gym_vector_env(64, n_landers=3)  # gymnasium.vector.VectorEnv, one lander per row
    sb3env = mll.sb3_vec_env(64, n_landers=3)    # stable_baselines3 VecEnv, one lander per row

Options: the names in CONFIG_OPTIONS (the fields of the wire's EnvConfig, e.g. n_landers,
continuous, enable_wind; an unset one takes the server's default); plus address= and
render_mode= (None, "rgb_array", "human"; not for vector_env).

address=None (the default) uses this process's embedded server: one `mll_server` child on a
free loopback port (binary from $MLL_SERVER_BIN, else PATH, else the repository's
build/server/service/mll_server), shared by all environments of the process that use it and
stopped when the last of them is closed or garbage-collected, and at interpreter exit.

Several servers (scale-out): address= also takes a sequence of "host:port" strings or one
comma-separated string. An environment lives on exactly one server for its whole life (its
state is there). An entry whose host is a name (a Kubernetes headless Service's) stands for every
address the name resolves to. `env`/`parallel_env` take server_index= (0-based into the servers
the list stands for); without it they go to the least-loaded server (envs hosted against its
--max_envs, then CPU), asked with GetServerInfo. `vector_env(n, address=[...])` places its envs the
same way (and moves them onto servers that join a name) and steps with one StepBatch per server (each on a Session stream kept open to that
server), all in flight at once; results are in env order and are the same bits as on one server
(each env's physics is its own).

TLS and token (servers started with --tls_cert/--tls_key, --auth_token_file):
tls_root_cert= a PEM file's path or PEM bytes (the CA or the self-signed server certificate)
turns on TLS; tls_server_name= overrides the name checked against the server's certificate.
token= is sent as `authorization: Bearer <token>` on every call; token=None (default) takes
$MLL_TOKEN when set and non-empty, token="" sends none. A missing or wrong token raises
MLLError with code UNAUTHENTICATED; another token's envs are NOT_FOUND. The embedded server
(address=None) is plaintext and needs no token.

Versions: `server_info(address)` (and `env.server_info` of every environment) is the server's
release, wire protocol version, capabilities and limits (GetServerInfo). Each connection asks
once and refuses, with FAILED_PRECONDITION naming both versions and what to upgrade, a server of
another protocol major or one lacking a capability the environment needs (docs/server.md,
"Versions and compatibility").

Errors reported by the server raise MLLError (attributes `code`, a grpc.StatusCode, and
`message`, the server's message).
"""

from __future__ import annotations

from ._channel import TOKEN_ENV
from ._errors import MLLError
from ._remote import CONFIG_OPTIONS, OUTCOMES
from ._server import ServerProcess, embedded_server, find_server_binary
from ._server_info import PROTOCOL, ServerInfo, ServerLimits, ServerLoad
from .aec import MultiLunarLanderEnv
from .gym_vector import GymVectorEnv
from .heuristic import heuristic
from .neighbors import neighbor_closeness
from .parallel import MultiLunarLanderParallelEnv
from .vector import VectorEnv

__all__ = [
    "CONFIG_OPTIONS",
    "GymVectorEnv",
    "MLLError",
    "MultiLunarLanderEnv",
    "MultiLunarLanderParallelEnv",
    "OUTCOMES",
    "PROTOCOL",
    "TOKEN_ENV",
    "ServerInfo",
    "ServerLimits",
    "ServerLoad",
    "ServerProcess",
    "VectorEnv",
    "embedded_server",
    "env",
    "find_server_binary",
    "gym_vector_env",
    "heuristic",
    "neighbor_closeness",
    "parallel_env",
    "raw_env",
    "sb3_vec_env",
    "server_info",
    "vector_env",
]


def env(address=None, render_mode: str | None = None, **options) -> MultiLunarLanderEnv:
    """The AEC environment (pettingzoo.AECEnv)."""
    return MultiLunarLanderEnv(address=address, render_mode=render_mode, **options)


raw_env = env  # PettingZoo's naming; the env has no wrappers to strip.


def parallel_env(address=None, render_mode: str | None = None, **options) -> MultiLunarLanderParallelEnv:
    """The parallel environment (pettingzoo.ParallelEnv)."""
    return MultiLunarLanderParallelEnv(address=address, render_mode=render_mode, **options)


def vector_env(num_envs: int, address=None, **options) -> VectorEnv:
    """`num_envs` environments stepped with one StepBatch per server per step by the C++ client's
    engine in the native library, over `transport=` "auto" (the default), "shared_memory" or
    "native" (see VectorEnv)."""
    return VectorEnv(num_envs, address=address, **options)


def gym_vector_env(num_envs: int, address=None, **options) -> GymVectorEnv:
    """`num_envs` environments as a gymnasium.vector.VectorEnv with one sub-environment per
    lander (num_envs x n_landers of them; parameter sharing), on vector_env's batched step
    (see GymVectorEnv)."""
    return GymVectorEnv(num_envs, address=address, **options)


def sb3_vec_env(num_envs: int, address=None, **options):
    """`num_envs` environments as a Stable-Baselines3 VecEnv with one environment per lander
    (num_envs x n_landers; parameter sharing), on vector_env's batched step (see
    multi_lunar_lander.sb3.SB3VecEnv). Needs stable-baselines3 (`multi_lunar_lander[sb3]`)."""
    try:
        from .sb3 import SB3VecEnv
    except ImportError as error:
        raise ImportError(
            f"sb3_vec_env needs stable-baselines3 ({error}); install it with "
            "`pip install 'stable-baselines3>=2.4.1'` (the package's `sb3` extra)"
        ) from error
    return SB3VecEnv(num_envs, address=address, **options)


def server_info(address=None, *, tls_root_cert=None, tls_server_name=None, token=None) -> ServerInfo:
    """The release, wire protocol version, capabilities and limits of the server at `address`
    ("host:port"; None: this process's embedded server), with the TLS and token options of
    parallel_env. Works with any server, compatible or not (a server from before GetServerInfo
    shows as protocol (1, 0)); raises MLLError when the server cannot be reached or refuses the
    token."""
    from ._channel import Security, parse_addresses
    from ._errors import invalid_argument
    from ._remote import Connection

    addresses = parse_addresses(address)
    if len(addresses) > 1:
        raise invalid_argument(
            f"address is {address!r}, {len(addresses)} servers; server_info takes one (ask each in turn)"
        )
    connection = Connection(addresses[0] if addresses else None, Security.from_options(tls_root_cert, tls_server_name, token))
    try:
        return connection.server_info
    finally:
        connection.close()
