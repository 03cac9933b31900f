"""The numpy heuristic pilot against Gymnasium's own `heuristic` function (no server needed)."""

import gymnasium
import numpy as np
import pytest
from gymnasium.envs.box2d.lunar_lander import heuristic as gymnasium_heuristic

import multi_lunar_lander as mll


def _observations(count=2000, seed=0):
    rng = np.random.default_rng(seed)
    obs = rng.normal(0.0, 0.6, size=(count, 12)).astype(np.float32)
    obs[:, 6:8] = rng.random((count, 2)) < 0.2  # Legs touch now and then.
    return obs


@pytest.mark.parametrize("continuous", [False, True])
def test_matches_gymnasium_heuristic_one_by_one_and_vectorised(continuous):
    reference_env = gymnasium.make("LunarLander-v3", continuous=continuous)
    observations = _observations()
    expected = np.array([gymnasium_heuristic(reference_env, s) for s in observations])
    reference_env.close()
    batched = mll.heuristic(observations.reshape(40, 50, 12), continuous).reshape(expected.shape)
    singles = np.array([mll.heuristic(s, continuous) for s in observations])
    if continuous:
        np.testing.assert_allclose(batched, expected, rtol=0, atol=1e-6)
        np.testing.assert_allclose(singles, expected, rtol=0, atol=1e-6)
    else:
        np.testing.assert_array_equal(batched, expected)
        np.testing.assert_array_equal(singles, expected)
        assert set(np.unique(expected)) == {0, 1, 2, 3}  # The sample covers every branch.
        assert isinstance(mll.heuristic(observations[0]), int)


def test_too_short_observation_is_an_error():
    with pytest.raises(ValueError, match="8"):
        mll.heuristic(np.zeros(5))
