"""A rolling restart under load (issue 29): each of three servers in turn gets SIGTERM (it
drains, --drain_s) and is started again on the same port, while a trainer steps a vector env
over the three. The trainer sees no error, and its results are the bits of an uninterrupted
run."""

import logging
import re
import signal

import numpy as np
import pytest

import multi_lunar_lander as mll
from multi_lunar_lander import _native

from mll_test_helpers import random_actions, same_bits

NUM_ENVS, STEPS = 12, 600
TERMINATE_AT = {100: 0, 250: 1, 400: 2}  # Step -> index of the server that gets SIGTERM.
DRAIN = ("--drain_s=1",)


def _server(port=None):
    return mll.ServerProcess(threads=1, extra_args=DRAIN + ((f"--address=127.0.0.1:{port}",) if port else ()))


def _port(server):
    return int(re.fullmatch(r"127\.0\.0\.1:(\d+)", server.address).group(1))


def _run(addresses, transport, servers=None, seed=3):
    """Every array of a STEPS-step seeded random run; with `servers`, the rolling restart: at each
    TERMINATE_AT step that server gets SIGTERM; once it has exited, a new one starts on its port."""
    vector = mll.vector_env(NUM_ENVS, address=addresses, n_landers=2, transport=transport)
    assert transport == "grpc" or vector.transport == transport
    rng = np.random.default_rng(seed)
    observations, infos = vector.reset(seed=seed)
    record = [observations, infos["episode_length"]]
    draining = None  # The index of the server draining now.
    for step in range(STEPS):
        if servers is not None:
            if draining is not None and (step in TERMINATE_AT or not servers[draining].running):
                old = servers[draining]
                assert old._process.wait(timeout=30) == 0, old.log_tail()  # Drained, exited 0.
                assert "drained in" in old.log_tail()
                servers[draining] = _server(_port(old))
                old.stop()
                draining = None
            if step in TERMINATE_AT:
                draining = TERMINATE_AT[step]
                servers[draining]._process.send_signal(signal.SIGTERM)
        result = vector.step(random_actions(rng, (NUM_ENVS, 2), False))
        record.extend(result[:-1])
        record.extend(result[-1][key] for key in sorted(result[-1]))
    failovers = vector.failovers
    vector.close()
    return record, failovers


# Sessions on grpcio's stream, and on shared memory (the native library's; Sessions attached to
# it are ended by the drain as well).
@pytest.mark.parametrize("transport", ["grpc", "shared_memory"])
def test_rolling_restart_of_three_servers_under_load_loses_nothing(caplog, transport):
    if transport == "shared_memory" and not _native.available():
        pytest.skip("the native library is not built")
    servers = [_server(), _server(), _server()]
    try:
        addresses = [server.address for server in servers]
        with caplog.at_level(logging.WARNING, logger="multi_lunar_lander"):
            got, failovers = _run(addresses, transport, servers)
        assert failovers == len(TERMINATE_AT)
        moved = [r.getMessage() for r in caplog.records if "failover" in r.getMessage()]
        assert len(moved) == len(TERMINATE_AT) and all("draining: " in m for m in moved), moved
        expected, failovers = _run(addresses, transport)
        assert failovers == 0
        assert len(got) == len(expected)
        for index, (x, y) in enumerate(zip(got, expected)):
            assert same_bits(x, y), f"array {index} differs"
        assert sum(int(np.sum(x)) for x in got[7::10]) > 0  # Auto-resets happened (and were replayed).
    finally:
        for server in servers:
            server.stop()
