"""Failover of EnvPool's async API (send/recv) on vector_env: envs lost with their server while
their steps are in flight are recreated elsewhere, replayed, and their steps sent again, so each
env's trajectory is the bits of a run without the fault; a failover target that drains during
the replay is passed over for the next server."""

import logging
import os
import signal
import time

import grpc
import numpy as np
import pytest

import multi_lunar_lander as mll

from mll_test_helpers import random_actions, wait_draining

NUM_ENVS, BATCH, RECVS, KILL_AT = 24, 8, 120, 60
OPTIONS = dict(n_landers=2, max_cycles=30)  # Each env's episodes end (truncated) within its ~40 steps.
SECONDS = 120  # Every loop's time bound.
TRANSPORTS = ["native", "shared_memory"]


def _kill(server):
    os.kill(server.pid, signal.SIGKILL)
    server._process.wait(timeout=10)


def _trajectories(vector, table, recvs, fault=None, fault_at=None):
    """Each env's results, in recv order (observations, rewards, terminations, truncations and
    auto_reset bytes per row), over `recvs` recvs after async_reset, each env sent its next
    row of `table` (indexed by the env's step count) as soon as recv returned it; fault() runs
    before recv number `fault_at`."""
    deadline = time.monotonic() + SECONDS
    vector.async_reset(seed=7)
    got = [[] for _ in range(vector.num_envs)]
    sent = np.zeros(vector.num_envs, int)
    for count in range(recvs):
        assert time.monotonic() < deadline, f"recv {count} of {recvs} after {SECONDS} s"
        if count == fault_at:
            fault()
        observations, rewards, terminations, truncations, _, infos = vector.recv()
        ids = infos["env_id"]
        for row, env in enumerate(ids):
            got[env].append(
                tuple(part[row].tobytes() for part in (observations, rewards, terminations, truncations))
                + (bool(infos["auto_reset"][row]),)
            )
        vector.send(table[sent[ids], ids], ids)
        sent[ids] += 1
    return got


def _assert_same_trajectories(got, expected, least):
    """Each env's trajectory in `got` is the one in `expected` (as far as both went, at least
    `least` results each)."""
    for env, (mine, theirs) in enumerate(zip(got, expected)):
        common = min(len(mine), len(theirs))
        assert common >= least, f"env {env}: {len(mine)} and {len(theirs)} results"
        assert mine[:common] == theirs[:common], f"env {env}"


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_kill_one_of_three_servers_during_send_recv(caplog, transport):
    table = random_actions(np.random.default_rng(11), (RECVS + 1, NUM_ENVS, 2), False)
    with mll.ServerProcess(threads=1) as a, mll.ServerProcess(threads=1) as b, mll.ServerProcess(threads=1) as c:
        addresses = [a.address, b.address, c.address]
        with mll.vector_env(NUM_ENVS, address=addresses, batch_size=BATCH, transport=transport, **OPTIONS) as vector:
            expected = _trajectories(vector, table, RECVS)
            assert vector.failovers == 0
        with caplog.at_level(logging.WARNING, logger="multi_lunar_lander"):
            with mll.vector_env(NUM_ENVS, address=addresses, batch_size=BATCH, transport=transport, **OPTIONS) as vector:
                got = _trajectories(vector, table, RECVS, lambda: _kill(b), KILL_AT)
                assert vector.failovers >= 1
                assert b.address not in vector.env_addresses
        assert any("failover" in record.getMessage() for record in caplog.records)
    assert sum(len(mine) for mine in got) == sum(len(theirs) for theirs in expected) == RECVS * BATCH
    _assert_same_trajectories(got, expected, RECVS * BATCH // NUM_ENVS // 2)
    assert any(flag for mine in got for *_, flag in mine[1:])  # Auto-resets happened (and were replayed).


def test_failover_off_raises_unavailable_from_recv():
    with mll.ServerProcess(threads=1) as a, mll.ServerProcess(threads=1) as d:
        with mll.vector_env(4, address=[a.address, d.address], batch_size=2, n_landers=2, failover=False) as vector:
            vector.async_reset(seed=1)
            infos = vector.recv()[-1]
            vector.send(np.zeros((2, 2), np.int32), infos["env_id"])
            _kill(d)
            with pytest.raises(mll.MLLError) as raised:
                for _ in range(10):  # Both envs of d are reached within a few recvs.
                    infos = vector.recv()[-1]
                    vector.send(np.zeros((2, 2), np.int32), infos["env_id"])
            assert raised.value.code == grpc.StatusCode.UNAVAILABLE
            assert vector.failovers == 0


def test_an_env_deleted_behind_its_back_is_recreated_on_its_server(address, raw_stub):
    from multi_lunar_lander._stubs import pb

    table = random_actions(np.random.default_rng(5), (41, 4, 2), False)

    def delete():
        raw_stub.DeleteEnv(pb.DeleteEnvRequest(name=vector.names[1]))

    with mll.vector_env(4, address=address, batch_size=2, n_landers=2, failover=True) as vector:
        got = _trajectories(vector, table, 40, delete, 20)
        assert vector.failovers == 1 and vector.env_addresses == [address] * 4
    with mll.vector_env(4, address=address, batch_size=2, n_landers=2) as vector:
        expected = _trajectories(vector, table, 40)
    _assert_same_trajectories(got, expected, 15)


def _rounds(vector, table, rounds, fault_round=None, fault=None):
    """Each env's results over `rounds` rounds after async_reset: a round sends the envs of each
    server in turn, the second server's first (as placed at the start), and recvs all six
    (batch_size 3). fault() runs before the sends of round `fault_round` (a server killed after
    them may have answered already)."""
    deadline = time.monotonic() + SECONDS
    placed = vector.env_addresses
    servers = sorted(set(placed), key=placed.index)
    groups = [[env for env in range(6) if placed[env] == server] for server in servers[1:] + servers[:1]]
    vector.async_reset(seed=3)
    got = [[] for _ in range(6)]
    for round_ in range(rounds + 1):
        assert time.monotonic() < deadline, f"round {round_} of {rounds} after {SECONDS} s"
        if round_ == fault_round:
            fault()
        if round_:
            for ids in groups:
                vector.send(table[round_ - 1, ids], ids)
        for _ in range(2):
            observations, rewards, *_, infos = vector.recv()
            for row, env in enumerate(infos["env_id"]):
                got[env].append((observations[row].tobytes(), rewards[row].tobytes()))
    return got


def test_a_target_that_drains_during_the_failover_is_passed_over(caplog):
    rounds, fault_round = 40, 20
    table = random_actions(np.random.default_rng(8), (rounds, 6, 2), False)
    with mll.ServerProcess(threads=1) as a, mll.ServerProcess(threads=1) as b, \
            mll.ServerProcess(threads=1, extra_args=("--drain_s=30",)) as c:
        addresses = [a.address, b.address, c.address]
        with mll.vector_env(6, address=addresses, batch_size=3, n_landers=2) as vector:
            expected = _rounds(vector, table, rounds)

        def fault():
            # b dies, then the steps of its envs are sent first: their failover places them on a
            # and c (the least loaded, one each), and c drains already, so its share goes on to a.
            _kill(b)
            c._process.send_signal(signal.SIGTERM)
            wait_draining(c.address)

        with caplog.at_level(logging.WARNING, logger="multi_lunar_lander"):
            with mll.vector_env(6, address=addresses, batch_size=3, n_landers=2) as vector:
                got = _rounds(vector, table, rounds, fault_round, fault)
                assert vector.env_addresses == [a.address] * 6
                assert vector.failovers == 2  # b's envs, then c's (its drain ended their stream).
    messages = [record.getMessage() for record in caplog.records if "failover" in record.getMessage()]
    assert any(f"passed over mll_server at {c.address} " in message for message in messages), messages
    assert any("draining: " in message.split("passed over")[-1] for message in messages), messages
    assert got == expected


def test_no_server_left_names_the_servers_tried():
    with mll.ServerProcess(threads=1) as a, mll.ServerProcess(threads=1) as b, \
            mll.ServerProcess(threads=1, extra_args=("--drain_s=30",)) as c:
        with mll.vector_env(3, address=[a.address, b.address, c.address], batch_size=1, n_landers=2) as vector:
            vector.async_reset(seed=1)
            for _ in range(3):
                vector.recv()
            _kill(b)
            _kill(a)
            c._process.send_signal(signal.SIGTERM)
            wait_draining(c.address)
            vector.send(np.zeros((1, 2), np.int32), [1])  # On b.
            with pytest.raises(mll.MLLError) as raised:
                vector.recv()  # Env 1's failover tries a (dead), then c (draining).
    assert raised.value.code == grpc.StatusCode.UNAVAILABLE
    message = raised.value.message
    assert "no reachable server" in message, message
    tried = message.split("; passed over ")[1:]
    assert [part.split()[2] for part in tried] == [a.address, c.address], message
    assert "draining: " in tried[1], message
