"""Server errors arrive as MLLError with the server's code and message."""

import grpc
import numpy as np
import pytest

import multi_lunar_lander as mll

from mll_test_helpers import delete_env, raises_code as _raises


@pytest.mark.parametrize(
    "option, value",
    [("n_landers", 0), ("n_landers", 33), ("gravity", -12.5), ("wind_power", 21.0), ("max_cycles", 0)],
)
def test_bad_config_is_invalid_argument_naming_the_field(address, option, value):
    error = _raises(grpc.StatusCode.INVALID_ARGUMENT, mll.parallel_env, address=address, **{option: value})
    assert option in error.message and str(value).rstrip("0").rstrip(".") in error.message


def test_config_type_and_name_errors_are_caught_before_sending(address):
    error = _raises(grpc.StatusCode.INVALID_ARGUMENT, mll.env, address=address, n_landers=2.5)
    assert "n_landers" in error.message
    error = _raises(grpc.StatusCode.INVALID_ARGUMENT, mll.env, address=address, render_mode="ansi")
    assert "render_mode" in error.message
    with pytest.raises(TypeError, match="landers"):
        mll.env(address=address, landers=3)


def test_bad_actions(address):
    env = mll.parallel_env(address=address, n_landers=2)
    env.reset(seed=0)
    error = _raises(grpc.StatusCode.INVALID_ARGUMENT, env.step, {"lander_0": 7, "lander_1": 0})
    assert "7" in error.message
    _raises(grpc.StatusCode.INVALID_ARGUMENT, env.step, {"lander_0": 0})  # lander_1 missing.
    env.close()
    continuous = mll.env(address=address, continuous=True)
    continuous.reset(seed=0)
    error = _raises(grpc.StatusCode.INVALID_ARGUMENT, continuous.step, np.array([np.nan, 0.0], np.float32))
    assert "nan" in error.message.lower()
    continuous.close()


def test_step_before_reset_is_failed_precondition(address):
    env = mll.parallel_env(address=address)
    _raises(grpc.StatusCode.FAILED_PRECONDITION, env._connection.call, "StepEnv", _step_request(env))
    env.close()


def _step_request(env):
    from multi_lunar_lander import _arrays
    from multi_lunar_lander._stubs import pb

    request = pb.StepEnvRequest(name=env.name)
    _arrays.to_proto(np.zeros(len(env.possible_agents), np.int32), pb.DTYPE_INT32, request.actions)
    return request


def test_unknown_env_is_not_found_naming_it(address, raw_stub):
    env = mll.env(address=address)
    delete_env(raw_stub, env.name)  # E.g. reclaimed by the server's idle timeout.
    error = _raises(grpc.StatusCode.NOT_FOUND, env.reset, seed=0)
    assert env.name in error.message
    env.close()  # Still fine: the env is already gone.


def test_unreachable_address_names_the_address():
    error = _raises(grpc.StatusCode.UNAVAILABLE, mll.env, address="127.0.0.1:1")
    assert "127.0.0.1:1" in error.message
