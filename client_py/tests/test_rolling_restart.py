"""A rolling restart under load (issue 29): each of three servers in turn gets SIGTERM (it
drains, --drain_s) and is replaced by a new process on the same port, while a trainer steps a
vector env over the three; the StatefulSet case of docs/deployment.md, where a replaced pod comes
back under its name. The trainer sees no error, its results are the bits of an uninterrupted
run, and its environments move back onto replaced servers at the next failover: they never all
pile onto one server, and end spread over the replacements."""

import logging
import re
import signal
import subprocess

import numpy as np
import pytest

import multi_lunar_lander as mll

from mll_test_helpers import listed_names, random_actions, same_bits, wait_draining

NUM_ENVS, STEPS = 12, 600
TERMINATE_AT = {100: 0, 250: 1, 400: 2}  # Step -> index of the server that gets SIGTERM.
DRAIN = ("--drain_s=1",)
DRAIN_EXIT_TIMEOUT_S = 30  # A drain of --drain_s=1 and an exit take well under a second.


def _server(port=None):
    return mll.ServerProcess(threads=1, extra_args=DRAIN + ((f"--address=127.0.0.1:{port}",) if port else ()))


def _port(server):
    return int(re.fullmatch(r"127\.0\.0\.1:(\d+)", server.address).group(1))


def _name(server):
    """The server's address as a host name that gRPC resolves, as a trainer gives a StatefulSet
    pod's DNS name (localhost stays 127.0.0.1: the name is covered, not a pod's new IP)."""
    return f"localhost:{_port(server)}"


def _replace_drained(servers, index, timeout_s=DRAIN_EXIT_TIMEOUT_S):
    """Waits for servers[index], which got SIGTERM, to finish its drain and exit 0 (within
    `timeout_s`), then starts its replacement on the same port."""
    old = servers[index]
    try:
        status = old._process.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        pytest.fail(f"the server on {old.address} had not exited {timeout_s} s after SIGTERM:\n{old.log_tail()}")
    assert status == 0 and "drained in" in old.log_tail(), f"exit status {status}:\n{old.log_tail()}"
    servers[index] = _server(_port(old))
    old.stop()


def _run(addresses, transport, servers=None, seed=3):
    """Every array of a STEPS-step seeded random run and the number of failovers; with `servers`
    (addresses[i] is servers[i]'s), the rolling restart: at each TERMINATE_AT step that server
    gets SIGTERM; once it has exited, a new one starts on its port. Third, at the end of a
    rolling restart: for each address, the names of the envs the vector env places there and
    the names its server lists (before the vector env's close deletes them); else None. Fourth,
    the most envs any one address held after a step."""
    vector = mll.vector_env(NUM_ENVS, address=addresses, n_landers=2, transport=transport)
    assert vector.transport == transport
    rng = np.random.default_rng(seed)
    observations, infos = vector.reset(seed=seed)
    record = [observations, infos["episode_length"]]
    draining = None  # The index of the server draining now.
    most_on_one = 0  # The most envs any one address held at a step.
    for step in range(STEPS):
        if servers is not None:
            if draining is not None and (step in TERMINATE_AT or not servers[draining].running):
                _replace_drained(servers, draining)
                draining = None
            if step in TERMINATE_AT:
                draining = TERMINATE_AT[step]
                servers[draining]._process.send_signal(signal.SIGTERM)
                wait_draining(servers[draining].address)  # The drain has begun: the next step sees it.
        result = vector.step(random_actions(rng, (NUM_ENVS, 2), False))
        most_on_one = max(most_on_one, max(vector.env_addresses.count(a) for a in set(vector.env_addresses)))
        record.extend(result[:-1])
        record.extend(result[-1][key] for key in sorted(result[-1]))
    if draining is not None:  # The last drain may outlast the run's steps (a fast machine).
        _replace_drained(servers, draining)
    placement = None
    if servers is not None:
        # By the address each server listens on (what a host name resolved to).
        placement = {server.address: (set(), listed_names(server.address)) for server in servers}
        for name, address in zip(vector.names, vector.env_addresses):
            placement[address][0].add(name)
    failovers = vector.failovers
    vector.close()
    return record, failovers, placement, most_on_one


# Sessions on gRPC C++'s stream, and on shared memory (Sessions attached to it are ended by the
# drain as well); servers given by IP address, and by host name.
@pytest.mark.parametrize(
    "transport, address_of",
    [("native", lambda server: server.address), ("shared_memory", lambda server: server.address), ("native", _name)],
    ids=["native", "shared_memory", "native-host-names"],
)
def test_rolling_restart_of_three_servers_under_load_loses_nothing(caplog, transport, address_of):
    servers = [_server(), _server(), _server()]
    originals = list(servers)
    try:
        addresses = [address_of(server) for server in servers]
        with caplog.at_level(logging.WARNING, logger="multi_lunar_lander"):
            got, failovers, placement, most_on_one = _run(addresses, transport, servers)
        assert failovers == len(TERMINATE_AT)
        moved = [r.getMessage() for r in caplog.records if "failover" in r.getMessage()]
        assert len(moved) == len(TERMINATE_AT) and all("draining: " in m for m in moved), moved
        # Every original process is gone, and the replacements hold exactly the envs the vector
        # env places on their addresses. A server replaced at its address takes envs again at the
        # next failover (the vector env probes the addresses it found down), so the envs never
        # pile onto the one server not yet restarted, and end spread over replacements.
        assert not any(server.running for server in originals)
        assert not set(servers) & set(originals)
        assert all(held == listed for held, listed in placement.values()), placement
        assert sum(len(held) for held, _ in placement.values()) == NUM_ENVS
        assert most_on_one < NUM_ENVS
        assert sum(1 for held, _ in placement.values() if held) >= 2, placement
        expected, failovers, _, _ = _run(addresses, transport)
        assert failovers == 0
        assert len(got) == len(expected)
        for index, (x, y) in enumerate(zip(got, expected)):
            assert same_bits(x, y), f"array {index} differs"
        assert sum(int(np.sum(x)) for x in got[7::10]) > 0  # Auto-resets happened (and were replayed).
    finally:
        for server in servers:
            server.stop()
