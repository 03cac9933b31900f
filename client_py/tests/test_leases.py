"""Leases follow the client: while an environment object lives, its environments survive
pauses longer than the server's idle timeout (the client renews them with KeepAlive from a
daemon thread); when the client process dies (SIGKILL, nothing runs after it) the server still
reclaims them after the timeout, and NOT_FOUND then says so and how to avoid it."""

import gc
import subprocess
import sys
import textwrap
import time

import grpc
import numpy as np
import pytest

import multi_lunar_lander as mll
from multi_lunar_lander import _lease
from multi_lunar_lander._stubs import pb, pb_grpc

IDLE_TIMEOUT_S = 1.0


@pytest.fixture(scope="module")
def short_lease_server():
    with mll.ServerProcess(threads=2, idle_timeout_s=IDLE_TIMEOUT_S) as process:
        yield process


@pytest.fixture(scope="module")
def stub(short_lease_server):
    with grpc.insecure_channel(short_lease_server.address) as channel:
        yield pb_grpc.MultiLunarLanderStub(channel)


def listed(stub) -> set:
    """Names hosted now; unlike GetEnv, listing touches no env's lease."""
    return {env.name for env in stub.ListEnvs(pb.ListEnvsRequest(page_size=1000)).envs}


def wait_until(condition, limit_s):
    end = time.monotonic() + limit_s
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(0.05)
    return condition()


def test_live_env_objects_survive_a_long_pause(short_lease_server, stub):
    address = short_lease_server.address
    parallel = mll.parallel_env(address=address, n_landers=2)
    aec = mll.env(address=address, n_landers=2)
    vec = mll.vector_env(3, address=address, n_landers=2)
    parallel.reset(seed=0)
    aec.reset(seed=0)
    vec.reset(seed=0)
    time.sleep(3.5 * IDLE_TIMEOUT_S)  # The trainer pauses (evaluation, a checkpoint, a debugger).
    names = {parallel.name, aec.name, *vec.names}
    assert names <= listed(stub)
    parallel.step({agent: 0 for agent in parallel.agents})
    aec.step(0)
    vec.step(np.zeros((3, 2), np.int64))
    for env in (parallel, aec, vec):
        env.close()
    assert not names & listed(stub)


def test_a_dropped_env_object_stops_renewing(short_lease_server, stub):
    env = mll.parallel_env(address=short_lease_server.address)
    connection = env._connection
    assert connection in _lease._KEEPER._leases
    del env
    gc.collect()
    assert wait_until(lambda: connection not in _lease._KEEPER._leases, 3 * IDLE_TIMEOUT_S)


CHILD = textwrap.dedent(
    """
    import sys, time
    import multi_lunar_lander as mll
    env = mll.parallel_env(address=sys.argv[1], n_landers=2)
    env.reset(seed=0)
    print(env.name, flush=True)
    time.sleep(120)
    """
)


def test_envs_of_a_killed_client_are_reclaimed_after_the_timeout(short_lease_server, stub):
    child = subprocess.Popen([sys.executable, "-c", CHILD, short_lease_server.address], stdout=subprocess.PIPE, text=True)
    try:
        name = child.stdout.readline().strip()
        assert name.startswith("envs/")
        time.sleep(2.5 * IDLE_TIMEOUT_S)  # The child only sleeps; its lease thread keeps the env.
        assert name in listed(stub)
        child.kill()  # SIGKILL: no close(), no finalizer, no goodbye.
        child.wait(timeout=10)
        killed_at = time.monotonic()
        assert wait_until(lambda: name not in listed(stub), IDLE_TIMEOUT_S + 3)
        assert time.monotonic() - killed_at >= IDLE_TIMEOUT_S / 3  # Not before a timeout could pass.
    finally:
        child.kill()
        child.wait(timeout=10)
        child.stdout.close()
    with pytest.raises(grpc.RpcError) as caught:
        stub.GetEnv(pb.GetEnvRequest(name=name))
    assert caught.value.code() == grpc.StatusCode.NOT_FOUND
    message = caught.value.details()
    assert f"{name} was reclaimed after being idle 1 s" in message
    assert "keep the client's env object alive" in message and "--idle_timeout_s" in message


def test_the_client_surfaces_the_reclaimed_message(short_lease_server, stub):
    env = mll.parallel_env(address=short_lease_server.address)
    env.reset(seed=0)
    name = env.name
    # The lease stops as if the process had paused without its renewal thread.
    _lease._KEEPER._leases.pop(env._connection)
    assert wait_until(lambda: name not in listed(stub), IDLE_TIMEOUT_S + 3)
    with pytest.raises(mll.MLLError) as caught:
        env.step({agent: 0 for agent in env.agents})
    assert caught.value.code == grpc.StatusCode.NOT_FOUND
    assert "was reclaimed after being idle" in caught.value.message
    env.close()
