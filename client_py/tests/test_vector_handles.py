"""vector_env over batch handles (PackedSteps.handle, a server with "packed_batch_handles"): each
list of envs goes to its server's Session once, with its names, and then as a handle with the
actions, as the server's mll_packed_batches_total counts them; the results are the same bits as
parallel envs stepped by name; a restored env (new name) declares its list again."""

import numpy as np
import pytest

import multi_lunar_lander as mll

from mll_test_helpers import metric, metrics_url, random_actions, same_bits

TRANSPORTS = ["native", "shared_memory"]
NAMES = 'mll_packed_batches_total{envs="names"}'
HANDLE = 'mll_packed_batches_total{envs="handle"}'


@pytest.fixture(scope="module")
def server():
    with mll.ServerProcess(threads=2, extra_args=("--metrics_address=127.0.0.1:0",)) as process:
        yield process.address, metrics_url(process)


def counts(url):
    return metric(url, NAMES), metric(url, HANDLE)


def test_the_server_offers_handles(server):
    address, _ = server
    info = mll.server_info(address)
    assert "packed_batch_handles" in info.capabilities and info.protocol >= (1, 2)


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_each_list_is_declared_once_then_stepped_by_handle_with_the_same_bits(server, transport):
    address, url = server
    num_envs, n_landers, seed, steps = 3, 2, 70, 40
    options = dict(address=address, n_landers=n_landers, max_cycles=15)
    vector = mll.vector_env(num_envs, transport=transport, **options)
    singles = [mll.parallel_env(**options) for _ in range(num_envs)]
    agents = singles[0].possible_agents
    before = counts(url)
    vector.reset(seed=seed)
    for i, single in enumerate(singles):
        single.reset(seed=seed + i)
    rng = np.random.default_rng(4)
    auto_resets = 0
    for _ in range(steps):  # max_cycles 15: every env crosses auto-resets.
        actions = random_actions(rng, (num_envs, n_landers), False)
        observations, rewards, _, _, active, infos = vector.step(actions)
        for i, single in enumerate(singles):
            if not single.agents:
                expected, _ = single.reset()
                assert infos["auto_reset"][i]
                auto_resets += 1
                assert same_bits(observations[i], np.stack([expected[agent] for agent in agents]))
                continue
            expected, expected_rewards, _, _, _ = single.step(
                {agent: actions[i, k] for k, agent in enumerate(agents) if agent in single.agents}
            )
            for k, agent in enumerate(agents):
                if active[i, k]:
                    assert same_bits(observations[i, k], expected[agent])
                    assert same_bits(rewards[i, k], expected_rewards[agent])
    assert auto_resets >= num_envs
    names, handle = counts(url)
    assert (names - before[0], handle - before[1]) == (1, steps - 1)
    vector.close()
    for single in singles:
        single.close()


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_async_lists_are_declared_once_each(server, transport):
    address, url = server
    vector = mll.vector_env(6, address=address, transport=transport, n_landers=1, batch_size=3)
    before = counts(url)
    vector.async_reset(seed=1)
    rng = np.random.default_rng(5)
    lists = set()
    for _ in range(30):
        *_, infos = vector.recv()
        lists.add(tuple(infos["env_id"]))
        vector.send(random_actions(rng, (3, 1), False), infos["env_id"])
    for _ in range(2):
        vector.recv()
    names, handle = counts(url)
    sent = 29  # The first recv returns the reset's observations of the first 3 envs.
    assert names - before[0] <= len(lists) + 1  # Each list once (one sent again before its answer came).
    assert names - before[0] + handle - before[1] == sent + 1
    assert handle - before[1] >= sent + 1 - (len(lists) + 1)
    vector.close()


def test_a_restored_env_declares_the_list_again(server):
    address, url = server
    vector = mll.vector_env(2, address=address, n_landers=1)
    twin = mll.vector_env(2, address=address, n_landers=1)
    vector.reset(seed=9)
    twin.reset(seed=9)
    rng = np.random.default_rng(6)
    for _ in range(5):
        actions = random_actions(rng, (2, 1), False)
        vector.step(actions)
        twin.step(actions)
    snapshot = vector.env_snapshot(1)
    before = counts(url)
    vector.restore_env(1, snapshot)  # Env 1 is a new env (new name) at the same point.
    actions = random_actions(rng, (2, 1), False)
    assert same_bits(vector.step(actions)[0], twin.step(actions)[0])
    assert counts(url)[0] - before[0] == 1
    actions = random_actions(rng, (2, 1), False)
    assert same_bits(vector.step(actions)[0], twin.step(actions)[0])
    assert counts(url) == (before[0] + 1, before[1] + 1 + 2)  # The twin stepped by its handle twice.
    vector.close()
    twin.close()
