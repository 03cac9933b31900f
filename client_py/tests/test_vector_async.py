"""vector_env's step_async/step_wait: the same step split in two, one step in flight at a time."""

import grpc
import numpy as np
import pytest

import multi_lunar_lander as mll


def _actions(rng, num_envs, n_landers):
    return rng.integers(0, 4, size=(num_envs, n_landers), dtype=np.int32)


def test_step_async_then_wait_gives_the_bits_of_step(address):
    # Two vector envs with the same seeds: one stepped with step(), the other with the split
    # call; 120 steps with max_cycles=40 so every env auto-resets several times.
    options = dict(address=address, n_landers=2, max_cycles=40)
    with mll.vector_env(3, **options) as whole, mll.vector_env(3, **options) as split:
        np.testing.assert_array_equal(whole.reset(seed=7)[0], split.reset(seed=7)[0])
        rng = np.random.default_rng(0)
        resets = 0
        for _ in range(120):
            actions = _actions(rng, 3, 2)
            expected = whole.step(actions)
            split.step_async(actions)
            got = split.step_wait()
            for left, right in zip(expected[:5], got[:5]):
                assert left.dtype == right.dtype
                np.testing.assert_array_equal(left, right)
            for key in expected[5]:
                np.testing.assert_array_equal(expected[5][key], got[5][key])
            resets += int(got[5]["auto_reset"].sum())
        assert resets >= 3


def test_two_halves_alternating_equal_one_vector_env(address):
    # Envs 0-1 and 2-3 as two halves, seeded so that each env gets the seed it has in the whole.
    options = dict(address=address, n_landers=3, max_cycles=30)
    with mll.vector_env(4, **options) as whole, mll.vector_env(2, **options) as first, \
            mll.vector_env(2, **options) as second:
        whole_obs, _ = whole.reset(seed=100)
        first_obs, _ = first.reset(seed=100)
        second_obs, _ = second.reset(seed=102)
        np.testing.assert_array_equal(whole_obs, np.concatenate([first_obs, second_obs]))
        rng = np.random.default_rng(1)
        for _ in range(80):
            actions = _actions(rng, 4, 3)
            first.step_async(actions[:2])
            second.step_async(actions[2:])  # Both halves in flight at once.
            expected = whole.step(actions)
            got_first, got_second = first.step_wait(), second.step_wait()
            for index in range(5):
                np.testing.assert_array_equal(expected[index],
                                              np.concatenate([got_first[index], got_second[index]]))


def test_one_step_in_flight_at_a_time(address):
    with mll.vector_env(2, address=address, n_landers=1) as env:
        env.reset(seed=0)
        actions = np.zeros((2, 1), dtype=np.int32)
        with pytest.raises(mll.MLLError) as error:
            env.step_wait()
        assert error.value.code == grpc.StatusCode.FAILED_PRECONDITION
        assert "step_async" in error.value.message
        env.step_async(actions)
        for call in (lambda: env.step_async(actions), lambda: env.step(actions), lambda: env.reset(seed=1)):
            with pytest.raises(mll.MLLError) as error:
                call()
            assert error.value.code == grpc.StatusCode.FAILED_PRECONDITION
            assert "step_wait" in error.value.message
        observations = env.step_wait()[0]
        assert observations.shape == (2, 1, 12)
        env.step(actions)  # Usable again.


def test_bad_actions_are_refused_before_anything_is_sent(address):
    with mll.vector_env(2, address=address, n_landers=2) as env:
        env.reset(seed=0)
        with pytest.raises(mll.MLLError) as error:
            env.step_async(np.zeros((3, 2), dtype=np.int32))
        assert error.value.code == grpc.StatusCode.INVALID_ARGUMENT
        with pytest.raises(mll.MLLError):
            env.step_wait()  # Nothing was sent.
        env.step_async(np.zeros((2, 2), dtype=np.int32))
        assert env.step_wait()[0].shape == (2, 2, 12)
