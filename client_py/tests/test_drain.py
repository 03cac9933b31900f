"""Graceful drain (issue 29): on SIGTERM with --drain_s, mll_server answers health NOT_SERVING,
refuses new envs and Sessions with UNAVAILABLE "draining: ...", ends its open Session streams
with that status, serves the envs it still has, and exits once they are gone (or --drain_s
has passed)."""

import queue
import signal
import time

import grpc
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc

import multi_lunar_lander as mll
from multi_lunar_lander._stubs import pb, pb_grpc

_END = object()


def _open_session(stub):
    """A raw Session stream: (request queue, response iterator)."""
    requests = queue.SimpleQueue()
    return requests, stub.Session(iter(requests.get, _END))


def _health(channel) -> int:
    return health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(), timeout=5).status


def _draining_error(call, *args):
    with pytest.raises(grpc.RpcError) as caught:
        call(*args, timeout=5)
    assert caught.value.code() == grpc.StatusCode.UNAVAILABLE, caught.value
    assert caught.value.details().startswith("draining: "), caught.value.details()
    return caught.value.details()


def test_sigterm_drains_sessions_refuses_new_envs_and_exits_when_envs_are_gone():
    with mll.ServerProcess(threads=1, extra_args=("--drain_s=20",)) as server:
        with grpc.insecure_channel(server.address) as channel:
            stub = pb_grpc.MultiLunarLanderStub(channel)
            config = pb.EnvConfig(n_landers=2)
            kept = stub.CreateEnv(pb.CreateEnvRequest(config=config), timeout=5).name
            requests, responses = _open_session(stub)
            requests.put(pb.SessionRequest(sequence=1, create_env=pb.CreateEnvRequest(config=config)))
            bound = next(responses).env.name
            requests.put(pb.SessionRequest(sequence=2, reset_env=pb.ResetEnvRequest(name=bound, seed=1)))
            assert next(responses).sequence == 2
            assert _health(channel) == health_pb2.HealthCheckResponse.SERVING

            server._process.send_signal(signal.SIGTERM)
            # The idle Session stream is ended at once with the status clients move on.
            with pytest.raises(grpc.RpcError) as ended:
                next(responses)
            assert ended.value.code() == grpc.StatusCode.UNAVAILABLE
            assert ended.value.details().startswith("draining: "), ended.value.details()
            requests.put(_END)

            assert _health(channel) == health_pb2.HealthCheckResponse.NOT_SERVING
            message = _draining_error(stub.CreateEnv, pb.CreateEnvRequest(config=config))
            assert "create environments on another server" in message
            _draining_error(stub.GetServerInfo, pb.GetServerInfoRequest())
            requests, responses = _open_session(stub)
            requests.put(pb.SessionRequest(sequence=1, reset_env=pb.ResetEnvRequest(name=kept)))
            with pytest.raises(grpc.RpcError) as refused:
                next(responses)
            assert refused.value.code() == grpc.StatusCode.UNAVAILABLE
            assert refused.value.details().startswith("draining: ")
            requests.put(_END)

            # The envs still here are served; the session's bound env went with its stream.
            stub.ResetEnv(pb.ResetEnvRequest(name=kept, seed=3), timeout=5)
            with pytest.raises(grpc.RpcError) as gone:
                stub.GetEnv(pb.GetEnvRequest(name=bound), timeout=5)
            assert gone.value.code() == grpc.StatusCode.NOT_FOUND
            assert server.running
            began = time.monotonic()
            stub.DeleteEnv(pb.DeleteEnvRequest(name=kept), timeout=5)
            assert server._process.wait(timeout=10) == 0
            assert time.monotonic() - began < 5  # Not the 20 s of --drain_s: no env was left.
        assert "drained in" in server.log_tail()


def test_drain_ends_after_drain_s_with_envs_left():
    with mll.ServerProcess(threads=1, extra_args=("--drain_s=0.5",)) as server:
        with grpc.insecure_channel(server.address) as channel:
            stub = pb_grpc.MultiLunarLanderStub(channel)
            stub.CreateEnv(pb.CreateEnvRequest(config=pb.EnvConfig(n_landers=1)), timeout=5)
            began = time.monotonic()
            server._process.send_signal(signal.SIGTERM)
            assert server._process.wait(timeout=10) == 0
            assert 0.4 < time.monotonic() - began < 8
        assert "1 envs left" in server.log_tail()
