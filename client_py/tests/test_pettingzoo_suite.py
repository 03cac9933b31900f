"""The real pettingzoo.test suite, discrete and continuous, against the real server; and the
layout of PettingZoo's state() that docs/api_python.md gives."""

import functools
import types
import warnings

import numpy as np
from mll_test_helpers import same_bits
from pettingzoo.test import (
    api_test,
    max_cycles_test,
    parallel_api_test,
    parallel_seed_test,
    render_test,
    seed_test,
    state_test,
)

import multi_lunar_lander as mll

N_LANDERS, MAX_CYCLES = 4, 80
# The warnings state_test gives this env, each by design: the state space has the observation
# space's infinite bounds, and once every lander is done every row is zero.
EXPECTED_STATE_WARNINGS = ("value is -infinity", "value is infinity", "State numpy array is all zeros")


def test_api(address, continuous):
    env = mll.env(address=address, continuous=continuous)
    api_test(env, num_cycles=300)
    env.close()


def test_parallel_api(address, continuous):
    env = mll.parallel_env(address=address, continuous=continuous)
    parallel_api_test(env, num_cycles=300)
    env.close()


def test_seed(address, continuous):
    seed_test(functools.partial(mll.env, address=address, continuous=continuous), num_cycles=100)


def test_parallel_seed(address, continuous):
    parallel_seed_test(functools.partial(mll.parallel_env, address=address, continuous=continuous), num_cycles=100)


def test_max_cycles_on_the_module_with_its_embedded_server():
    # max_cycles_test calls mod.parallel_env / mod.env itself (no address: the embedded server).
    max_cycles_test(mll)


def test_max_cycles_continuous(address):
    module = types.SimpleNamespace(
        env=functools.partial(mll.env, address=address, continuous=True),
        parallel_env=functools.partial(mll.parallel_env, address=address, continuous=True),
    )
    max_cycles_test(module)


def test_render(address, continuous):
    def make(render_mode=None):
        return mll.env(address=address, render_mode=render_mode, continuous=continuous)

    render_test(make)


def test_state(address, continuous):
    """PettingZoo's state_test on the AEC env (every turn of episodes that end by crashes and by
    max_cycles) and the parallel env; any warning beyond the expected ones fails (state_test only
    warns when state() is not an array, and then stops checking)."""
    env = mll.env(address=address, continuous=continuous, max_cycles=40)
    parallel = mll.parallel_env(address=address, continuous=continuous, max_cycles=40)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        state_test(env, parallel, num_cycles=60)
    unexpected = [str(w.message) for w in caught if not any(text in str(w.message) for text in EXPECTED_STATE_WARNINGS)]
    assert not unexpected
    assert not env.agents, "the episode was meant to end within num_cycles"
    env.close()
    parallel.close()


def _action(rng, continuous):
    return rng.uniform(-1, 1, 2).astype(np.float32) if continuous else int(rng.integers(0, 4))


def _check_state(env, latest) -> np.ndarray:
    """Asserts env.state() is as documented: float32 (N * 12,) in state_space, lander i's latest
    observation (`latest[agent]`) at [12 i, 12 i + 12) to the bit while it is in `agents`, zeros
    otherwise. Returns it."""
    state = env.state()
    assert state.dtype == np.float32 and state.shape == (N_LANDERS * 12,) and env.state_space.contains(state)
    zeros = np.zeros(12, np.float32)
    want = np.concatenate([latest[agent] if agent in env.agents else zeros for agent in env.possible_agents])
    assert same_bits(state, want)
    return state


def _check_space(env):
    space = env.observation_space(env.possible_agents[0])
    assert env.state_space.shape == (N_LANDERS * 12,) and env.state_space.dtype == np.float32
    assert same_bits(env.state_space.low, np.tile(space.low, N_LANDERS))
    assert same_bits(env.state_space.high, np.tile(space.high, N_LANDERS))
    assert same_bits(env.state(), np.zeros(N_LANDERS * 12, np.float32))  # Before the first reset.


def _fly_aec(env, seed):
    """One episode of random turns, checking state() after the reset and every turn against
    observe(); the states, and whether some lander was absent while others flew."""
    _check_space(env)
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    observe = {agent: env.observe(agent) for agent in env.agents}
    states, partial = [_check_state(env, observe)], False
    for agent in env.agent_iter(N_LANDERS * (MAX_CYCLES + 1)):
        _, _, terminated, truncated, _ = env.last()
        env.step(None if terminated or truncated else _action(rng, env.continuous))
        states.append(_check_state(env, {agent: env.observe(agent) for agent in env.agents}))
        partial |= 0 < len(env.agents) < N_LANDERS
    assert not env.agents
    return states, partial


def _fly_parallel(env, seed):
    """One episode of random steps, checking state() after the reset and every step against the
    observations returned; a clone's state() mid-episode too. As _fly_aec."""
    _check_space(env)
    rng = np.random.default_rng(seed)
    latest, _ = env.reset(seed=seed)
    states, partial = [_check_state(env, latest)], False
    for step in range(MAX_CYCLES):
        if not env.agents:
            break
        observations = env.step({agent: _action(rng, env.continuous) for agent in env.agents})[0]
        latest.update(observations)
        states.append(_check_state(env, latest))
        partial |= 0 < len(env.agents) < N_LANDERS
        if step == 10:
            twin = env.clone()  # A snapshot restored: the same state.
            assert same_bits(twin.state(), states[-1])
            twin.close()
    assert not env.agents
    return states, partial


def test_state_layout_and_bits_on_the_given_and_the_embedded_server(address, continuous):
    """state() rows are the observations the client holds, to the bit; rows of landers no longer in
    `agents` are zeros; the same seed and actions give the same states on another server."""
    for make, fly in ((mll.env, _fly_aec), (mll.parallel_env, _fly_parallel)):
        runs = []
        for where in (address, None):
            env = make(
                address=where, continuous=continuous, n_landers=N_LANDERS, max_cycles=MAX_CYCLES,
                terminate_on_damage=False,  # Landers end one by one.
            )
            runs.append(fly(env, seed=3))
            env.close()
        (states, partial), (embedded, _) = runs
        assert partial, "some lander was meant to be done while others flew"
        assert len(states) == len(embedded) and all(same_bits(a, b) for a, b in zip(states, embedded))
