"""Replay ring buffer and n-step folding."""

import numpy as np
import pytest

from mll_dqn.replay import NStepFolder, ReplayBuffer


def _fill(buffer, start, count):
    values = np.arange(start, start + count)
    buffer.add(np.repeat(values[:, None], 12, 1).astype(np.float32), values,
               values.astype(np.float32),
               np.repeat(values[:, None] + 0.5, 12, 1).astype(np.float32),
               np.full(count, 0.99, np.float32))


def test_ring_buffer_wraps_and_keeps_the_newest():
    buffer = ReplayBuffer(10, 12)
    _fill(buffer, 0, 7)
    _fill(buffer, 7, 7)  # 14 added into 10 slots: 4..13 remain.
    assert len(buffer) == 10
    assert sorted(buffer.actions.tolist()) == list(range(4, 14))
    # Every slot is internally consistent (obs, reward, next_obs match).
    np.testing.assert_array_equal(buffer.obs[:, 0], buffer.actions)
    np.testing.assert_array_equal(buffer.rewards, buffer.actions)
    np.testing.assert_array_equal(buffer.next_obs[:, 3], buffer.actions + 0.5)


def test_sample_is_without_replacement_and_from_stored_rows():
    buffer = ReplayBuffer(100, 12)
    _fill(buffer, 0, 30)
    obs, actions, rewards, next_obs, discounts = buffer.sample(
        30, np.random.default_rng(1))
    assert sorted(actions.tolist()) == list(range(30))
    np.testing.assert_array_equal(obs[:, 0], actions)
    with pytest.raises(ValueError, match="batch_size = 31 exceeds the 30"):
        buffer.sample(31, np.random.default_rng(1))


def test_state_dict_round_trip():
    buffer = ReplayBuffer(8, 12)
    _fill(buffer, 0, 6)
    _fill(buffer, 6, 5)
    copy = ReplayBuffer(8, 12)
    copy.load_state_dict(buffer.state_dict())
    assert len(copy) == 8 and copy.next_index == buffer.next_index
    np.testing.assert_array_equal(copy.actions, buffer.actions)
    np.testing.assert_array_equal(copy.next_obs, buffer.next_obs)


def _reference_nstep(rewards, n, gamma, terminal_last):
    """n-step transitions of one finished episode, computed directly."""
    out = []
    length = len(rewards)
    for t in range(length):
        horizon = min(n, length - t)
        ret = sum(gamma ** k * rewards[t + k] for k in range(horizon))
        ends_episode = t + horizon == length
        discount = 0.0 if (ends_episode and terminal_last) else gamma ** horizon
        out.append((t, ret, t + horizon, discount))
    return out


@pytest.mark.parametrize("n", [1, 2, 3, 5])
def test_nstep_matches_direct_computation(n):
    gamma = 0.9
    rng = np.random.default_rng(n)
    # Two streams: stream 0 terminates after 7 steps, stream 1 is truncated
    # after 4 (bootstraps from its last observation).
    lengths, terminal = [7, 4], [True, False]
    rewards = [rng.normal(size=7), rng.normal(size=4)]
    folder = NStepFolder(n, gamma, 2, 12)
    got = {0: [], 1: []}
    for t in range(7):
        mask = np.array([t < lengths[0], t < lengths[1]])
        obs = np.zeros((2, 12), np.float32)
        obs[:, 0] = t  # obs encodes the time step ...
        next_obs = obs + 1  # ... and next_obs the next one.
        rew = np.array([rewards[s][t] if mask[s] else 0.0 for s in (0, 1)])
        last = np.array([t == lengths[s] - 1 for s in (0, 1)])
        out = folder.add(mask, obs, np.array([0, 1]), rew, next_obs,
                         last & np.array(terminal), last)
        if out is None:
            continue
        for o, a, r, nxt, d in zip(*out):
            got[int(a)].append((int(o[0]), float(r), int(nxt[0]), float(d)))
    for s in (0, 1):
        want = _reference_nstep(rewards[s], n, gamma, terminal[s])
        got_sorted = sorted(got[s])
        assert [g[0] for g in got_sorted] == [w[0] for w in want]
        for g, w in zip(got_sorted, want):
            assert g[1] == pytest.approx(w[1], rel=1e-5)
            assert g[2] == w[2] and g[3] == pytest.approx(w[3])


def test_nstep_stream_restarts_cleanly_after_an_episode():
    folder = NStepFolder(3, 0.5, 1, 12)
    ones = np.ones(1, bool)
    obs = np.zeros((1, 12), np.float32)
    folder.add(ones, obs, np.array([0]), np.array([1.0]), obs, ones, ones)
    out = folder.add(ones, obs + 7, np.array([2]), np.array([4.0]), obs + 8,
                     ~ones, ~ones)
    assert out is None  # The new episode's first step is held, not mixed.
    out = folder.add(ones, obs + 8, np.array([3]), np.array([2.0]), obs + 9,
                     ones, ones)
    assert [float(r) for r in out[2]] == [5.0, 2.0]
    assert out[0][0, 0] == 7 and out[0][1, 0] == 8


def _prioritized(capacity, count, alpha=1.0):
    from mll_dqn.replay import PrioritizedReplayBuffer
    buffer = PrioritizedReplayBuffer(capacity, 12, alpha)
    _fill(buffer, 0, count)
    return buffer


def test_prioritized_sampling_follows_the_priorities():
    buffer = _prioritized(8, 8)
    # Row 5's error is 9 times each other row's: with alpha 1 it is drawn
    # about 9 / (9 + 7) of the time.
    errors = np.ones(8)
    errors[5] = 9.0
    buffer.update_priorities(np.arange(8), errors - buffer.epsilon)
    rng = np.random.default_rng(0)
    draws = np.concatenate([buffer.sample_prioritized(8, rng, 0.4)[1]
                            for _ in range(500)])
    assert abs(np.mean(draws == 5) - 9 / 16) < 0.02
    assert set(np.unique(draws)) == set(range(8))
    batch, index, weights = buffer.sample_prioritized(8, rng, 1.0)
    # Each row is what was stored at its index, and the frequent row gets the
    # smallest importance weight (beta 1: weight proportional to 1 / P).
    np.testing.assert_array_equal(batch[1], index)
    assert weights.max() == 1.0
    np.testing.assert_allclose(weights[index == 5], 1 / 9, rtol=1e-5)


def test_new_transitions_get_the_largest_priority_and_the_tree_sums():
    buffer = _prioritized(6, 4)
    buffer.update_priorities(np.array([0, 1]), np.array([3.0, 0.5]))
    _fill(buffer, 4, 4)  # Wraps: rows 0 and 1 are overwritten by 6 and 7.
    leaves = buffer._tree[buffer._leaves:buffer._leaves + 6]
    assert leaves[0] == leaves[1] == leaves[4] == leaves[5] == buffer._max_priority
    assert buffer._max_priority == 3.0 + buffer.epsilon
    assert buffer._tree[1] == leaves.sum()


def test_prioritized_state_round_trips():
    from mll_dqn.replay import PrioritizedReplayBuffer
    buffer = _prioritized(10, 7, alpha=0.6)
    buffer.update_priorities(np.arange(3), np.array([0.1, 2.0, 0.7]))
    copy = PrioritizedReplayBuffer(10, 12, 0.6)
    copy.load_state_dict(buffer.state_dict())
    rng_a, rng_b = np.random.default_rng(3), np.random.default_rng(3)
    first, second = buffer.sample_prioritized(5, rng_a, 0.5), copy.sample_prioritized(5, rng_b, 0.5)
    np.testing.assert_array_equal(first[1], second[1])
    np.testing.assert_array_equal(first[2], second[2])
