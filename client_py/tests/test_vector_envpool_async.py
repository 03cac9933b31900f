"""EnvPool's async API on vector_env (batch_size=, async_reset, send, recv, step(actions, env_id)):
each env's trajectory is the synchronous API's, bit for bit, over every transport and several
servers, with several requests in flight on each server's stream; and the errors."""

import pickle

import grpc
import numpy as np
import pytest

import multi_lunar_lander as mll
TRANSPORTS = ["native", "shared_memory"]


@pytest.fixture(scope="module")
def second_server():
    with mll.ServerProcess(threads=1) as server:
        yield server.address


def _synchronous(address, num_envs, table, steps, transport, **options):
    """Every env's observations, rewards, terminations and auto-reset flags, reset then `steps`
    synchronous steps with table[t, env] as env's t-th actions."""
    with mll.vector_env(num_envs, address=address, transport=transport, **options) as vector:
        observations, infos = vector.reset(seed=5)
        record = [[(observations[e].tobytes(), None, None, False)] for e in range(num_envs)]
        for t in range(steps):
            observations, rewards, terminations, _, _, infos = vector.step(table[t])
            for e in range(num_envs):
                record[e].append(
                    (observations[e].tobytes(), rewards[e].tobytes(), terminations[e].tobytes(),
                     bool(infos["auto_reset"][e]))
                )
    return record


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_each_envs_trajectory_is_the_synchronous_ones(address, second_server, transport):
    num_envs, batch_size, steps, n_landers = 7, 3, 160, 2  # batch_size need not divide num_envs.
    addresses = [address, second_server]
    # Envs the async API serves first may run ahead: the synchronous reference goes 3x as far.
    table = np.random.default_rng(3).integers(0, 4, (3 * steps, num_envs, n_landers), dtype=np.int32)
    expected = _synchronous(addresses, num_envs, table, 3 * steps, transport, n_landers=n_landers)
    with mll.vector_env(num_envs, address=addresses, transport=transport, batch_size=batch_size,
                        n_landers=n_landers) as vector:
        vector.async_reset(seed=5)
        got = [[] for _ in range(num_envs)]
        sent = np.zeros(num_envs, int)
        while sent.min() < steps:
            observations, rewards, terminations, _, active, infos = vector.recv()
            env_id = infos["env_id"]
            assert env_id.dtype.kind == "i" and env_id.shape == (batch_size,)
            for row, e in enumerate(env_id):
                first = not got[e]
                got[e].append(
                    (observations[row].tobytes(), None if first else rewards[row].tobytes(),
                     None if first else terminations[row].tobytes(), bool(infos["auto_reset"][row]))
                )
                assert not (first or infos["auto_reset"][row]) or not active[row].any()
            vector.send(table[sent[env_id], env_id], env_id)
            sent[env_id] += 1
    for e in range(num_envs):
        assert got[e] == expected[e][: len(got[e])], f"env {e}"
        assert len(got[e]) >= steps
    assert sum(flag for e in range(num_envs) for *_, flag in got[e]) > num_envs  # Auto-resets happened.


def test_several_requests_are_in_flight_on_one_stream(address):
    with mll.vector_env(8, address=address, n_landers=1, batch_size=2, transport=TRANSPORTS[-1]) as vector:
        vector.async_reset(seed=1)
        for _ in range(4):
            infos = vector.recv()[-1]
            vector.send(np.zeros((2, 1), np.int32), infos["env_id"])
        code, message = _code(vector.send, np.zeros((8, 1), np.int32), np.arange(8))  # All 8 are in flight.
        assert code == grpc.StatusCode.FAILED_PRECONDITION and "has a step in flight" in message
        received = [vector.recv()[-1]["env_id"] for _ in range(4)]
        assert sorted(np.concatenate(received)) == list(range(8))


def test_step_is_send_then_recv_and_batch_size_num_envs_is_synchronous(address):
    with mll.vector_env(4, address=address, n_landers=1) as synchronous, \
            mll.vector_env(4, address=address, n_landers=1, batch_size=4) as full, \
            mll.vector_env(4, address=address, n_landers=1, batch_size=2) as half:
        assert full.batch_size == 4 and synchronous.batch_size == 4
        first, _ = synchronous.reset(seed=2)
        full.reset(seed=2)
        actions = np.full((4, 1), 2, np.int32)
        expected = synchronous.step(actions)[0]
        assert np.array_equal(full.step(actions)[0], expected)
        half.async_reset(seed=2)
        observations, *_, infos = half.recv()
        assert np.array_equal(observations, first[infos["env_id"]])
        observations, *_, infos = half.step(actions[:2], infos["env_id"])
        assert list(infos["env_id"]) == [2, 3]  # Reset results come first, as they are ready.
        observations, *_, infos = half.step(actions[:2], [2, 3])
        assert list(infos["env_id"]) == [0, 1]
        assert np.array_equal(observations, expected[:2])


def _code(call, *args, **kwargs):
    with pytest.raises(mll.MLLError) as caught:
        call(*args, **kwargs)
    return caught.value.code, caught.value.message


def test_bad_use_gets_a_clear_error(address):
    for bad in (0, 5, 2.5, True):
        code, message = _code(mll.vector_env, 4, address=address, batch_size=bad)
        assert code == grpc.StatusCode.INVALID_ARGUMENT and "batch_size" in message and "1..4" in message
    with mll.vector_env(4, address=address, n_landers=1, batch_size=2) as vector:
        code, message = _code(vector.recv)
        assert code == grpc.StatusCode.FAILED_PRECONDITION and "batch_size = 2" in message
        vector.async_reset(seed=0)
        zeros = np.zeros((2, 1), np.int32)
        code, message = _code(vector.send, zeros, [0, 1])
        assert code == grpc.StatusCode.FAILED_PRECONDITION and "env 0 has a step in flight" in message
        vector.recv()
        code, message = _code(vector.send, zeros, [0, 4])
        assert code == grpc.StatusCode.INVALID_ARGUMENT and "env_id holds 4; allowed: 0..3" in message
        code, message = _code(vector.send, zeros, [1, 1])
        assert code == grpc.StatusCode.INVALID_ARGUMENT and "more than once" in message
        code, message = _code(vector.send, np.zeros((3, 1), np.int32), [0, 1])
        assert code == grpc.StatusCode.INVALID_ARGUMENT and "actions" in message
        code, message = _code(vector.reset)
        assert code == grpc.StatusCode.FAILED_PRECONDITION and "recv them first" in message.lower()
        code, message = _code(vector.step_async, np.zeros((4, 1), np.int32))
        assert code == grpc.StatusCode.FAILED_PRECONDITION
        vector.send(zeros, [0, 1])  # None of the refused calls changed what is in flight.
        assert sorted(vector.recv()[-1]["env_id"]) == [2, 3]
        assert sorted(vector.recv()[-1]["env_id"]) == [0, 1]


def test_pickles_with_its_batch_size(address):
    with mll.vector_env(4, address=address, n_landers=1, batch_size=2) as vector:
        copy = pickle.loads(pickle.dumps(vector))
        try:
            assert copy.batch_size == 2
        finally:
            copy.close()
