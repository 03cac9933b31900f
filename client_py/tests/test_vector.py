"""vector_env: shapes, per-env seeds, auto-reset at episode end, deletion on close."""

import numpy as np
import pytest

import multi_lunar_lander as mll

from mll_test_helpers import assert_not_found


def test_shapes_dtypes_and_seeds(address, continuous):
    vector = mll.vector_env(4, address=address, n_landers=3, continuous=continuous)
    observations, _ = vector.reset(seed=100)
    assert observations.shape == (4, 3, 12) and observations.dtype == np.float32
    single = mll.parallel_env(address=address, n_landers=3, continuous=continuous)
    for i in range(4):  # Env i is seeded 100 + i.
        expected, _ = single.reset(seed=100 + i)
        np.testing.assert_array_equal(observations[i], np.stack([expected[a] for a in single.possible_agents]))
    actions = mll.heuristic(observations, continuous)
    assert actions.shape == ((4, 3, 2) if continuous else (4, 3))
    observations, rewards, terminations, truncations, active, infos = vector.step(actions)
    assert observations.shape == (4, 3, 12) and rewards.shape == (4, 3) and rewards.dtype == np.float32
    for flags in (terminations, truncations, active):
        assert flags.shape == (4, 3) and flags.dtype == bool
    assert active.all() and not infos["auto_reset"].any()
    with pytest.raises(mll.MLLError, match="shape"):
        vector.step(actions[:2])
    vector.close()
    single.close()


def test_episode_end_then_auto_reset(address):
    vector = mll.vector_env(3, address=address, n_landers=2, max_cycles=5)
    observations, _ = vector.reset(seed=7)
    zeros = np.zeros((3, 2), np.int32)
    for _ in range(5):
        observations, rewards, terminations, truncations, active, infos = vector.step(zeros)
        assert active.all()  # Free fall: nobody lands or crashes within 5 steps.
    assert truncations.all() and not terminations.any() and infos["episode_over"].all()
    assert (infos["episode_length"] == 5).all() and (infos["outcome"] == mll.OUTCOMES.index("truncated")).all()
    # The next step starts new episodes (continuing each env's stream); its actions are ignored.
    observations, rewards, terminations, truncations, active, infos = vector.step(zeros + 2)
    assert infos["auto_reset"].all() and not active.any() and not infos["episode_over"].any()
    assert (rewards == 0).all() and not terminations.any() and not truncations.any()
    assert (infos["episode_length"] == 0).all()
    reference = mll.parallel_env(address=address, n_landers=2, max_cycles=5)
    reference.reset(seed=7)
    for _ in range(5):  # The same draws from the generator as env 0 (engine dispersions).
        reference.step({agent: 0 for agent in reference.agents})
    second_episode, _ = reference.reset()  # Env 0's stream continued.
    np.testing.assert_array_equal(observations[0], np.stack([second_episode[a] for a in reference.possible_agents]))
    observations, rewards, terminations, truncations, active, infos = vector.step(zeros)
    assert active.all() and not infos["auto_reset"].any() and (infos["episode_length"] == 1).all()
    vector.close()
    reference.close()


@pytest.mark.parametrize("transport", ["shared_memory", "native"])
def test_close_deletes_the_envs_before_it_returns(address, raw_stub, transport):
    # close() half-closes each Session stream and waits for the server to end it, which the
    # server does once it has deleted the session's envs: none is left the moment close returns.
    vector = mll.vector_env(3, address=address, transport=transport)
    names = vector.names
    vector.close()
    vector.close()  # Idempotent.
    for name in names:
        assert_not_found(raw_stub, name)
