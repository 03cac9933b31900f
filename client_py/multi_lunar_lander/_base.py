"""The part of the AEC and parallel environments that is not about stepping: creating the
server-side environment, spaces, rendering and deletion."""

from __future__ import annotations

import weakref
from typing import Any, Sequence

import gymnasium
import numpy as np

from . import _arrays, _lease
from ._errors import MLLError
from ._channel import Security, parse_addresses
from ._remote import Connection, config_dict, connect_single, make_config, rebuild, space_from_proto
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
        connection.call("DeleteEnv", pb.DeleteEnvRequest(name=name), timeout=2.0)
    except MLLError:
        pass
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
        **options: Any,
    ):
        """Creates the environment on one server of `address` (see the package docstring for
        address lists, server_index, TLS and token); `options` are the EnvConfig options."""
        super().__init__()  # pettingzoo.AECEnv / ParallelEnv, next in the subclass's MRO.
        security = Security.from_options(tls_root_cert, tls_server_name, token)
        config = make_config(render_mode, False, options)
        connection, server_index = connect_single(address, server_index, security)
        # What a pickle carries (__reduce__): the arguments that make the same environment on the
        # same server again, never the connection.
        addresses = parse_addresses(address)
        self._init_kwargs = dict(
            options,
            address=list(addresses) or None,
            server_index=server_index if addresses else None,
            render_mode=render_mode,
            **security.as_options(),
        )
        try:
            connection.check_server()  # GetServerInfo, once per connection.
            env = connection.call("CreateEnv", pb.CreateEnvRequest(config=config))
        except BaseException:
            connection.close()
            raise
        self._connection = connection
        self._name = env.name
        self._deleter = weakref.finalize(self, _delete_env, connection, env.name)
        _lease.hold(connection, env.name, env.idle_timeout_s)
        self.render_mode = render_mode
        self.config = config_dict(env.config)
        self._env_config = env.config  # Filled in by the server (what a state carries).
        self.continuous = bool(env.config.continuous)
        self.possible_agents = list(env.possible_agents)
        self._agent_index = {agent: index for index, agent in enumerate(self.possible_agents)}
        # One space object per agent, returned by every call (seeding one agent's space must
        # not reseed another's).
        self.observation_spaces = {a: space_from_proto(env.observation_space) for a in self.possible_agents}
        self.action_spaces = {a: space_from_proto(env.action_space) for a in self.possible_agents}
        self.metadata = dict(METADATA, render_fps=env.render_fps or METADATA["render_fps"])
        self._viewer: Viewer | None = None
        self._init_state()

    def __reduce__(self):
        """Pickles as its arguments: options, address (the server it lives on; None stays None,
        the embedded server of the unpickling process) and TLS/token settings (the token
        itself included). Unpickling creates a new, not yet reset environment on that server,
        so copies made by cloudpickle or sent to worker processes (SuperSuit's
        concat_vec_envs_v1, Ray) each have their own."""
        return rebuild, (type(self), self._init_kwargs)

    def _init_state(self) -> None:
        """The subclass's own attributes, set once the server-side env exists."""
        raise NotImplementedError

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
        (GetServerInfo, asked when the environment was created)."""
        return self._connection.server_info

    def observation_space(self, agent: str) -> gymnasium.spaces.Space:
        return self.observation_spaces[agent]

    def action_space(self, agent: str) -> gymnasium.spaces.Space:
        return self.action_spaces[agent]

    def _frame(self) -> np.ndarray:
        frame = self._connection.call(
            "RenderEnv", pb.RenderEnvRequest(name=self._name, format=pb.FRAME_FORMAT_RGB)
        )
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
