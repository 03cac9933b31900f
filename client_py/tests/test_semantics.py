"""What the PettingZoo suite does not pin down: reward accounting, agent bookkeeping, and the
same episode through every client class."""

import grpc
import numpy as np
import pytest

import multi_lunar_lander as mll

from mll_test_helpers import raises_code, run_heuristic_parallel


@pytest.mark.parametrize("shared_reward", [True, False])
def test_last_reward_is_the_sum_since_the_agents_previous_turn(address, continuous, shared_reward):
    env = mll.env(address=address, continuous=continuous, shared_reward=shared_reward, max_cycles=150)
    env.reset(seed=3)
    pending = {agent: 0.0 for agent in env.possible_agents}
    totals = {agent: 0.0 for agent in env.possible_agents}
    for agent in env.agent_iter():
        observation, reward, terminated, truncated, info = env.last()
        assert reward == pytest.approx(pending[agent], abs=1e-4)
        pending[agent] = 0.0
        if terminated or truncated:
            assert info["episode_return"] == pytest.approx(totals[agent], abs=1e-3)
            assert info["outcome"] in mll.OUTCOMES[1:]
            action = None
        else:
            assert "episode_return" not in info
            action = mll.heuristic(observation, continuous)
        env.step(action)
        for other, value in env.rewards.items():
            pending[other] += value
            totals[other] += value
    assert env.agents == []
    env.close()


def test_parallel_agents_shrink_by_the_agents_just_done(address, continuous):
    env = mll.parallel_env(address=address, continuous=continuous, n_landers=5, terminate_on_damage=False)
    env.reset(seed=11)
    for agent in env.possible_agents:
        env.action_space(agent).seed(5)
    seen_done = set()
    steps = 0
    while env.agents and steps < 600:
        before = list(env.agents)
        actions = {agent: env.action_space(agent).sample() for agent in before}
        observations, rewards, terminations, truncations, infos = env.step(actions)
        for result in (observations, rewards, terminations, truncations, infos):
            assert set(result) == set(before)
        done = {agent for agent in before if terminations[agent] or truncations[agent]}
        assert env.agents == [agent for agent in before if agent not in done]
        for agent in done:
            assert infos[agent]["outcome"] in mll.OUTCOMES[1:]
            assert infos[agent]["episode_length"] == steps + 1
        seen_done |= done
        steps += 1
    assert env.agents == [] and seen_done == set(env.possible_agents)
    env.close()


def _aec_trajectory(env, seed):
    env.reset(seed=seed)
    seen = {agent: [] for agent in env.possible_agents}
    final = {}
    for agent in env.agent_iter():
        observation, _, terminated, truncated, info = env.last()
        if terminated or truncated:
            final[agent] = info
            env.step(None)
        else:
            seen[agent].append(observation)
            env.step(mll.heuristic(observation, env.continuous))
    return seen, final


def _vector_trajectory(env, seed):
    observations, _ = env.reset(seed=seed)
    names = env.possible_agents
    seen = {agent: [observations[0, i]] for i, agent in enumerate(names)}
    final = {}
    while True:
        actions = mll.heuristic(observations, env.continuous)
        observations, _, terminations, truncations, active, infos = env.step(actions)
        for i, agent in enumerate(names):
            if not active[0, i]:
                continue
            if terminations[0, i] or truncations[0, i]:
                final[agent] = {
                    "outcome": mll.OUTCOMES[infos["outcome"][0, i]],
                    "episode_return": float(infos["episode_return"][0, i]),
                    "episode_length": int(infos["episode_length"][0, i]),
                }
            else:
                seen[agent].append(observations[0, i])
        if infos["episode_over"][0]:
            return seen, final


def test_same_seed_gives_identical_episodes_in_env_parallel_env_and_vector_env(address, continuous):
    options = dict(address=address, continuous=continuous, n_landers=3, max_cycles=400)
    aec, parallel, vector = mll.env(**options), mll.parallel_env(**options), mll.vector_env(2, **options)
    trajectories = [_aec_trajectory(aec, 21), run_heuristic_parallel(parallel, 21), _vector_trajectory(vector, 21)]
    reference_seen, reference_final = trajectories[0]
    assert sum(len(v) for v in reference_seen.values()) > 30
    for seen, final in trajectories[1:]:
        assert final == reference_final
        for agent, observations in reference_seen.items():
            assert len(seen[agent]) == len(observations)
            np.testing.assert_array_equal(np.array(seen[agent]), np.array(observations))
    for env in (aec, parallel, vector):
        env.close()


def test_unseeded_reset_continues_the_stream_and_reseeding_repeats_it(address):
    env = mll.parallel_env(address=address)
    first, _ = env.reset(seed=5)
    second, _ = env.reset()
    again, _ = env.reset(seed=5)
    assert not np.array_equal(first["lander_0"], second["lander_0"])
    np.testing.assert_array_equal(first["lander_0"], again["lander_0"])
    env.close()


def test_spaces_come_from_the_server_spec(address, continuous):
    env = mll.parallel_env(address=address, continuous=continuous, n_landers=4)
    assert env.possible_agents == [f"lander_{i}" for i in range(4)]
    observation_space = env.observation_space("lander_2")
    assert observation_space.shape == (12,) and observation_space.dtype == np.float32
    action_space = env.action_space("lander_2")
    if continuous:
        assert action_space.shape == (2,) and action_space.dtype == np.float32
        assert action_space.low.tolist() == [-1, -1] and action_space.high.tolist() == [1, 1]
    else:
        assert action_space.n == 4
    assert env.action_space("lander_1") is not action_space  # One object per agent ...
    assert env.action_space("lander_2") is action_space  # ... the same one every call.
    assert env.config["n_landers"] == 4 and env.config["max_cycles"] == 500  # Defaults filled in.
    env.close()


def test_rgb_array_frames(address):
    env = mll.parallel_env(address=address, render_mode="rgb_array", n_landers=2)
    env.reset(seed=0)
    frame = env.render()
    assert frame.shape == (400, 600, 3) and frame.dtype == np.uint8
    assert frame.std() > 0  # Not a blank image.
    env.close()


def test_parallel_step_with_no_agent_left_returns_empty_dicts(address):
    """PettingZoo's reference parallel envs answer step({}) after the episode with five empty
    dicts (SuperSuit's black_death_v3 relies on it); the other steps after the end fail."""
    env = mll.parallel_env(address=address, n_landers=2, max_cycles=30)
    error = raises_code(grpc.StatusCode.FAILED_PRECONDITION, env.step, {})
    assert "ResetEnv" in error.message  # Before the first reset: no episode to be over.
    env.reset(seed=2)
    for _ in range(30):
        env.step({agent: 0 for agent in env.agents})
        if not env.agents:
            break
    assert env.agents == []
    assert env.step({}) == ({}, {}, {}, {}, {})
    assert env.step({}) == ({}, {}, {}, {}, {})
    error = raises_code(grpc.StatusCode.FAILED_PRECONDITION, env.step, {"lander_0": 0})
    assert "episode is over" in error.message
    env.reset(seed=2)
    assert env.agents == ["lander_0", "lander_1"]
    raises_code(grpc.StatusCode.INVALID_ARGUMENT, env.step, {})  # Agents are active again.
    env.close()
