"""Several servers: envs pinned to one server each, vector_env spread over the servers by their
load with one StepBatch per server, and the same bits as on one server (whether a
server listens on TCP or on a Unix-domain socket)."""

import subprocess
import tempfile

import grpc
import numpy as np
import pytest

import multi_lunar_lander as mll
from multi_lunar_lander._stubs import pb, pb_grpc
from mll_test_helpers import listed_names, metric, metrics_url, rollout


@pytest.fixture(scope="module")
def two_servers():
    with mll.ServerProcess(threads=1) as first, mll.ServerProcess(threads=1) as second:
        yield first.address, second.address


@pytest.fixture(scope="module")
def unix_server():
    """A server on a Unix-domain socket, as the embedded one is."""
    with mll.ServerProcess(threads=2, unix_socket=True) as process:
        yield process.address


def test_a_socket_path_too_long_for_a_unix_socket_is_invalid_argument(monkeypatch, tmp_path):
    long_dir = tmp_path / ("d" * 100)
    long_dir.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(long_dir))
    with pytest.raises(mll.MLLError) as caught:
        mll.ServerProcess(unix_socket=True)
    assert caught.value.code == grpc.StatusCode.INVALID_ARGUMENT
    assert "longer than 107 bytes" in caught.value.message and str(long_dir) in caught.value.message
    assert list(long_dir.iterdir()) == []  # Its work directory is removed.


def test_vector_env_spreads_envs_by_load_over_the_servers(two_servers):
    first, second = two_servers
    before = listed_names(first), listed_names(second)
    vector = mll.vector_env(5, address=[first, second], n_landers=2)
    assert vector.addresses == [first, second] and vector.address == f"{first},{second}"
    # Water-filling on what each server hosts (the two have the same --max_envs): each env to the
    # one holding fewer, the first on a tie; each server's envs a run of consecutive indices.
    hosted, placed = [len(before[0]), len(before[1])], [0, 0]
    for _ in range(5):
        server = 0 if hosted[0] + placed[0] <= hosted[1] + placed[1] else 1
        placed[server] += 1
    assert vector.env_addresses == [first] * placed[0] + [second] * placed[1]
    names = vector.names
    assert listed_names(first) - before[0] == set(names[: placed[0]])
    assert listed_names(second) - before[1] == set(names[placed[0] :])
    vector.close()
    assert listed_names(first) == before[0] and listed_names(second) == before[1]


@pytest.mark.skipif(
    "--metrics_address" not in subprocess.run(
        [mll.find_server_binary(), "--help"], capture_output=True, text=True, timeout=30
    ).stdout,
    reason="this mll_server has no --metrics_address flag",
)
def test_each_step_is_one_step_batch_per_server_on_its_session_stream():
    flags = ("--metrics_address=127.0.0.1:0",)
    with mll.ServerProcess(threads=1, extra_args=flags) as a, mll.ServerProcess(threads=1, extra_args=flags) as b:
        vector = mll.vector_env(5, address=[a.address, b.address], n_landers=2)
        observations, _ = vector.reset(seed=4)
        for _ in range(7):
            observations = vector.step(mll.heuristic(observations))[0]
        # A session attached to shared memory has one request more: the attach.
        attach = 1 if vector.transport == "shared_memory" else 0
        vector.close()
        for process, envs in ((a, 3), (b, 2)):
            url = metrics_url(process)
            # Each step is one request on the server's Session, a StepBatch of its envs; each env
            # was created and reset there too (one request each), none by a unary call.
            assert metric(url, 'mll_rpc_duration_seconds_count{method="Session"}') == 7 + attach + 2 * envs
            assert metric(url, 'mll_steps_total{method="Session"}') == 7 * envs
            for method in ("StepBatch", "CreateEnv", "ResetEnv"):
                assert metric(url, f'mll_rpc_duration_seconds_count{{method="{method}"}}') == 0


@pytest.mark.parametrize("spec", ["list", "comma_string", "unix_socket_and_tcp"])
def test_two_servers_give_the_same_bits_as_one(address, two_servers, unix_server, continuous, spec):
    # max_cycles 40 over 90 steps: episodes end and auto-reset on both layouts.
    options = dict(n_landers=3, continuous=continuous, max_cycles=40)
    servers = [unix_server, two_servers[1]] if spec == "unix_socket_and_tcp" else list(two_servers)
    spread = mll.vector_env(6, address=servers if spec != "comma_string" else ",".join(servers), **options)
    single = mll.vector_env(6, address=address, **options)
    assert set(spread.env_addresses) == set(servers) and set(single.env_addresses) == {address}
    ours, reference = rollout(spread, 11, 90), rollout(single, 11, 90)
    assert len(ours) == len(reference)
    for got, expected in zip(ours, reference):
        assert got.dtype == expected.dtype
        np.testing.assert_array_equal(got, expected)
    spread.close()
    single.close()


def test_more_servers_than_envs_uses_the_least_loaded(two_servers, address):
    servers = [*two_servers, address]
    hosted = [len(listed_names(server)) for server in servers]
    vector = mll.vector_env(1, address=servers)
    assert vector.addresses == servers
    # The same --max_envs everywhere: the server hosting fewest, the first of those on a tie.
    assert vector.env_addresses == [servers[hosted.index(min(hosted))]]
    vector.close()


def test_an_item_error_names_the_env_in_env_order(two_servers):
    vector = mll.vector_env(4, address=list(two_servers), n_landers=1, failover=False)  # Else recreated.
    vector.reset(seed=0)
    # Behind the client's back: env 2 (first server) and env 1 (second server) go away.
    for index in (2, 1):
        with grpc.insecure_channel(vector.env_addresses[index]) as channel:
            pb_grpc.MultiLunarLanderStub(channel).DeleteEnv(pb.DeleteEnvRequest(name=vector.names[index]))
    with pytest.raises(mll.MLLError) as caught:
        vector.step(np.zeros((4, 1), np.int32))
    assert caught.value.code == grpc.StatusCode.NOT_FOUND
    assert caught.value.message.startswith(f"env 1 ({vector.names[1]}): ")  # The first in env order.
    vector.close()


def test_single_envs_are_pinned_by_server_index_or_least_loaded(two_servers):
    first, second = two_servers
    pinned = mll.parallel_env(address=[first, second], server_index=1)
    assert pinned.address == second and pinned.name in listed_names(second)
    pinned.reset(seed=3)
    pinned.step({agent: 0 for agent in pinned.agents})  # Every call goes to its server.
    aec = mll.env(address=f"{first},{second}", server_index=0)
    assert aec.address == first and aec.name in listed_names(first)
    # Without server_index: the least-loaded server (same --max_envs: the one hosting fewer).
    spread = []
    for _ in range(4):
        hosted = {server: len(listed_names(server)) for server in (first, second)}
        spread.append(mll.parallel_env(address=(first, second)))
        assert hosted[spread[-1].address] == min(hosted.values()), (hosted, spread[-1].address)
    for env in [pinned, aec, *spread]:
        env.close()


@pytest.mark.parametrize("server_index", [2, -1, 0.5, True])
def test_bad_server_index_is_invalid_argument(two_servers, server_index):
    with pytest.raises(mll.MLLError) as caught:
        mll.parallel_env(address=list(two_servers), server_index=server_index)
    assert caught.value.code == grpc.StatusCode.INVALID_ARGUMENT
    assert "server_index" in caught.value.message and "[0, 2)" in caught.value.message


@pytest.mark.parametrize("address", ["", [], ["127.0.0.1:1", ""], "a:1, ,b:2", [50051], 50051])
def test_bad_address_forms_are_invalid_argument(address):
    with pytest.raises(mll.MLLError) as caught:
        mll.vector_env(2, address=address)
    assert caught.value.code == grpc.StatusCode.INVALID_ARGUMENT
    assert "address" in caught.value.message


def test_an_unreachable_server_in_the_list_takes_no_envs(two_servers):
    first = two_servers[0]
    before = listed_names(first)
    # A server of the list that does not answer (a pod not up yet) gets none; failover may use it
    # once it answers.
    with mll.vector_env(4, address=[first, "127.0.0.1:1"], n_landers=1) as vector:
        assert vector.env_addresses == [first] * 4
        assert vector.failover
        vector.reset(seed=0)
    assert listed_names(first) == before
    # None answers: UNAVAILABLE naming one.
    with pytest.raises(mll.MLLError) as caught:
        mll.vector_env(4, address=["127.0.0.1:1", "127.0.0.1:2"])
    assert caught.value.code == grpc.StatusCode.UNAVAILABLE
    assert "127.0.0.1:1" in caught.value.message
