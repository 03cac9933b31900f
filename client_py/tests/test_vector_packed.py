"""vector_env over the packed StepBatch: the same bits as parallel_env stepping the same seeds
and actions (auto-resets included), the same bits over two servers as over one, and per-env
errors from `PackedStepData.errors` naming the env."""

import grpc
import numpy as np
import pytest

import multi_lunar_lander as mll
from multi_lunar_lander._stubs import pb_grpc

from mll_test_helpers import delete_env, random_actions, rollout, same_bits


def test_packed_steps_equal_parallel_envs_bit_for_bit_across_auto_resets(address, continuous):
    num_envs, n_landers, seed = 4, 3, 50
    options = dict(address=address, n_landers=n_landers, continuous=continuous, max_cycles=25)
    vector = mll.vector_env(num_envs, **options)
    singles = [mll.parallel_env(**options) for _ in range(num_envs)]
    agents = singles[0].possible_agents
    observations, _ = vector.reset(seed=seed)
    for i, single in enumerate(singles):  # Env i is seeded seed + i.
        expected, _ = single.reset(seed=seed + i)
        assert same_bits(observations[i], np.stack([expected[agent] for agent in agents]))
    rng = np.random.default_rng(3)
    auto_resets = transitions = 0
    for _ in range(70):  # max_cycles 25: every env's episodes end and auto-reset at least twice.
        actions = random_actions(rng, (num_envs, n_landers), continuous)
        observations, rewards, terminations, truncations, active, infos = vector.step(actions)
        for i, single in enumerate(singles):
            if not single.agents:  # Its episode was over: the vector env started the next one.
                expected, _ = single.reset()  # No seed: the env's stream continues.
                assert infos["auto_reset"][i] and not active[i].any() and not infos["episode_over"][i]
                assert same_bits(observations[i], np.stack([expected[agent] for agent in agents]))
                assert not rewards[i].any() and not terminations[i].any() and not truncations[i].any()
                auto_resets += 1
                continue
            step = single.step({agent: actions[i, k] for k, agent in enumerate(agents) if agent in single.agents})
            expected_obs, expected_rewards, expected_terms, expected_truncs, expected_infos = step
            assert not infos["auto_reset"][i]
            assert active[i].tolist() == [agent in expected_obs for agent in agents]
            assert infos["episode_over"][i] == (not single.agents)
            for k, agent in enumerate(agents):
                if agent not in expected_obs:  # Done before this step: a zero row.
                    assert not observations[i, k].any() and rewards[i, k] == 0
                    continue
                transitions += 1
                assert same_bits(observations[i, k], expected_obs[agent])
                assert same_bits(rewards[i, k], expected_rewards[agent])
                assert terminations[i, k] == expected_terms[agent] and truncations[i, k] == expected_truncs[agent]
                info = expected_infos[agent]
                assert mll.OUTCOMES[infos["outcome"][i, k]] == info.get("outcome")
                if "episode_return" in info:
                    assert same_bits(infos["episode_return"][i, k], info["episode_return"])
                    assert infos["episode_length"][i, k] == info["episode_length"]
    assert auto_resets >= 2 * num_envs and transitions > 300
    vector.close()
    for single in singles:
        single.close()


def test_results_are_ordinary_writable_arrays(address):
    vector = mll.vector_env(3, address=address, n_landers=2)
    vector.reset(seed=0)
    result = vector.step(np.zeros((3, 2), np.int32))
    arrays = list(result[:5]) + list(result[5].values())
    for array in arrays:
        assert isinstance(array, np.ndarray) and array.flags.writeable and array.flags.c_contiguous
    expected = [np.float32, np.float32, bool, bool, bool]  # observations .. active
    assert [array.dtype for array in result[:5]] == [np.dtype(d) for d in expected]
    assert {key: value.dtype for key, value in result[5].items()} == {
        "auto_reset": bool, "episode_over": bool, "outcome": np.uint8,
        "episode_return": np.float32, "episode_length": np.int32,
    }
    result[0][:] = 1.0  # Writing into one step's result does not touch the next one's.
    assert not np.array_equal(vector.step(np.zeros((3, 2), np.int32))[0], result[0])
    vector.close()


@pytest.fixture(scope="module")
def two_servers():
    with mll.ServerProcess(threads=1) as first, mll.ServerProcess(threads=2) as second:
        yield first.address, second.address


def test_uneven_shares_over_two_servers_give_the_same_bits_as_one(address, two_servers, continuous):
    # 7 envs over both servers (placed by load); random actions crash landers at different
    # steps in different envs, and max_cycles 20 over 50 steps auto-resets every env.
    options = dict(n_landers=3, continuous=continuous, max_cycles=20)
    spread = mll.vector_env(7, address=list(two_servers), **options)
    single = mll.vector_env(7, address=address, **options)
    assert set(spread.env_addresses) == set(two_servers)
    ours, reference = rollout(spread, 5, 50), rollout(single, 5, 50)
    assert len(ours) == len(reference)
    for got, expected in zip(ours, reference):
        assert same_bits(got, expected) and got.dtype == expected.dtype
    spread.close()
    single.close()


def test_an_env_deleted_behind_the_vector_envs_back_is_named(address, raw_stub):
    vector = mll.vector_env(4, address=address, n_landers=2)
    vector.reset(seed=0)
    for index in (3, 2):  # Both fail; the first in env order is reported.
        delete_env(raw_stub, vector.names[index])
    with pytest.raises(mll.MLLError) as caught:
        vector.step(np.zeros((4, 2), np.int32))
    assert caught.value.code == grpc.StatusCode.NOT_FOUND
    assert caught.value.message.startswith(f"env 2 ({vector.names[2]}): ")
    assert vector.names[2].split("/")[-1] in caught.value.message.split(": ", 1)[1]  # The server's own words.
    vector.close()


def test_a_failed_env_on_the_second_server_is_named_by_its_env_index(two_servers):
    vector = mll.vector_env(5, address=list(two_servers), n_landers=1, failover=False)  # Else recreated.
    vector.reset(seed=0)
    with grpc.insecure_channel(vector.env_addresses[3]) as channel:  # Row 1 of the second server.
        delete_env(pb_grpc.MultiLunarLanderStub(channel), vector.names[3])
    with pytest.raises(mll.MLLError) as caught:
        vector.step(np.zeros((5, 1), np.int32))
    assert caught.value.code == grpc.StatusCode.NOT_FOUND
    assert caught.value.message.startswith(f"env 3 ({vector.names[3]}): ")
    vector.close()
