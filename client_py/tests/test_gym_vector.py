"""gym_vector_env: a real gymnasium.vector.VectorEnv, one sub-environment per lander, on the
packed batched step; NEXT_STEP autoreset, the idle-lander rule, Gymnasium's vector wrappers."""

import pickle

import grpc
import gymnasium
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode
from gymnasium.wrappers import vector as vector_wrappers

import multi_lunar_lander as mll

from mll_test_helpers import raises_code

# Lander 0 falls (no engine) and crashes; landers 1 and 2 fire their main engine and fly on,
# so lander 0 is idle for a while before its env's episode ends.
_CRASH_EARLY = dict(n_landers=3, remove_on_damage=True, terminate_on_damage=False, max_cycles=90)
_FALL_AND_HOVER = (0, 2, 2)


def test_it_is_a_gymnasium_vector_env_with_batched_spaces(address, continuous):
    env = mll.gym_vector_env(4, address=address, n_landers=3, continuous=continuous)
    assert isinstance(env, gymnasium.vector.VectorEnv)
    assert env.num_envs == 12 and env.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    assert env.single_observation_space.shape == (12,)
    assert env.observation_space.shape == (12, 12) and env.observation_space.dtype == np.float32
    if continuous:
        assert env.single_action_space.shape == (2,) and env.action_space.shape == (12, 2)
    else:
        assert env.single_action_space.n == 4 and env.action_space.nvec.tolist() == [4] * 12
    observations, infos = env.reset(seed=0)
    assert observations.shape == (12, 12) and observations in env.observation_space
    env.action_space.seed(0)
    result = env.step(env.action_space.sample())
    assert len(result) == 5 and result[0] in env.observation_space
    assert result[1].shape == result[2].shape == result[3].shape == (12,)
    env.close()
    assert env.closed


def test_same_seed_same_actions_same_bits_as_vector_env(address, continuous):
    options = dict(n_landers=3, continuous=continuous, max_cycles=60)
    gym_env = mll.gym_vector_env(3, address=address, **options)
    raw = mll.vector_env(3, address=address, **options)
    observations, _ = gym_env.reset(seed=11)
    expected, _ = raw.reset(seed=11)
    assert observations.tobytes() == expected.tobytes()
    rng = np.random.default_rng(4)
    resets = 0
    for _ in range(130):  # max_cycles 60: every env ends at least one episode.
        actions = rng.uniform(-1, 1, (9, 2)).astype(np.float32) if continuous else rng.integers(0, 4, 9)
        observations, rewards, terminations, truncations, infos = gym_env.step(actions)
        o, r, te, tr, active, raw_infos = raw.step(actions.reshape((3, 3) + actions.shape[1:]))
        assert observations.tobytes() == o.tobytes()
        assert rewards.tobytes() == np.where(active, r, 0).astype(np.float32).tobytes()
        assert np.array_equal(terminations, (te & active).ravel())
        assert np.array_equal(truncations, (tr & active).ravel())
        assert np.array_equal(infos["idle"], ~active.ravel())
        resets += int(raw_infos["auto_reset"].sum())
    assert resets >= 3
    gym_env.close()
    raw.close()


def test_a_lander_that_finishes_early_reports_its_end_once_then_idles(address):
    env = mll.gym_vector_env(1, address=address, **_CRASH_EARLY)
    env.reset(seed=1)
    actions = np.array(_FALL_AND_HOVER)
    history = [env.step(actions) for _ in range(95)]
    ends = [t for t, step in enumerate(history) if step[2][0] or step[3][0]]
    assert len(ends) == 1, "lander 0 reports its end exactly once per episode"
    end = ends[0]
    observations, rewards, terminations, _, infos = history[end]
    assert terminations[0] and not terminations[1:].any() and not infos["idle"][0]
    assert infos["_episode_return"].tolist() == [True, False, False]
    assert infos["outcome"][0] == mll.OUTCOMES.index("crashed")
    assert infos["episode_length"][0] == end + 1
    returns = sum(step[1][0] for step in history[: end + 1])
    assert infos["episode_return"][0] == pytest.approx(returns, rel=1e-5)
    others_end = next(t for t, step in enumerate(history) if step[2][1] or step[3][1])
    assert others_end > end + 5
    for t in range(end + 1, others_end + 1):  # Idle while the other landers fly.
        observations, rewards, terminations, truncations, infos = history[t]
        assert infos["idle"].tolist() == [True, False, False] and infos["_idle"][0]
        assert not observations[0].any() and rewards[0] == 0 and not terminations[0] and not truncations[0]
    observations, rewards, terminations, truncations, infos = history[others_end + 1]  # The reset step.
    assert infos["idle"].all() and not rewards.any() and not (terminations | truncations).any()
    assert observations[0].any()  # Lander 0's first observation of the new episode.
    assert not history[others_end + 2][4]["idle"].any()  # Everyone acts again.
    env.close()


def test_record_episode_statistics_returns_are_exact(address):
    env = vector_wrappers.RecordEpisodeStatistics(mll.gym_vector_env(2, address=address, **_CRASH_EARLY))
    env.reset(seed=3)
    actions = np.array(_FALL_AND_HOVER * 2)
    reported = []
    for _ in range(250):
        _, _, terminations, truncations, infos = env.step(actions)
        if "_episode_return" in infos:
            mask = infos["_episode_return"]
            assert np.array_equal(mask, infos["_episode"])  # The wrapper saw the same ends.
            np.testing.assert_allclose(infos["episode"]["r"][mask], infos["episode_return"][mask], rtol=1e-5)
            reported.extend(infos["episode_return"][mask].tolist())
    assert len(reported) >= 6 and len(env.return_queue) == len(reported)
    np.testing.assert_allclose(list(env.return_queue), reported, rtol=1e-5)
    env.close()


def test_normalize_observation_and_reward_and_dict_info_to_list(address):
    env = mll.gym_vector_env(2, address=address, n_landers=2, max_cycles=40)
    wrapped = vector_wrappers.DictInfoToList(
        vector_wrappers.NormalizeReward(vector_wrappers.NormalizeObservation(env), gamma=0.99)
    )
    observations, _ = wrapped.reset(seed=5)
    rng = np.random.default_rng(1)
    ended = 0
    for _ in range(100):
        observations, rewards, terminations, truncations, infos = wrapped.step(rng.integers(0, 4, 4))
        assert observations.shape == (4, 12) and np.isfinite(observations).all() and np.isfinite(rewards).all()
        assert isinstance(infos, list) and len(infos) == 4
        for row, info in enumerate(infos):
            if terminations[row] or truncations[row]:
                assert "episode_return" in info and "outcome" in info
                ended += 1
    assert ended >= 4
    running = wrapped.env.env.obs_rms
    assert running.count > 100 and np.abs(observations).max() < 20
    wrapped.close()


def test_clip_and_rescale_action_on_the_continuous_env(address):
    env = vector_wrappers.ClipAction(mll.gym_vector_env(2, address=address, n_landers=2, continuous=True))
    env.reset(seed=0)
    _, rewards, _, _, _ = env.step(np.full((4, 2), 5.0, dtype=np.float32))  # Clipped to 1, accepted.
    assert rewards.shape == (4,)
    env.close()


def test_bad_actions_and_seeds_are_rejected_with_the_shape(address):
    env = mll.gym_vector_env(2, address=address, n_landers=3)
    env.reset(seed=0)
    error = raises_code(grpc.StatusCode.INVALID_ARGUMENT, env.step, np.zeros((2, 3), np.int64))
    assert "(2, 3)" in error.message and "(6,)" in error.message
    raises_code(grpc.StatusCode.INVALID_ARGUMENT, env.reset, seed=[1, 2])
    env.close()


def test_a_bad_option_raises_the_servers_error_and_nothing_else(address, monkeypatch):
    import gc
    import sys

    ignored = []  # Exceptions raised in __del__ (gymnasium's VectorEnv.__del__ closes the env).
    monkeypatch.setattr(sys, "unraisablehook", ignored.append)
    error = raises_code(grpc.StatusCode.INVALID_ARGUMENT, mll.gym_vector_env, 2, address=address, n_landers=0)
    assert "n_landers" in error.message
    del error
    gc.collect()
    assert not ignored, [u.exc_value for u in ignored]


def test_it_pickles_as_its_arguments(address):
    env = mll.gym_vector_env(2, address=address, n_landers=2, gravity=-8.0)
    copy = pickle.loads(pickle.dumps(env))
    assert copy.num_envs == 4 and copy.vector.config == env.vector.config
    assert not set(copy.vector.names) & set(env.vector.names)
    assert copy.reset(seed=9)[0].tobytes() == env.reset(seed=9)[0].tobytes()
    copy.close()
    env.close()
