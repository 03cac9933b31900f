"""An elastic fleet behind one name, as a Kubernetes headless Service is (issue 45): servers on
several loopback addresses (127.0.0.2, 127.0.0.3, 127.0.0.4) share a port behind the name
`fleet.test`, which a hosts file maps to some of them. The vector env runs in a private mount
namespace whose /etc/hosts is that file (mll_test_helpers.run_with_hosts; skipped where unshare -m
is not permitted), and the scenario changes the name's addresses by rewriting the file in place.

Each scenario runs as a child process (this file run as a script, inside the namespace), starts its
own servers there, and prints one JSON line of what it measured; the tests check it. The trainer's
trajectories are compared with an undisturbed run's (the same actions, one server) to the bits.
"""

import json
import os
import pathlib
import sys
import time

import grpc
import numpy as np
import pytest

HERE = pathlib.Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))

import multi_lunar_lander as mll  # noqa: E402
from mll_test_helpers import (  # noqa: E402
    free_port_on,
    listed_names,
    quota_and_roomy_servers,
    run_with_hosts,
    server_at,
    write_hosts,
)

NAME = "fleet.test"
HOSTS = ("127.0.0.2", "127.0.0.3", "127.0.0.4")
NUM_ENVS = 48
LANDERS = 2
JOIN_WITHIN_S = 30  # The bound: from the joining server's SERVING to >= 12 envs on it.
SCENARIO_TIMEOUT_S = 150


def _actions(step):
    """The actions of step `step`: the same for the trainer and its undisturbed twin."""
    return np.random.default_rng(step).integers(0, 4, size=(NUM_ENVS, LANDERS), dtype=np.int32)


class _Trajectory:
    """Every array a run of the vector env returned, step after step."""

    def __init__(self):
        self.columns = {"observations": [], "rewards": [], "terminations": [], "truncations": []}

    def add(self, observations, rewards=None, terminations=None, truncations=None):
        for key, value in zip(self.columns, (observations, rewards, terminations, truncations)):
            if value is not None:
                self.columns[key].append(np.array(value, copy=True))

    def equal(self, other):
        """The first column that differs from `other`'s, or None."""
        for key, values in self.columns.items():
            mine, theirs = np.stack(values), np.stack(other.columns[key])
            if mine.shape != theirs.shape or mine.tobytes() != theirs.tobytes():
                return key
        return None


def _undisturbed(address, steps, seed):
    """The trajectory of `steps` steps of a vector env alone on `address`."""
    vector = mll.vector_env(NUM_ENVS, address=address, n_landers=LANDERS)
    try:
        trajectory = _Trajectory()
        trajectory.add(vector.reset(seed=seed)[0])
        for step in range(steps):
            trajectory.add(*vector.step(_actions(step))[:4])
        return trajectory
    finally:
        vector.close()


def _hosted(port):
    """How many envs each server holds (ListEnvs), by host; 0 for one that is not up."""
    counts = {}
    for host in HOSTS:
        try:
            counts[host] = len(listed_names(f"{host}:{port}"))
        except grpc.RpcError as error:
            assert error.code() == grpc.StatusCode.UNAVAILABLE, error
            counts[host] = 0
    return counts


def _scenario_join(hosts_file, port):
    """48 envs over two servers of the name; a third joins it: when does it hold >= 12? With the
    default rediscover interval (10 s), as a trainer that sets nothing runs."""
    seed = 11
    with server_at(HOSTS[0], port), server_at(HOSTS[1], port):
        write_hosts(hosts_file, {NAME: HOSTS[:2]})
        vector = mll.vector_env(NUM_ENVS, address=f"{NAME}:{port}", n_landers=LANDERS)
        try:
            trajectory = _Trajectory()
            trajectory.add(vector.reset(seed=seed)[0])
            before = _hosted(port)
            step = 0
            for step in range(50):
                trajectory.add(*vector.step(_actions(step))[:4])
            with server_at(HOSTS[2], port):
                serving = time.monotonic()  # server_at returns once its health check says SERVING.
                write_hosts(hosts_file, {NAME: HOSTS})
                joined_after_s, hosted = None, {}
                # Bounded in steps and in time: the trainer steps on until the new server holds
                # its share, then 30 steps more.
                while step < 100000 and time.monotonic() - serving < JOIN_WITHIN_S + 10:
                    step += 1
                    trajectory.add(*vector.step(_actions(step))[:4])
                    hosted = _hosted(port)
                    if hosted[HOSTS[2]] >= NUM_ENVS // 4:
                        joined_after_s = time.monotonic() - serving
                        break
                for _ in range(30):
                    step += 1
                    trajectory.add(*vector.step(_actions(step))[:4])
                after = _hosted(port)
                result = dict(
                    before=before,
                    hosted_at_join=hosted,
                    after=after,
                    joined_after_s=joined_after_s,
                    rebalances=vector.rebalances,
                    failovers=vector.failovers,
                    steps=step + 1,
                    env_addresses=vector.env_addresses,
                )
        finally:
            vector.close()
        reference = _undisturbed(f"{HOSTS[0]}:{port}", step + 1, seed)
    result["differs"] = trajectory.equal(reference)
    return result


def _scenario_leave(hosts_file, port):
    """Three servers in the name; one leaves it while up, then another dies: the failover puts
    nothing on the one that left, which keeps its envs."""
    seed = 5
    with server_at(HOSTS[0], port) as first, server_at(HOSTS[1], port), server_at(HOSTS[2], port):
        write_hosts(hosts_file, {NAME: HOSTS})
        vector = mll.vector_env(NUM_ENVS, address=f"{NAME}:{port}", n_landers=LANDERS, rediscover_interval_s=1)
        try:
            trajectory = _Trajectory()
            trajectory.add(vector.reset(seed=seed)[0])
            before = _hosted(port)
            step = 0
            for step in range(40):
                trajectory.add(*vector.step(_actions(step))[:4])
            write_hosts(hosts_file, {NAME: HOSTS[:2]})
            # Steps on for a few rediscovery intervals with the server out of the name and up.
            left = time.monotonic()
            while time.monotonic() - left < 3 and step < 100000:
                step += 1
                trajectory.add(*vector.step(_actions(step))[:4])
            while_left = _hosted(port)
            first.kill()
            first.wait(timeout=10)
            for _ in range(40):
                step += 1
                trajectory.add(*vector.step(_actions(step))[:4])
            after = _hosted(port)
            result = dict(
                before=before,
                while_left=while_left,
                after=after,
                failovers=vector.failovers,
                rebalances=vector.rebalances,
                steps=step + 1,
            )
        finally:
            vector.close()
        reference = _undisturbed(f"{HOSTS[1]}:{port}", step + 1, seed)
    result["differs"] = trajectory.equal(reference)
    return result


def _scenario_all_gone(hosts_file, port):
    """Every server of the name gone (from the name, and down): the error names the name."""
    with server_at(HOSTS[0], port) as first, server_at(HOSTS[1], port) as second:
        write_hosts(hosts_file, {NAME: HOSTS[:2]})
        vector = mll.vector_env(8, address=f"{NAME}:{port}", n_landers=LANDERS, rediscover_interval_s=1)
        try:
            vector.reset(seed=1)
            vector.step(np.zeros((8, LANDERS), dtype=np.int32))
            write_hosts(hosts_file, {})
            for process in (first, second):
                process.kill()
                process.wait(timeout=10)
            started = time.monotonic()
            try:
                vector.step(np.zeros((8, LANDERS), dtype=np.int32))
                error = None
            except mll.MLLError as caught:
                error = dict(code=caught.code.name, message=caught.message)
            return dict(error=error, seconds=time.monotonic() - started)
        finally:
            vector.close()


SCENARIOS = {"join": _scenario_join, "leave": _scenario_leave, "all_gone": _scenario_all_gone}


def _run(scenario, tmp_path):
    hosts_file = tmp_path / "hosts"
    write_hosts(hosts_file, {})
    completed = run_with_hosts(
        hosts_file, [sys.executable, __file__, scenario, hosts_file], timeout_s=SCENARIO_TIMEOUT_S
    )
    lines = [line for line in completed.stdout.splitlines() if line.startswith("{")]
    assert completed.returncode == 0 and lines, f"exit {completed.returncode}:\n{completed.stdout[-6000:]}"
    return json.loads(lines[-1]), completed.stdout


def test_a_server_that_joins_the_name_takes_its_share_within_30_s_to_the_same_bits(tmp_path):
    result, log = _run("join", tmp_path)
    port_free = [host for host, count in result["before"].items() if count]
    # Two servers in the name: all 48 envs there, evenly, none on the third (not up yet).
    assert sorted(port_free) == sorted(HOSTS[:2]), result
    assert result["before"][HOSTS[0]] == result["before"][HOSTS[1]] == NUM_ENVS // 2, result
    assert result["joined_after_s"] is not None, f"the joined server never held {NUM_ENVS // 4}:\n{result}\n{log}"
    assert result["joined_after_s"] < JOIN_WITHIN_S, result
    # Even within one env per server, and no failover: a move is not a loss.
    assert sorted(result["after"].values()) == [NUM_ENVS // 3] * 3, result
    assert result["failovers"] == 0 and result["rebalances"] >= 1, result
    assert "VectorEnv rebalance: " in log and "moved onto 127.0.0.4" in log, log
    assert result["differs"] is None, f"{result['differs']} differ from the undisturbed run's"


def test_a_server_that_leaves_the_name_keeps_its_envs_and_gets_no_new_ones(tmp_path):
    result, log = _run("leave", tmp_path)
    assert sorted(result["before"].values()) == [NUM_ENVS // 3] * 3, result
    # Out of the name and up: its envs stay.
    assert result["while_left"] == result["before"], result
    # The first server died: its envs went to the second (in the name), none to the third.
    assert result["after"] == {HOSTS[0]: 0, HOSTS[1]: 2 * NUM_ENVS // 3, HOSTS[2]: NUM_ENVS // 3}, result
    assert result["failovers"] == 1 and result["rebalances"] == 0, result
    assert result["differs"] is None, f"{result['differs']} differ from the undisturbed run's"


def test_every_server_of_the_name_gone_is_unavailable_naming_the_name(tmp_path):
    result, _ = _run("all_gone", tmp_path)
    error = result["error"]
    assert error is not None and error["code"] == "UNAVAILABLE", result
    assert f"{NAME}:" in error["message"] and "resolves to no address" in error["message"], error
    assert "127.0.0.2" in error["message"] and "127.0.0.3" in error["message"], error


def test_placement_puts_new_envs_beside_a_half_full_server_first():
    """One server already hosts half its max_envs of another tenant's envs: a new vector env's
    envs go to the other servers first (water-filling, by what GetServerInfo reports)."""
    port = free_port_on(*HOSTS)
    limit = ("--max_envs=40",)
    with server_at(HOSTS[0], port, limit), server_at(HOSTS[1], port, limit), server_at(HOSTS[2], port, limit):
        tenant = mll.vector_env(20, address=f"{HOSTS[0]}:{port}", n_landers=1)
        try:
            addresses = ",".join(f"{host}:{port}" for host in HOSTS)
            vector = mll.vector_env(24, address=addresses, n_landers=1)
            try:
                placed = [address.rsplit(":", 1)[0] for address in vector.env_addresses]
                assert placed.count(HOSTS[0]) == 0, placed
                assert placed.count(HOSTS[1]) == placed.count(HOSTS[2]) == 12, placed
                # 46 more: 8 each to the others (20 each, as the tenant's server), then the three
                # fill together (10 each).
                more = mll.vector_env(46, address=addresses, n_landers=1)
                try:
                    assert _hosted(port) == {HOSTS[0]: 30, HOSTS[1]: 30, HOSTS[2]: 30}, _hosted(port)
                finally:
                    more.close()
            finally:
                vector.close()
        finally:
            tenant.close()


def test_a_token_quota_reached_on_one_server_moves_the_rest_to_the_others(tmp_path):
    """Placement plans by envs hosted against --max_envs; a server whose per-token quota is lower
    answers RESOURCE_EXHAUSTED past it, and the envs it refused go to the server with room."""
    small, large = quota_and_roomy_servers(tmp_path, ["tenant-a"], max_envs_per_token=4)
    with small, large:
        addresses = [small.address, large.address]
        with mll.vector_env(12, address=addresses, token="tenant-a", n_landers=1) as vector:
            placed = vector.env_addresses
            assert placed.count(small.address) == 4 and placed.count(large.address) == 8, placed
            vector.reset(seed=2)
            vector.step(np.zeros((12, 1), np.int32))
        # 25 envs, room for 24 (4 + 20): RESOURCE_EXHAUSTED naming the servers and the quota.
        with pytest.raises(mll.MLLError) as caught:
            mll.vector_env(25, address=addresses, token="tenant-a", n_landers=1)
        assert caught.value.code == grpc.StatusCode.RESOURCE_EXHAUSTED, caught.value
        assert "no room for" in caught.value.message and small.address in caught.value.message, caught.value


if __name__ == "__main__":
    # A scenario, inside the private mount namespace: its JSON line on stdout.
    scenario_name, hosts_path = sys.argv[1], pathlib.Path(sys.argv[2])
    scenario_port = free_port_on(*HOSTS)
    print(json.dumps(SCENARIOS[scenario_name](hosts_path, scenario_port)), flush=True)
    os._exit(0)


@pytest.mark.parametrize("value", [-1, float("nan"), float("inf"), "10", True])
def test_rediscover_interval_s_must_be_a_finite_number_of_seconds(value):
    with pytest.raises(mll.MLLError) as raised:
        mll.vector_env(2, address="127.0.0.1:1", rediscover_interval_s=value)
    assert raised.value.code == grpc.StatusCode.INVALID_ARGUMENT, raised.value
    assert "rediscover_interval_s is" in raised.value.message and "0 (never)" in raised.value.message
