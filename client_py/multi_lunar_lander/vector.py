"""Many environments stepped together: one StepBatch call per server per step, arrays in and
out.

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

from typing import Any, NamedTuple, Sequence

import grpc
import numpy as np

from . import _arrays
from ._channel import Security, parse_addresses
from ._errors import MLLError, from_item_error, invalid_argument
from ._remote import Connection, action_array, config_dict, make_config, seed_value, space_from_proto
from ._stubs import pb

# (StepData field, wire dtype, per-env trailing shape given n_landers).
_COLUMNS = (
    ("observations", pb.DTYPE_FLOAT32, lambda n: (n, 12)),
    ("rewards", pb.DTYPE_FLOAT32, lambda n: (n,)),
    ("terminations", pb.DTYPE_UINT8, lambda n: (n,)),
    ("truncations", pb.DTYPE_UINT8, lambda n: (n,)),
    ("stepped", pb.DTYPE_UINT8, lambda n: (n,)),
    ("outcomes", pb.DTYPE_UINT8, lambda n: (n,)),
    ("episode_returns", pb.DTYPE_FLOAT32, lambda n: (n,)),
    ("episode_lengths", pb.DTYPE_INT32, lambda n: (n,)),
)


class _Batch(NamedTuple):
    """One server's share of a vector env: its connection, its StepBatch request, and the env
    indices of the request's entries, in order."""

    connection: Connection
    request: "pb.StepBatchRequest"
    envs: list


class VectorEnv:
    """`num_envs` Multi Lunar Lander environments with the same options, on the server(s) of
    `address` (env i on server i mod S; None: the embedded server). TLS and token: as for
    `parallel_env` (tls_root_cert=, tls_server_name=, token=).

    reset(seed=None, options=None) -> (observations, infos): observations float32
      (num_envs, n_landers, 12); seed s gives env i the seed s + i (None continues each env's
      stream).
    step(actions) -> (observations, rewards, terminations, truncations, active, infos): actions
      int (num_envs, n_landers) or, continuous, float (num_envs, n_landers, 2); entries of done
      agents are ignored. rewards float32 (num_envs, n_landers); terminations, truncations and
      active bool (num_envs, n_landers): `active` marks the rows that carry a transition (the
      agent was active at the start of the step and this is not an auto-reset).
    infos: "auto_reset" bool (num_envs,), "episode_over" bool (num_envs,), "outcome" uint8
      (num_envs, n_landers) with codes indexing OUTCOMES, "episode_return" float32 and
      "episode_length" int32 (num_envs, n_landers) (so far in the episode, final once done).
    """

    def __init__(
        self,
        num_envs: int,
        address: str | Sequence[str] | None = None,
        *,
        tls_root_cert: str | bytes | None = None,
        tls_server_name: str | None = None,
        token: str | None = None,
        **options: Any,
    ):
        if int(num_envs) != num_envs or num_envs < 1:
            raise invalid_argument(f"num_envs is {num_envs!r}; expected an integer >= 1")
        self.num_envs = int(num_envs)
        config = make_config(None, True, options)
        security = Security.from_options(tls_root_cert, tls_server_name, token)
        addresses = parse_addresses(address)
        servers = addresses or (None,)  # None: the embedded server.
        self._names: list[str | None] = [None] * self.num_envs  # None: not created.
        # Env i lives on server i mod S; servers beyond num_envs get no connection.
        self._connections: list[Connection] = []
        try:
            for server in servers[: self.num_envs]:
                self._connections.append(Connection(server, security, addresses))
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
        except BaseException:
            self.close()
            raise
        spec = envs[0]
        self.config = config_dict(spec.config)
        self.continuous = bool(spec.config.continuous)
        self.n_landers = int(spec.config.n_landers)
        self.possible_agents = list(spec.possible_agents)
        self.single_observation_space = space_from_proto(spec.observation_space)
        self.single_action_space = space_from_proto(spec.action_space)
        # One batch request per server, built once; each step only replaces the action bytes.
        # self._steps[i] is env i's entry in its server's request.
        self._action_dtype = action_dtype = pb.DTYPE_FLOAT32 if self.continuous else pb.DTYPE_INT32
        action_shape = (self.n_landers, 2) if self.continuous else (self.n_landers,)
        self._batches = [_Batch(connection, pb.StepBatchRequest(), []) for connection in self._connections]
        self._steps = []
        for index, name in enumerate(self._names):
            batch = self._batches[index % len(self._batches)]
            step = batch.request.steps.add(name=name)
            step.actions.dtype = action_dtype
            step.actions.shape.extend(action_shape)
            batch.envs.append(index)
            self._steps.append(step)

    def _connection_of(self, index: int) -> Connection:
        return self._connections[index % len(self._connections)]

    @property
    def address(self) -> str:
        """The servers' addresses, comma-separated (a valid `address=` for another client)."""
        return ",".join(self.addresses)

    @property
    def addresses(self) -> list[str]:
        """The address of each server that holds environments, in server order."""
        return [connection.address for connection in self._connections]

    @property
    def names(self) -> list[str]:
        """The server-side resource names, `envs/{id}`, in env order."""
        return list(self._names)

    @property
    def env_addresses(self) -> list[str]:
        """The address of the server of each environment, in env order (env i: server i mod S)."""
        return [self._connection_of(index).address for index in range(self.num_envs)]

    def _stack(self, datas: list, auto_reset: np.ndarray, episode_over: np.ndarray):
        columns = {
            field: _arrays.stack_bytes(
                [getattr(data, field).data for data in datas], dtype, (self.num_envs,) + shape(self.n_landers)
            )
            for field, dtype, shape in _COLUMNS
        }
        active = columns["stepped"].astype(bool)
        active[auto_reset] = False
        infos = {
            "auto_reset": auto_reset,
            "episode_over": episode_over,
            "outcome": columns["outcomes"],
            "episode_return": columns["episode_returns"],
            "episode_length": columns["episode_lengths"],
        }
        return (
            columns["observations"],
            columns["rewards"],
            columns["terminations"].astype(bool),
            columns["truncations"].astype(bool),
            active,
            infos,
        )

    def reset(self, seed: int | None = None, options: dict | None = None):
        seed = seed_value(seed)
        waits = []
        for index, name in enumerate(self._names):
            request = pb.ResetEnvRequest(name=name)
            if seed is not None:
                request.seed = (seed + index) % 2**64
            waits.append(self._connection_of(index).future("ResetEnv", request))
        datas = [wait().data for wait in waits]
        no = np.zeros(self.num_envs, dtype=bool)
        observations, _, _, _, _, infos = self._stack(datas, no, no.copy())
        return observations, infos

    def step(self, actions):
        block = action_array(actions, self.continuous, (self.num_envs, self.n_landers), "actions")
        for step, data in zip(self._steps, _arrays.row_bytes(block, self._action_dtype)):
            step.actions.data = data
        # One StepBatch per server, all in flight at once: the first server's call runs on this
        # thread while the others' futures proceed.
        waits = [batch.connection.future("StepBatch", batch.request) for batch in self._batches[1:]]
        replies = [self._batches[0].connection.call("StepBatch", self._batches[0].request)]
        replies.extend(wait() for wait in waits)
        results = [None] * self.num_envs
        for batch, reply in zip(self._batches, replies):
            if len(reply.results) != len(batch.envs):
                raise MLLError(
                    grpc.StatusCode.INTERNAL,
                    f"{batch.connection.address} answered StepBatch of {len(batch.envs)} envs with "
                    f"{len(reply.results)} results",
                )
            for index, result in zip(batch.envs, reply.results):
                results[index] = result
        for index, result in enumerate(results):  # The first failed env in env order, as on one server.
            if result.HasField("error"):
                raise from_item_error(result.error.code, result.error.message, f"env {index} ({self._names[index]}): ")
        datas = [result.data for result in results]
        auto_reset = np.fromiter((data.auto_reset for data in datas), dtype=bool, count=self.num_envs)
        episode_over = np.fromiter((data.episode_over for data in datas), dtype=bool, count=self.num_envs)
        return self._stack(datas, auto_reset, episode_over)

    def close(self) -> None:
        """Deletes the environments on their servers and closes the connections. Idempotent."""
        if all(connection.closed for connection in self._connections):
            return
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
