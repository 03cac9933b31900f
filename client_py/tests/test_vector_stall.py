"""A stalled server costs a Python vector env one bounded pause (issue 44's report, as a trainer
meets it): vector_env(24, n_landers=3) over three servers, 300 seeded steps, one server stopped
with SIGSTOP at step 100 (its sockets stay open; it answers nothing). The step that meets it waits
its deadline, the engine fails that server's envs over by replay, and every env's results are
the bits of an undisturbed run; resumed, the stopped server holds none of the abandoned envs once
their lease ends. Sync steps and EnvPool's send/recv, over shared memory and the native stream."""

import contextlib
import logging
import time

import numpy as np
import pytest

import multi_lunar_lander as mll
from multi_lunar_lander import _channel
from mll_test_helpers import holds_no_env_within, same_bits, stopped

NUM_ENVS, N_LANDERS, STEPS, STOP_AT, SEED = 24, 3, 300, 100, 11
# The bound on the one pause: the deadline plus a generous allowance for the replay (a bound,
# not a measurement).
ALLOWANCE_S = 10


def _actions(env, count):
    """Env `env`'s actions for its step `count`: the same whatever order steps are sent in."""
    return np.random.default_rng([SEED, env, count]).integers(0, 4, N_LANDERS, dtype=np.int32)


def _sync_run(vector, stall):
    """Every array of a STEPS-step seeded run with step(); `stall()` is entered at STOP_AT.
    Returns (arrays, slowest step in seconds)."""
    observations, _ = vector.reset(seed=SEED)
    record, slowest = [observations], 0.0
    with contextlib.ExitStack() as stack:
        for step in range(STEPS):
            if step == STOP_AT:
                stack.enter_context(stall())
            actions = np.stack([_actions(env, step) for env in range(NUM_ENVS)])
            with _timed() as took:
                result = vector.step(actions)
            slowest = max(slowest, took())
            record.extend(result[:-1])
            record.extend(result[-1][key] for key in sorted(result[-1]))
    return record, slowest


def _send_recv_run(vector, stall):
    """Each env's results, in its own order, over a send/recv run (batch_size 8): STEPS recvs,
    each sending the received envs their next actions; `stall()` is entered at recv STOP_AT.
    Returns ({env: arrays}, slowest recv in seconds)."""
    vector.async_reset(seed=SEED)
    steps = np.zeros(NUM_ENVS, int)
    record, slowest = {env: [] for env in range(NUM_ENVS)}, 0.0
    with contextlib.ExitStack() as stack:
        for call in range(STEPS):
            if call == STOP_AT:
                stack.enter_context(stall())
            with _timed() as took:
                observations, rewards, terminations, truncations, active, infos = vector.recv()
            slowest = max(slowest, took())
            ids = infos["env_id"]
            for row, env in enumerate(ids):
                record[int(env)].extend(
                    (observations[row], rewards[row], terminations[row], truncations[row], active[row])
                )
            vector.send(np.stack([_actions(int(env), steps[env]) for env in ids]), ids)
            steps[ids] += 1
    return record, slowest


@contextlib.contextmanager
def _timed():
    """`with _timed() as took:` ... then took() is the block's duration in seconds."""
    began, ended = time.monotonic(), []
    try:
        yield lambda: ended[0] - began
    finally:
        ended.append(time.monotonic())


def _same(got, expected):
    """Bit for bit. Per env (send/recv): which envs a recv returns depends on when answers come,
    so each env's results are compared as far as both runs got, which is past the stall (each
    env took about 100 steps, the stall came near its 33rd)."""
    if isinstance(expected, dict):
        assert got.keys() == expected.keys()
        for env in expected:
            common = min(len(got[env]), len(expected[env]))
            assert common >= 5 * 50, f"env {env}: {common // 5} steps in both runs"
            _same(got[env][:common], expected[env][:common])
        return
    assert len(got) == len(expected)
    for index, (x, y) in enumerate(zip(got, expected)):
        assert same_bits(x, y), f"array {index} differs"


@pytest.mark.parametrize("transport", ["shared_memory", "native"])
@pytest.mark.parametrize("mode", ["step", "send_recv"])
def test_a_stopped_server_of_three_costs_one_pause_and_no_bit(mode, transport, caplog):
    run = _sync_run if mode == "step" else _send_recv_run
    batch_size = NUM_ENVS if mode == "step" else 8
    with (
        mll.ServerProcess(threads=1) as a,
        mll.ServerProcess(threads=1, idle_timeout_s=2) as b,
        mll.ServerProcess(threads=1) as c,
    ):
        options = dict(
            address=[a.address, b.address, c.address], n_landers=N_LANDERS, transport=transport, batch_size=batch_size
        )
        with mll.vector_env(NUM_ENVS, **options) as undisturbed:
            expected, _ = run(undisturbed, contextlib.nullcontext)
            assert undisturbed.failovers == 0
        with mll.vector_env(NUM_ENVS, **options) as vector, caplog.at_level(logging.WARNING, "multi_lunar_lander"):
            got, slowest = run(vector, lambda: stopped(b))
            assert vector.failovers == 1 and b.address not in vector.env_addresses
            assert vector.transport == transport
        # The default deadline (5 s, plus 1 ms per lander action of the batch) was met and ended
        # the pause.
        assert _channel.DEFAULT_STEP_TIMEOUT_S <= slowest <= _channel.DEFAULT_STEP_TIMEOUT_S + ALLOWANCE_S
        warnings = [r.getMessage() for r in caplog.records if "failover" in r.getMessage()]
        assert len(warnings) == 1 and "DEADLINE_EXCEEDED" in warnings[0] and b.address in warnings[0], warnings
        _same(got, expected)
        # Resumed (stopped() continues it), the server reclaims the abandoned envs: the client's
        # cancelled session deletes them, or their 2 s lease ends.
        assert holds_no_env_within(b.address, 30)


def test_failover_off_the_only_server_stopped_raises_deadline_exceeded_within_the_timeout():
    with mll.ServerProcess(threads=1) as server:
        vector = mll.vector_env(4, address=server.address, n_landers=2, step_timeout_s=1.5)
        assert not vector.failover
        vector.reset(seed=1)
        with stopped(server), pytest.raises(mll.MLLError) as raised, _timed() as took:
            vector.step(np.zeros((4, 2), np.int32))
        assert raised.value.code.name == "DEADLINE_EXCEEDED"
        assert server.address in raised.value.message and "1.5" in raised.value.message, raised.value.message
        assert 1.5 <= took() <= 1.5 + 5
        vector.close()


@pytest.mark.parametrize("transport", ["shared_memory", "native"])
def test_close_with_the_server_stopped_returns_within_the_step_timeout_and_the_envs_go_later(transport):
    # close() waits for the server to end each stream only up to the step timeout (at most 2 s),
    # then cancels it; resumed, the server deletes the cancelled session's envs.
    with mll.ServerProcess(threads=1) as server:
        vector = mll.vector_env(4, address=server.address, transport=transport, step_timeout_s=1.0)
        vector.reset(seed=1)
        with stopped(server), _timed() as took:
            vector.close()
        assert 1.0 <= took() <= 1.0 + ALLOWANCE_S
        assert holds_no_env_within(server.address, 30)


def test_computing_between_step_async_and_step_wait_longer_than_the_deadline_and_a_keepalive_round(address):
    """A trainer may compute for long between step_async and step_wait: the deadline counts from
    when it starts waiting (the answer came meanwhile and is read then), and the engine does not
    close the connection over the keepalive ping whose acknowledgement it reads only then (32 s:
    a ping every 20 s, grpcio's 10 s wait for its ack, and 2 s more). Both transports at once."""
    actions = np.zeros((3, 2), np.int32)
    with contextlib.ExitStack() as stack:
        pairs = []
        for transport in ("shared_memory", "native"):
            options = dict(address=address, n_landers=2, transport=transport, step_timeout_s=1)
            vector, reference = (stack.enter_context(mll.vector_env(3, **options)) for _ in range(2))
            assert vector.transport == transport
            vector.reset(seed=4)
            reference.reset(seed=4)
            vector.step_async(actions)
            pairs.append((vector, reference))
        time.sleep(32)
        for vector, reference in pairs:
            got = vector.step_wait()
            expected = reference.step(actions)
            for x, y in zip(got[:-1], expected[:-1]):
                assert same_bits(x, y)
            assert vector.failovers == 0
            assert same_bits(vector.step(actions)[0], reference.step(actions)[0])
