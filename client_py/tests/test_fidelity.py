"""Fidelity against Gymnasium's LunarLander-v3: the heuristic pilot flies one lander for 100
seeds in ours and in Gymnasium's, and the statistics must agree.

The Box2D versions differ (Debian's 2.4.1 vs the pip box2d 2.3), so episodes cannot match bit
for bit, and seed s means different terrain and pushes in the two generators: the samples are
independent. Each statistic must agree within

    allowance = |known Box2D 2.4.1-vs-2.3 offset| + 4 * standard error of the difference,

the standard error coming from the seed-to-seed spread measured in this run (a two-sample
z-test at 4 sigma: a false alarm about 1 in 16,000). The offsets are the figures of a
faithful C++ port built against each Box2D (200 seeds): discrete return 237 vs 241, landing
88.5% vs 92%, length 272 vs 240; continuous 286 vs 286, 100% vs 100%, 215 vs 200.

Ours runs with terminate_reward=0: with one lander, terminate_reward is the only rule
Gymnasium does not have (its crash costs damage_reward = -100 alone); Gymnasium's TimeLimit
of 1000 steps is our max_cycles.
"""

import gymnasium
import numpy as np
import pytest

import multi_lunar_lander as mll

EPISODES = 100
# (return, landing rate, length) offsets of Box2D 2.4.1 against 2.3 (200 seeds each).
BOX2D_OFFSET = {False: (-4.0, -0.035, 32.0), True: (0.0, 0.0, 15.0)}


def _gymnasium_episodes(continuous):
    env = gymnasium.make("LunarLander-v3", continuous=continuous)
    returns, landed, lengths = [], [], []
    for seed in range(EPISODES):
        observation, _ = env.reset(seed=seed)
        total, steps = 0.0, 0
        while True:
            observation, reward, terminated, truncated, _ = env.step(mll.heuristic(observation, continuous))
            total += reward
            steps += 1
            if terminated or truncated:
                break
        returns.append(total)
        landed.append(terminated and not env.unwrapped.lander.awake)
        lengths.append(steps)
    env.close()
    return np.array(returns), np.array(landed, dtype=float), np.array(lengths, dtype=float)


def _our_episodes(address, continuous):
    """The first episode of each of 100 envs seeded 0..99, all stepped in one batch."""
    vector = mll.vector_env(
        EPISODES, address=address, n_landers=1, continuous=continuous, terminate_reward=0.0, max_cycles=1000
    )
    observations, _ = vector.reset(seed=0)
    finished = np.zeros(EPISODES, dtype=bool)
    returns, landed, lengths = np.zeros(EPISODES), np.zeros(EPISODES), np.zeros(EPISODES)
    for _ in range(1001):
        observations, _, _, _, _, infos = vector.step(mll.heuristic(observations, continuous))
        ending = infos["episode_over"] & ~finished
        returns[ending] = infos["episode_return"][ending, 0]
        landed[ending] = infos["outcome"][ending, 0] == mll.OUTCOMES.index("landed")
        lengths[ending] = infos["episode_length"][ending, 0]
        finished |= ending
        if finished.all():
            break
    vector.close()
    assert finished.all()
    return returns, landed, lengths


@pytest.mark.parametrize("continuous", [False, True], ids=["discrete", "continuous"])
def test_heuristic_statistics_match_gymnasium(address, continuous):
    ours = _our_episodes(address, continuous)
    theirs = _gymnasium_episodes(continuous)
    report = []
    for name, a, b, offset in zip(("return", "landing rate", "length"), ours, theirs, BOX2D_OFFSET[continuous]):
        if name == "landing rate":  # Binomial spread, pooled; at least one episode's worth.
            p = (a.mean() + b.mean()) / 2
            standard_error = max(np.sqrt(p * (1 - p) * 2 / EPISODES), 1.0 / EPISODES)
        else:
            standard_error = np.sqrt(a.var(ddof=1) / EPISODES + b.var(ddof=1) / EPISODES)
        allowance = abs(offset) + 4 * standard_error
        difference = a.mean() - b.mean()
        report.append(f"{name}: ours {a.mean():.3f} gymnasium {b.mean():.3f} allowed +-{allowance:.3f}")
        assert abs(difference) <= allowance, "; ".join(report)
    print("; ".join(report))
