"""Failover of the PettingZoo envs (issue "A fleet that loses no episode"): a parallel or AEC env
whose server dies (kill -9), drains (SIGTERM), stalls (SIGSTOP: it answers nothing within
step_timeout_s), or loses it goes on from its record on a reachable server; every turn shows the
bits of an env that ran without the fault, with the same seed and actions. Each test drives the env
in lockstep with such a reference env."""

import contextlib
import logging
import os
import pathlib
import pickle
import re
import signal
import time

import grpc
import numpy as np
import pytest

import multi_lunar_lander as mll
from multi_lunar_lander import _channel
from multi_lunar_lander._stubs import pb
from mll_test_helpers import holds_no_env_within, stopped

KINDS = {"parallel": mll.parallel_env, "aec": mll.env}


def _parallel_turn(env, reference, rng):
    """One step of both envs with the same random actions (a reset at the episode's end);
    what each returned, with its agents and PettingZoo state."""
    if not reference.agents:
        results = env.reset(), reference.reset()
    else:
        actions = {agent: int(rng.integers(0, 4)) for agent in reference.agents}
        results = env.step(actions), reference.step(actions)
    return [(result, e.agents, e.state()) for result, e in zip(results, (env, reference))]


def _aec_view(env):
    """Everything a PettingZoo trainer reads of an AEC env after a turn."""
    return (
        env.agent_selection if env.agents else None,
        list(env.agents),
        env.last() if env.agents else None,
        dict(env.rewards),
        dict(env._cumulative_rewards),
        dict(env.terminations),
        dict(env.truncations),
        dict(env.infos),
        [env.observe(agent) for agent in env.possible_agents],
        env.state(),
    )


def _aec_turn(env, reference, rng):
    """One turn of both envs (agent_selection's random action, or its dead step; a reset at the
    episode's end); what a trainer reads of each afterwards."""
    if not reference.agents:
        env.reset()
        reference.reset()
    else:
        _, _, terminated, truncated, _ = reference.last()
        action = None if terminated or truncated else int(rng.integers(0, 4))
        env.step(action)
        reference.step(action)
    return [_aec_view(env), _aec_view(reference)]


TURNS = {"parallel": _parallel_turn, "aec": _aec_turn}


def _lockstep(kind, env, reference, turns, fault_at=None, fault=None, seed=7):
    """`turns` turns of `env` and `reference` with the same seed and actions, fault() called
    before turn `fault_at` (mid-episode); asserts every turn shows the same bits in both
    (pickled: -0.0 and 0.0 differ). Returns the longest turn's seconds."""
    rng = np.random.default_rng(seed)
    first = [e.reset(seed=seed) for e in (env, reference)]
    assert pickle.dumps(first[0]) == pickle.dumps(first[1])
    slowest = 0.0
    for turn in range(turns):
        if turn == fault_at:
            assert reference.agents, "the fault is meant to come mid-episode"
            fault()
        began = time.monotonic()
        got, want = TURNS[kind](env, reference, rng)
        slowest = max(slowest, time.monotonic() - began)
        assert pickle.dumps(got) == pickle.dumps(want), f"turn {turn} differs"
    return slowest


def _lockstep_on(kind, env, twin, turns=60):
    """`turns` more turns of both, as they are, with the same actions: the same bits."""
    rng = np.random.default_rng(11)
    for _ in range(turns):
        got, want = TURNS[kind](env, twin, rng)
        assert pickle.dumps(got) == pickle.dumps(want)


def _kill(server):
    os.kill(server.pid, signal.SIGKILL)
    server._process.wait(timeout=10)


def _failover_warnings(caplog):
    return [r.getMessage() for r in caplog.records if "failover" in r.getMessage()]


@pytest.mark.parametrize("kind", KINDS)
def test_kill_the_server_of_an_env_mid_episode(kind, caplog):
    with mll.ServerProcess(threads=1) as a, mll.ServerProcess(threads=1) as b, mll.ServerProcess(threads=1) as c:
        env = KINDS[kind](address=[a.address, b.address, c.address], server_index=1, n_landers=2)
        reference = KINDS[kind](address=a.address, n_landers=2)
        assert env.failover and env.failovers == 0 and env.address == b.address
        turns = 400 if kind == "parallel" else 800  # Past episode ends: unseeded resets replayed.
        with caplog.at_level(logging.WARNING, logger="multi_lunar_lander"):
            _lockstep(kind, env, reference, turns, fault_at=turns // 2 + 5, fault=lambda: _kill(b))
        assert env.failovers == 1
        assert env.address in (a.address, c.address)
        warnings = _failover_warnings(caplog)
        assert len(warnings) == 1 and "UNAVAILABLE" in warnings[0], warnings
        snapshot = env.snapshot()  # The record goes on past the failover.
        twin = KINDS[kind](address=c.address, n_landers=2)
        twin.restore(snapshot)
        _lockstep_on(kind, env, twin)
        for e in (env, reference, twin):
            e.close()


@pytest.mark.parametrize("kind", KINDS)
def test_failover_off_raises_unavailable(kind):
    with mll.ServerProcess(threads=1) as a, mll.ServerProcess(threads=1) as d:
        env = KINDS[kind](address=[a.address, d.address], server_index=1, n_landers=2, failover=False)
        assert not env.failover
        env.reset(seed=1)
        _kill(d)
        with pytest.raises(mll.MLLError) as raised:
            if kind == "parallel":
                env.step({agent: 0 for agent in env.agents})
            else:
                env.step(0)
        assert raised.value.code == grpc.StatusCode.UNAVAILABLE
        assert env.failovers == 0
        env.close()


@pytest.mark.parametrize("kind", KINDS)
def test_the_embedded_server_killed_is_restarted_and_the_env_replayed(kind, address):
    env = KINDS[kind](n_landers=2)  # address=None: the embedded server.
    reference = KINDS[kind](address=address, n_landers=2)
    assert env.failover
    killed = mll.embedded_server()
    _lockstep(kind, env, reference, 160, fault_at=60, fault=lambda: _kill(killed))
    assert env.failovers == 1
    restarted = mll.embedded_server()
    assert restarted is not killed and restarted.running and env.address == restarted.address
    env.close()
    reference.close()
    assert mll.embedded_server() is None  # The restarted one stops with its last user.


@pytest.mark.parametrize("kind", KINDS)
def test_a_draining_server_moves_its_env_when_it_refuses_it(kind, caplog):
    """A draining server serves the envs it holds until its drain ends (calls on them are not new
    work), then refuses them: the env moves, passing over servers that drain too."""
    with (
        mll.ServerProcess(threads=1, extra_args=("--drain_s=1",)) as drained,
        mll.ServerProcess(threads=1, extra_args=("--drain_s=60",)) as draining,
        mll.ServerProcess(threads=1) as healthy,
    ):
        addresses = [drained.address, draining.address, healthy.address]
        env = KINDS[kind](address=addresses, server_index=0, n_landers=2)
        reference = KINDS[kind](address=draining.address, n_landers=2)  # Served while its server drains.
        rng = np.random.default_rng(3)
        env.reset(seed=3)
        reference.reset(seed=3)
        for _ in range(20):
            TURNS[kind](env, reference, rng)
        draining._process.send_signal(signal.SIGTERM)
        drained._process.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + 30
        with caplog.at_level(logging.WARNING, logger="multi_lunar_lander"):
            for _ in range(10_000):  # Until the drain of `drained` ends and the env moves.
                got, want = TURNS[kind](env, reference, rng)
                assert pickle.dumps(got) == pickle.dumps(want)
                if env.failovers or time.monotonic() > deadline:
                    break
                time.sleep(0.005)
        assert env.failovers == 1 and env.address == healthy.address
        assert drained._process.wait(timeout=15) == 0 and "drained in" in drained.log_tail()
        assert len(_failover_warnings(caplog)) == 1
        _lockstep_on(kind, env, reference, 30)
        env.close()
        reference.close()


@pytest.mark.parametrize("kind", KINDS)
def test_an_env_lost_by_its_server_is_recreated_there(kind, address, raw_stub):
    env = KINDS[kind](address=address, n_landers=2, failover=True)
    reference = KINDS[kind](address=address, n_landers=2)

    def delete():
        raw_stub.DeleteEnv(pb.DeleteEnvRequest(name=env.name))

    _lockstep(kind, env, reference, 80, fault_at=30, fault=delete)
    assert env.failovers == 1 and env.address == address
    env.close()
    reference.close()


def test_aec_snapshot_restores_clones_and_refuses_the_other_step_api(address):
    with mll.ServerProcess(threads=1) as other:
        env = mll.env(address=address, n_landers=3, continuous=True)
        env.reset(seed=5)
        rng = np.random.default_rng(8)
        for _ in range(31):  # Mid-cycle: some agents have acted since the world stepped.
            env.step(None if env.terminations[env.agent_selection] or env.truncations[env.agent_selection]
                     else rng.uniform(-1, 1, 2).astype(np.float32))
        snapshot = env.snapshot()
        assert snapshot[:4] == b"MLLS" and snapshot[4:6] == (2).to_bytes(2, "little")  # Format version 2.
        elsewhere = mll.env(address=other.address, n_landers=3, continuous=True)
        assert elsewhere.restore(snapshot) is None
        twin = env.clone()
        for copy in (elsewhere, twin):
            assert pickle.dumps(_aec_view(copy)) == pickle.dumps(_aec_view(env))
        for _ in range(40):
            action = None if env.terminations[env.agent_selection] or env.truncations[env.agent_selection] else (
                rng.uniform(-1, 1, 2).astype(np.float32))
            for e in (env, elsewhere, twin):
                e.step(action)
            assert pickle.dumps(_aec_view(elsewhere)) == pickle.dumps(_aec_view(env))
            assert pickle.dumps(_aec_view(twin)) == pickle.dumps(_aec_view(env))
            if not env.agents:
                break
        parallel = mll.parallel_env(address=address, n_landers=3, continuous=True)
        parallel.reset(seed=5)
        parallel.step({agent: np.zeros(2, np.float32) for agent in parallel.agents})
        for target, foreign in ((env, parallel.snapshot()), (parallel, snapshot)):
            with pytest.raises(mll.MLLError, match="other step API") as raised:
                target.restore(foreign)
            assert raised.value.code == grpc.StatusCode.INVALID_ARGUMENT
        for e in (env, elsewhere, twin, parallel):
            e.close()


# ------------------------------------------------------------------ stalls

# The bound on the one pause a stall costs: the deadline plus a generous allowance for the probe
# of the stalled server and the replay (a bound, not a measurement).
PAUSE_BOUND_S = _channel.DEFAULT_STEP_TIMEOUT_S + 10


@pytest.mark.parametrize("kind", KINDS)
def test_a_stopped_server_costs_one_pause_and_no_bit(kind, caplog):
    """Default step_timeout_s: the turn that meets the stopped server waits its deadline, then the
    env moves (one failover, DEADLINE_EXCEEDED) with every bit of a run without the fault. Resumed,
    the server reclaims the abandoned env by its lease (the client no longer renews it)."""
    with (
        mll.ServerProcess(threads=1) as a,
        mll.ServerProcess(threads=1, idle_timeout_s=2) as b,
        mll.ServerProcess(threads=1) as c,
    ):
        env = KINDS[kind](address=[a.address, b.address, c.address], server_index=1, n_landers=2)
        reference = KINDS[kind](address=a.address, n_landers=2)
        turns = 120 if kind == "parallel" else 240
        with caplog.at_level(logging.WARNING, logger="multi_lunar_lander"), contextlib.ExitStack() as stack:
            slowest = _lockstep(kind, env, reference, turns, turns // 2 + 5, lambda: stack.enter_context(stopped(b)))
            assert env.failovers == 1 and env.address in (a.address, c.address)
        assert _channel.DEFAULT_STEP_TIMEOUT_S <= slowest <= PAUSE_BOUND_S
        warnings = _failover_warnings(caplog)
        assert len(warnings) == 1 and "DEADLINE_EXCEEDED" in warnings[0] and b.address in warnings[0], warnings
        assert holds_no_env_within(b.address, 30)
        for e in (env, reference):
            e.close()


@pytest.mark.parametrize("kind", KINDS)
def test_failover_off_a_stopped_server_raises_deadline_exceeded_within_the_timeout(kind):
    with mll.ServerProcess(threads=1) as server:
        env = KINDS[kind](address=server.address, n_landers=2, step_timeout_s=1.5)
        assert not env.failover
        env.reset(seed=1)
        with stopped(server), pytest.raises(mll.MLLError) as raised:
            began = time.monotonic()
            try:
                env.step({agent: 0 for agent in env.agents} if kind == "parallel" else 0)
            finally:
                took = time.monotonic() - began
        assert raised.value.code == grpc.StatusCode.DEADLINE_EXCEEDED
        assert server.address in raised.value.message and "1.5 s" in raised.value.message, raised.value.message
        assert 1.5 <= took <= 1.5 + 5
        assert env.failovers == 0
        env.close()


@pytest.mark.parametrize("value", [-1, float("nan"), float("inf"), "5", True])
def test_step_timeout_s_must_be_a_finite_number_of_seconds(value, address):
    with pytest.raises(mll.MLLError) as raised:
        mll.parallel_env(address=address, step_timeout_s=value)
    assert raised.value.code == grpc.StatusCode.INVALID_ARGUMENT and "step_timeout_s" in raised.value.message


def test_deadline_and_keepalive_settings_are_the_cpp_clients():
    """step_timeout_s's default and the channels' keepalive are the C++ client's (and the keepalive
    is what the server's ping policy accepts: proto/include/mll/http2_keepalive.h)."""
    root = pathlib.Path(__file__).resolve().parents[2]
    types = (root / "client_cpp/include/mll/client_types.h").read_text()
    step_ms = int(re.search(r"std::chrono::milliseconds step_timeout\{(\d+)\};", types).group(1))
    assert _channel.DEFAULT_STEP_TIMEOUT_S == step_ms / 1000
    keepalive = (root / "proto/include/mll/http2_keepalive.h").read_text()

    def constant(name):
        return int(re.search(rf"inline constexpr int {name} = (\d+);", keepalive).group(1))

    options = dict(_channel.CHANNEL_OPTIONS)
    assert options["grpc.keepalive_time_ms"] == constant("kKeepaliveTimeMs")
    assert options["grpc.keepalive_timeout_ms"] == constant("kKeepaliveTimeoutMs")
    assert options["grpc.keepalive_permit_without_calls"] == 1
    assert options["grpc.http2.max_pings_without_data"] == 0
    assert constant("kKeepaliveMinReceivedPingIntervalMs") <= options["grpc.keepalive_time_ms"] // 2
