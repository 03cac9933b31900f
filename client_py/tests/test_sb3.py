"""sb3_vec_env: a Stable-Baselines3 VecEnv, one environment per lander, on the packed batched
step; SB3's same-step reset convention and the idle-lander rule; SB3's PPO and VecEnv wrappers
run on it (stable-baselines3 2.4.1 on Debian's torch 1.13 and gymnasium 1.x)."""

import pickle

import numpy as np
import pytest
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import VecEnv, VecNormalize

import multi_lunar_lander as mll

from mll_test_helpers import without_log_files
from test_gym_vector import _CRASH_EARLY, _FALL_AND_HOVER


def test_same_bits_as_gym_vector_env_with_same_step_resets(address):
    env = mll.sb3_vec_env(1, address=address, **_CRASH_EARLY)
    gym_env = mll.gym_vector_env(1, address=address, **_CRASH_EARLY)
    assert isinstance(env, VecEnv) and env.num_envs == 3
    env.seed(1)
    assert env.reset().tobytes() == gym_env.reset(seed=1)[0].tobytes()
    actions = np.array(_FALL_AND_HOVER)
    ended = {0: 0, 1: 0, 2: 0}
    for _ in range(200):  # max_cycles 90: two episodes.
        observations, rewards, dones, infos = env.step(actions)
        expected, expected_rewards, terminations, truncations, gym_infos = gym_env.step(actions)
        assert rewards.tobytes() == expected_rewards.tobytes()
        for k in range(3):
            if terminations[k] or truncations[k]:  # A real end: final observation in the info.
                ended[k] += 1
                assert dones[k] and not observations[k].any()
                assert infos[k]["terminal_observation"].tobytes() == expected[k].tobytes()
                assert infos[k]["TimeLimit.truncated"] == bool(truncations[k] and not terminations[k])
                assert infos[k]["episode"]["r"] == pytest.approx(gym_infos["episode_return"][k])
            elif gym_infos["idle"][k]:  # Idle (or its env's reset step): a zero-reward terminal step.
                assert dones[k] and rewards[k] == 0 and infos[k]["idle"]
                assert not infos[k]["terminal_observation"].any() and "episode" not in infos[k]
                assert observations[k].tobytes() == expected[k].tobytes()
            else:
                assert not dones[k] and infos[k] == {}
                assert observations[k].tobytes() == expected[k].tobytes()
    assert min(ended.values()) >= 2
    env.close()
    gym_env.close()


def test_ppo_runs_with_vec_normalize_and_logs_real_episodes_only(address):
    env = VecNormalize(mll.sb3_vec_env(2, address=address, n_landers=2, max_cycles=60))
    model = without_log_files(PPO("MlpPolicy", env, n_steps=64, batch_size=64, n_epochs=1, seed=0, device="cpu"))
    model.learn(total_timesteps=2 * 4 * 64)
    assert model.num_timesteps == 512
    # Every lander ends an episode within 60 steps, then idles; only the real ends are logged.
    lengths = [info["l"] for info in model.ep_info_buffer]
    assert len(lengths) >= 4 * 2 and all(1 <= length <= 60 for length in lengths)
    env.close()


def test_it_pickles_as_its_arguments(address):
    env = mll.sb3_vec_env(2, address=address, n_landers=2)
    copy = pickle.loads(pickle.dumps(env))
    assert copy.num_envs == 4 and not set(copy.vector.names) & set(env.vector.names)
    env.seed(3)
    copy.seed(3)
    assert copy.reset().tobytes() == env.reset().tobytes()
    copy.close()
    env.close()
