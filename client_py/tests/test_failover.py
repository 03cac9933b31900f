"""Failover by deterministic replay (issue 29): a vector env over several servers loses none of
its envs when one server dies; its results are the bits of a run without the fault."""

import logging
import os
import signal
import struct
import zlib

import grpc
import numpy as np
import pytest

import multi_lunar_lander as mll

from mll_test_helpers import random_actions, same_bits

STEPS, KILL_AT = 1000, 300


def _run(addresses, kill=None, seed=5):
    """Every array of a STEPS-step seeded random run of vector_env(24); kills `kill` (a
    ServerProcess) before step KILL_AT."""
    vector = mll.vector_env(24, address=addresses, n_landers=2)
    rng = np.random.default_rng(seed)
    observations, infos = vector.reset(seed=seed)
    record = [observations, infos["episode_length"]]
    for step in range(STEPS):
        if kill is not None and step == KILL_AT:
            os.kill(kill.pid, signal.SIGKILL)
            kill._process.wait(timeout=10)
        result = vector.step(random_actions(rng, (24, 2), False))
        record.extend(result[:-1])
        record.extend(result[-1][key] for key in sorted(result[-1]))
    failovers = vector.failovers
    env_addresses = vector.env_addresses
    vector.close()
    return record, failovers, env_addresses


def test_kill_one_of_three_servers_mid_run(caplog):
    with mll.ServerProcess(threads=1) as a, mll.ServerProcess(threads=1) as b, mll.ServerProcess(threads=1) as c:
        addresses = [a.address, b.address, c.address]
        expected, failovers, _ = _run(addresses)
        assert failovers == 0
        with caplog.at_level(logging.WARNING, logger="multi_lunar_lander"):
            got, failovers, env_addresses = _run(addresses, kill=b)
        assert failovers == 1
        assert b.address not in env_addresses
        assert sum(b.address in r.getMessage() or "UNAVAILABLE" in r.getMessage() for r in caplog.records) == 1
        assert len(got) == len(expected)
        for index, (x, y) in enumerate(zip(got, expected)):
            assert same_bits(x, y), f"array {index} differs"
        assert sum(int(np.sum(x)) for x in got[7 : 2 + 10 * KILL_AT : 10]) > 0  # Auto-resets were replayed.


def test_failover_off_raises_unavailable():
    with mll.ServerProcess(threads=1) as a, mll.ServerProcess(threads=1) as d:
        vector = mll.vector_env(4, address=[a.address, d.address], n_landers=2, failover=False)
        assert not vector.failover
        vector.reset(seed=1)
        vector.step(np.zeros((4, 2), np.int32))
        os.kill(d.pid, signal.SIGKILL)
        d._process.wait(timeout=10)
        with pytest.raises(mll.MLLError) as raised:
            vector.step(np.zeros((4, 2), np.int32))
        assert raised.value.code == grpc.StatusCode.UNAVAILABLE
        vector.close()


def test_not_found_env_is_recreated_on_its_server(address, raw_stub):
    from multi_lunar_lander._stubs import pb

    vector = mll.vector_env(3, address=address, n_landers=2, failover=True)
    reference = mll.vector_env(3, address=address, n_landers=2)
    rng = np.random.default_rng(3)
    vector.reset(seed=9)
    reference.reset(seed=9)
    for step in range(40):
        if step == 20:
            raw_stub.DeleteEnv(pb.DeleteEnvRequest(name=vector.names[1]))
        actions = random_actions(rng, (3, 2), False)
        got, want = vector.step(actions), reference.step(actions)
        assert all(same_bits(x, y) for x, y in zip(got[:-1], want[:-1]))
    assert vector.failovers == 1 and vector.env_addresses == [address] * 3
    vector.close()
    reference.close()


def _parallel_steps(env, rng, steps):
    """Every array of `steps` random steps of a parallel env (reset at the episode's end)."""
    out = []
    for _ in range(steps):
        if not env.agents:
            observations, _ = env.reset()
            out.extend(observations[a] for a in sorted(observations))
            continue
        actions = {a: int(rng.integers(0, 4)) for a in env.agents}
        for part in env.step(actions)[:4]:
            out.extend(np.asarray(part[a]) for a in sorted(part))
    return out


def test_parallel_snapshot_restores_on_another_server_process(address):
    with mll.ServerProcess(threads=1) as other:
        env = mll.parallel_env(address=address, n_landers=2)
        env.reset(seed=11)
        _parallel_steps(env, np.random.default_rng(1), 150)  # Crosses episode ends (unseeded resets).
        snapshot = env.snapshot()
        assert snapshot[:4] == b"MLLS"
        elsewhere = mll.parallel_env(address=other.address, n_landers=2)
        restored = elsewhere.restore(snapshot)
        assert sorted(restored) == sorted(env.agents) == sorted(elsewhere.agents)
        twin = env.clone()
        expected = _parallel_steps(env, np.random.default_rng(2), 60)
        for copy in (elsewhere, twin):
            got = _parallel_steps(copy, np.random.default_rng(2), 60)
            assert len(got) == len(expected) and all(same_bits(x, y) for x, y in zip(got, expected))
        for e in (env, elsewhere, twin):
            e.close()


def test_vector_env_snapshot_moves_an_env_between_server_processes(address):
    with mll.ServerProcess(threads=1) as other:
        vector = mll.vector_env(3, address=address, n_landers=2, max_cycles=40)
        target = mll.vector_env(3, address=other.address, n_landers=2, max_cycles=40)
        rng = np.random.default_rng(4)
        vector.reset(seed=21)
        target.reset(seed=99)
        for _ in range(70):  # Past max_cycles: auto-resets in the record.
            last = vector.step(random_actions(rng, (3, 2), False))[0]
        observations = target.restore_env(2, vector.env_snapshot(1))
        assert same_bits(observations, last[1])
        for _ in range(50):
            actions = random_actions(rng, (3, 2), False)
            want = vector.step(actions)
            got = target.step(actions[[0, 2, 1]])
            assert all(same_bits(g[2], w[1]) for g, w in zip(got[:5], want[:5]))
        vector.close()
        target.close()


def test_a_damaged_snapshot_is_refused_and_the_env_untouched(address):
    env = mll.parallel_env(address=address, n_landers=2)
    reference = mll.parallel_env(address=address, n_landers=2)
    for e in (env, reference):
        e.reset(seed=3)
        _parallel_steps(e, np.random.default_rng(5), 10)
    snapshot = env.snapshot()
    name = env.name
    flipped = bytearray(snapshot)
    flipped[len(snapshot) // 2] ^= 0x10
    other_options = mll.parallel_env(address=address, n_landers=3)
    other_options.reset(seed=3)
    cases = {
        "damaged": bytes(flipped),
        "damaged|truncated": snapshot[:-9],
        "MLLS": b"NOPE" + snapshot[4:],
        "other options": other_options.snapshot(),
        "bytes": "not bytes",
    }
    for match, bad in cases.items():
        with pytest.raises(mll.MLLError, match=match) as raised:
            env.restore(bad)
        assert raised.value.code == grpc.StatusCode.INVALID_ARGUMENT
    assert env.name == name
    got = _parallel_steps(env, np.random.default_rng(6), 30)
    want = _parallel_steps(reference, np.random.default_rng(6), 30)
    assert all(same_bits(x, y) for x, y in zip(got, want))
    with pytest.raises(mll.MLLError) as raised:
        mll.parallel_env(address=address).snapshot()
    assert raised.value.code == grpc.StatusCode.FAILED_PRECONDITION
    for e in (env, reference, other_options):
        e.close()


def _with_protocol(snapshot: bytes, major: int, minor: int) -> bytes:
    """`snapshot` as a server of wire protocol major.minor would have written it (CRC-32 renewed)."""
    body = bytearray(snapshot[:-4])
    body[6:10] = struct.pack("<HH", major, minor)  # After b"MLLS" and the u16 format version.
    return bytes(body) + struct.pack("<I", zlib.crc32(body))


def test_a_snapshot_from_another_protocol_major_is_refused_naming_both(address):
    """A snapshot says which wire protocol its server spoke; another major is refused before any
    replay (the env untouched), the same major with another minor restores."""
    env = mll.parallel_env(address=address, n_landers=2)
    env.reset(seed=3)
    _parallel_steps(env, np.random.default_rng(5), 10)
    snapshot, name = env.snapshot(), env.name
    major, minor = env.server_info.protocol
    with pytest.raises(mll.MLLError, match=rf"wire protocol {major + 1}\.0 .* speaks {major}\.{minor}") as raised:
        env.restore(_with_protocol(snapshot, major + 1, 0))
    assert raised.value.code == grpc.StatusCode.INVALID_ARGUMENT and env.name == name
    vector = mll.vector_env(2, address=address, n_landers=2)
    vector.reset(seed=1)
    with pytest.raises(mll.MLLError, match="restore it on a server of protocol") as raised:
        vector.restore_env(1, _with_protocol(snapshot, major + 1, 0))
    assert raised.value.code == grpc.StatusCode.INVALID_ARGUMENT
    same_minor = vector.restore_env(0, snapshot)
    other_minor = vector.restore_env(1, _with_protocol(snapshot, major, minor + 1))
    assert same_bits(other_minor, same_minor) and np.abs(same_minor).sum() > 0
    vector.close()
    env.close()
