"""Every action the clients accept is checked: what is not an action of the env (an unknown
agent, a string, None, a float or bool for a discrete action, the wrong shape, NaN) raises
MLLError INVALID_ARGUMENT naming the agent and what is allowed, never a numpy or gRPC error of
its own, and the env keeps working afterwards."""

import grpc
import numpy as np
import pytest

import multi_lunar_lander as mll

from mll_test_helpers import raises_code

N = 2
NOT_DISCRETE = ["up", None, 1.5, 2.0, np.float32(1.0), True, np.bool_(False), [1], np.array([1, 2]), {"a": 1},
                2**40, 2**70, object(), b"\x01"]
NOT_CONTINUOUS = ["up", None, 0.5, True, [0.1], [0.1, 0.2, 0.3], [[0.1, 0.2]], ["a", "b"], [None, 0.1],
                  [[0.1], 0.2], np.array([True, False]), {"main": 0.1}]
# Of the right type: their values are the server's to check (it names the lander).
BAD_VALUES = {False: [7, -1, np.int64(4)], True: [[np.nan, 0.0], [0.0, np.inf], np.array([-np.inf, 0], np.float32)]}


def _valid(continuous):
    return np.array([0.5, -0.2], np.float32) if continuous else 2


def _expect_invalid(call, *args, names=()):
    error = raises_code(grpc.StatusCode.INVALID_ARGUMENT, call, *args)
    for name in names:
        assert name in error.message, error.message
    return error


@pytest.mark.parametrize("bad_index", [0, N - 1])
def test_parallel_rejects_every_kind_of_bad_action_naming_the_agent(address, continuous, bad_index):
    env = mll.parallel_env(address=address, n_landers=N, continuous=continuous)
    env.reset(seed=0)
    agent = env.possible_agents[bad_index]
    for bad in NOT_CONTINUOUS if continuous else NOT_DISCRETE:
        actions = {a: _valid(continuous) for a in env.agents}
        actions[agent] = bad
        error = _expect_invalid(env.step, actions, names=(agent, "allowed"))
        assert "0..3" in error.message or "[main, lateral]" in error.message
    for bad in BAD_VALUES[continuous]:
        actions = {a: _valid(continuous) for a in env.agents}
        actions[agent] = bad
        _expect_invalid(env.step, actions, names=(agent,))
    # Nothing above stepped the world; the env still steps.
    *_, infos = env.step({a: _valid(continuous) for a in env.agents})
    assert set(infos) == set(env.possible_agents)
    env.close()


def test_parallel_rejects_unknown_agents_and_non_dicts(address):
    env = mll.parallel_env(address=address, n_landers=N)
    env.reset(seed=0)
    error = _expect_invalid(env.step, {"lander_0": 0, "lander_1": 0, "lander_99": 2}, names=("lander_99", "lander_1"))
    assert "not agents of this env" in error.message
    _expect_invalid(env.step, {"lander_0": 0, "lander_1": 0, 0: 1}, names=("0",))
    _expect_invalid(env.step, [0, 0], names=("dict",))
    _expect_invalid(env.step, None, names=("dict",))
    observations, *_ = env.step({"lander_0": 0, "lander_1": 0})
    assert set(observations) == {"lander_0", "lander_1"}
    env.close()


def test_aec_rejects_every_kind_of_bad_action_naming_the_agent(address, continuous):
    env = mll.env(address=address, n_landers=N, continuous=continuous)
    env.reset(seed=0)
    env.step(_valid(continuous))  # lander_1's turn now.
    assert env.agent_selection == "lander_1"
    for bad in [b for b in (NOT_CONTINUOUS if continuous else NOT_DISCRETE) if b is not None]:
        _expect_invalid(env.step, bad, names=("lander_1", "allowed"))
    for bad in BAD_VALUES[continuous]:
        _expect_invalid(env.step, bad, names=("lander_1",))
    assert env.agent_selection == "lander_1"
    env.step(_valid(continuous))
    assert env.agent_selection == "lander_0"
    env.close()


def test_vector_rejects_bad_action_blocks(address, continuous):
    vec = mll.vector_env(3, address=address, n_landers=N, continuous=continuous)
    vec.reset(seed=0)
    shape = (3, N, 2) if continuous else (3, N)
    good = np.zeros(shape, np.float32 if continuous else np.int64)
    bad_blocks = [
        "up",
        None,
        np.zeros(shape[:-1] if continuous else shape + (1,)),  # Wrong shape.
        np.full(shape, "up"),
        np.zeros(shape, bool),
        np.zeros(shape, object),
        [[0] * N, [0] * N, [0]],  # Ragged.
    ]
    if not continuous:
        bad_blocks += [np.zeros(shape, np.float32), np.full(shape, 2**40)]
    for bad in bad_blocks:
        _expect_invalid(vec.step, bad, names=("actions", "allowed"))
    # Values of active agents: the server names the env and the lander.
    bad = good.copy()
    bad[1, 1] = np.nan if continuous else 9
    _expect_invalid(vec.step, bad, names=("env 1", "lander_1"))
    observations, *_ = vec.step(good)
    assert observations.shape == (3, N, 12)
    vec.close()
