"""The real pettingzoo.test suite, discrete and continuous, against the real server."""

import functools
import types

from pettingzoo.test import (
    api_test,
    max_cycles_test,
    parallel_api_test,
    parallel_seed_test,
    render_test,
    seed_test,
)

import multi_lunar_lander as mll


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
