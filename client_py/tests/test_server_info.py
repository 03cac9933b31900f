"""GetServerInfo from the Python client: the real mll_server's answer (mll.server_info and
env.server_info), asked once per connection; the compatibility check on synthetic ServerInfo
values (another protocol major, a missing capability, a v1.0 server); and fake servers of an
older release (no GetServerInfo) and of a newer protocol, on loopback."""

import importlib.metadata
import json
import os
import time
from concurrent import futures

import grpc
import numpy as np
import pytest

import multi_lunar_lander as mll
from multi_lunar_lander import _server_info
from multi_lunar_lander._remote import Connection
from multi_lunar_lander._stubs import pb, pb_grpc

CLIENT_VERSION = importlib.metadata.version("multi_lunar_lander")


def synthetic(protocol, capabilities=(), version="9.8.7"):
    return mll.ServerInfo(version, protocol, frozenset(capabilities), mll.ServerLimits())


def test_the_real_server_reports_its_release_protocol_and_limits(address):
    info = mll.server_info(address)
    # Client and server are released together: the project's one version.
    assert info.server_version == CLIENT_VERSION
    assert info.protocol == mll.PROTOCOL == (1, 3)
    assert {
        "packed_step_batch", "auto_reset", "keep_alive", "shared_memory_sessions", "packed_batch_handles", "server_load"
    } <= info.capabilities
    assert info.limits == mll.ServerLimits(
        max_envs=10000,
        max_envs_per_token=0,
        max_message_bytes=64 << 20,
        idle_timeout_s=300.0,
        max_landers=32,
        threads=2,
        shared_memory_sessions=64,
    )
    as_json = json.loads(json.dumps(info.as_dict()))
    assert as_json["protocol"] == [1, 3]
    assert set(as_json["load"]) == {"envs_hosted", "cpu_cores", "cores_available", "agent_steps_per_s"}
    with pytest.raises(AttributeError):  # Frozen.
        info.server_version = "x"


def test_every_env_exposes_its_servers_answer_asked_once_per_connection(address, monkeypatch):
    asked = []
    original = _server_info.fetch
    monkeypatch.setattr(_server_info, "fetch", lambda connection: asked.append(connection) or original(connection))
    expected = mll.server_info(address)
    asked.clear()
    penv = mll.parallel_env(address=address, n_landers=1)
    assert penv.server_info == expected
    assert penv.server_info is penv.server_info
    penv.close()
    aec = mll.env(address=address, n_landers=1)
    assert aec.server_info == expected
    aec.close()
    # One GetServerInfo per connection: penv's and aec's.
    assert len(asked) == 2
    # The vector env's servers are asked by the C++ engine, once each (every address once).
    with mll.ServerProcess(threads=1) as other:
        second = mll.server_info(other.address)
        with mll.vector_env(2, address=[address, other.address], n_landers=1) as vector:
            assert vector.server_info == expected
            assert vector.server_infos == [expected, second]
            vector.reset(seed=0)
            vector.step(np.zeros((2, 1), np.int32))
            assert vector.server_infos == [expected, second]


def test_the_load_follows_the_envs_hosted_and_the_work():
    """ServerInfo.load: envs_hosted counts every env (creates and deletes), cpu_cores rises above 0
    under a bounded step load and stays within [0, cores_available]; not part of ==."""
    with mll.ServerProcess(threads=1, max_envs=8) as server:
        first = mll.server_info(server.address)
        assert first.load.envs_hosted == 0
        assert 0 < first.load.cores_available <= (os.cpu_count() or 1)
        assert 0 <= first.load.cpu_cores <= first.load.cores_available
        envs = [mll.parallel_env(address=server.address, n_landers=2) for _ in range(3)]
        assert mll.server_info(server.address).load.envs_hosted == 3
        envs.pop().close()
        assert mll.server_info(server.address).load.envs_hosted == 2
        # At most 1.5 s or 5,000 steps of stepping, whichever ends first.
        end, steps = time.monotonic() + 1.5, 0
        for env in envs:
            env.reset(seed=1)
        while steps < 5000 and time.monotonic() < end:
            env = envs[steps % 2]
            if not env.agents:
                env.reset()
            env.step({agent: 2 for agent in env.agents})
            steps += 1
        after = mll.server_info(server.address)
        assert after.load.envs_hosted == 2
        assert 0 < after.load.cpu_cores <= after.load.cores_available
        assert after.load.agent_steps_per_s > 0
        assert after == first  # The same server: its load is no part of what it is.
        for env in envs:
            env.close()


def test_least_loaded_takes_the_lowest_fill_then_cpu_then_the_first():
    def server(hosted, max_envs=100, cpu=0.0, cores=2.0):
        limits = mll.ServerLimits(max_envs=max_envs)
        return mll.ServerInfo("0.1.0", (1, 3), frozenset(), limits, mll.ServerLoad(hosted, cpu, cores, 0.0))

    least = _server_info.least_loaded
    assert least([server(50), server(10)]) == 1
    assert least([server(10, cpu=1.5), server(10, cpu=0.5)]) == 1  # Same fill: the lower CPU.
    assert least([server(10, cpu=1.0, cores=4.0), server(10, cpu=0.6, cores=2.0)]) == 0  # 0.25 < 0.3.
    assert least([server(10), server(10)]) == 0  # A full tie: the first.
    # Fill is against each server's own bound: 30 of 1000 is emptier than 5 of 100.
    assert least([server(5), server(30, max_envs=1000)]) == 1
    assert least([server(100), None, server(99)]) == 2  # Full, did not answer, has room.
    assert least([server(100), None]) is None
    # A bound of 0 (a server that reports none) counts as the largest known bound.
    assert least([server(20, max_envs=0), server(30, max_envs=50)]) == 0  # 21/50 < 31/50.
    assert least([mll.ServerInfo.predating(), server(0)]) == 0  # No load reported: taken as empty.


@pytest.mark.parametrize(
    "protocol, upgrade",
    [((2, 0), "upgrade the client to a release of protocol v2"), ((0, 3), "upgrade the server to a release of protocol v1")],
)
def test_another_protocol_major_is_refused_naming_both_versions(protocol, upgrade):
    with pytest.raises(mll.MLLError) as caught:
        _server_info.check_compatible(synthetic(protocol), "host:1")
    assert caught.value.code == grpc.StatusCode.FAILED_PRECONDITION
    message = caught.value.message
    assert f"mll_server 9.8.7 at host:1 (protocol v{protocol[0]}.{protocol[1]})" in message
    assert f"this client (multi_lunar_lander {CLIENT_VERSION}, protocol v{mll.PROTOCOL[0]}.{mll.PROTOCOL[1]})" in message
    assert upgrade in message


def test_a_missing_capability_is_refused_unless_the_server_predates_the_list():
    with pytest.raises(mll.MLLError) as caught:
        _server_info.check_compatible(
            synthetic((1, 1), ["auto_reset"]), "host:1", ("packed_step_batch", "auto_reset"), "vector_env"
        )
    assert caught.value.code == grpc.StatusCode.FAILED_PRECONDITION
    message = caught.value.message
    assert "mll_server 9.8.7 at host:1 (protocol v1.1) lacks capability 'packed_step_batch'" in message
    assert "which vector_env of this client" in message
    assert "upgrade the server" in message
    # A newer minor with capabilities this client does not know: fine.
    _server_info.check_compatible(synthetic((1, 9), ["packed_step_batch", "later"]), "host:1", ("packed_step_batch",))
    # Protocol 1.0 (a server from before GetServerInfo) lists nothing: not refused, tried.
    _server_info.check_compatible(mll.ServerInfo.predating(), "host:1", ("packed_step_batch",))
    assert not mll.ServerInfo.predating().lacks("packed_step_batch")
    assert synthetic((1, 1)).lacks("packed_step_batch")


class _FakeService(pb_grpc.MultiLunarLanderServicer):
    """A server of mll.v1 answering GetServerInfo with `info` (UNIMPLEMENTED when None, as a
    release from before GetServerInfo does) and CreateEnv with a made-up env; the rest of the
    methods are UNIMPLEMENTED (the generated servicer's defaults)."""

    def __init__(self, info):
        self.info = info
        self.creates = 0

    def GetServerInfo(self, request, context):
        if self.info is None:
            return super().GetServerInfo(request, context)
        return self.info

    def CreateEnv(self, request, context):
        self.creates += 1
        return pb.Env(
            name="envs/fake",
            config=pb.EnvConfig(n_landers=1),
            possible_agents=["lander_0"],
            observation_space=pb.Space(
                kind=pb.Space.KIND_BOX, dtype=pb.DTYPE_FLOAT32, shape=[12], low=[-1] * 12, high=[1] * 12
            ),
            action_space=pb.Space(kind=pb.Space.KIND_DISCRETE, dtype=pb.DTYPE_INT32, n=4),
        )


@pytest.fixture
def fake_server():
    servers = []

    def start(info):
        service = _FakeService(info)
        server = grpc.server(futures.ThreadPoolExecutor(max_workers=2))
        pb_grpc.add_MultiLunarLanderServicer_to_server(service, server)
        port = server.add_insecure_port("127.0.0.1:0")
        server.start()
        servers.append(server)
        return f"127.0.0.1:{port}", service

    yield start
    for server in servers:
        server.stop(grace=None)


def test_a_server_without_get_server_info_is_protocol_1_0(fake_server):
    address, service = fake_server(None)
    info = mll.server_info(address)
    assert info == mll.ServerInfo.predating()
    assert (info.server_version, info.protocol, info.capabilities) == ("", (1, 0), frozenset())
    connection = Connection(address)
    try:
        connection.check_server(("packed_step_batch",), "vector_env")  # Not refused: unknown.
    finally:
        connection.close()


def test_a_newer_protocol_is_refused_before_anything_is_created(fake_server):
    address, service = fake_server(pb.ServerInfo(server_version="2.0.0", protocol_major=2, protocol_minor=0))
    for make in (lambda: mll.parallel_env(address=address), lambda: mll.vector_env(2, address=address)):
        with pytest.raises(mll.MLLError) as caught:
            make()
        assert caught.value.code == grpc.StatusCode.FAILED_PRECONDITION
        assert f"mll_server 2.0.0 at {address} (protocol v2.0) speaks a newer wire protocol" in caught.value.message
        assert "upgrade the client" in caught.value.message
    assert service.creates == 0
    assert mll.server_info(address).protocol == (2, 0)  # Still readable, for a look.


def test_vector_env_refuses_a_server_without_packed_batches(fake_server):
    address, service = fake_server(
        pb.ServerInfo(server_version="0.0.9", protocol_major=1, protocol_minor=1, capabilities=["auto_reset"])
    )
    with pytest.raises(mll.MLLError) as caught:
        mll.vector_env(2, address=address)
    assert caught.value.code == grpc.StatusCode.FAILED_PRECONDITION
    # The C++ engine's words (it quotes with ").
    assert 'lacks capability "packed_step_batch"' in caught.value.message, caught.value.message
    assert service.creates == 0
    # A single env needs no capability: created.
    penv = mll.parallel_env(address=address)
    assert penv.name == "envs/fake" and service.creates == 1
    penv.close()  # The fake's DeleteEnv is UNIMPLEMENTED, which close() ignores.


def test_server_info_takes_one_server(address):
    with pytest.raises(mll.MLLError) as caught:
        mll.server_info([address, address])
    assert caught.value.code == grpc.StatusCode.INVALID_ARGUMENT
    assert "server_info takes one" in caught.value.message
