"""The client's smoke subset, for both ends of its dependency ranges: scripts/dependency-ranges.sh
runs this file in venvs that hold exactly the declared floors (client_py/constraints-floor.txt)
and the newest releases, with the package installed from its wheel; the normal suite runs it in
the project venv. Each test needs only the runtime dependencies, pytest, and the [render] extra
for the last two (skipped without it).

$MLL_EXPECT_CONSTRAINTS (set by the script): a constraints file whose versions the environment
must hold exactly; $MLL_EXPECT_INSTALLED=1: the package must come from site-packages, not from a
source tree."""

from __future__ import annotations

import importlib.metadata
import io
import os
import pathlib
import re
import sys

import gymnasium
import numpy as np
import pytest
from pettingzoo.test import api_test, parallel_api_test

import multi_lunar_lander as mll

GYMNASIUM_1 = int(gymnasium.__version__.split(".")[0]) >= 1


def test_the_environment_holds_what_the_run_asked_for():
    versions = {
        name: importlib.metadata.version(name)
        for name in ("grpcio", "grpcio-health-checking", "protobuf", "numpy", "gymnasium", "pettingzoo")
    }
    print(f"Python {sys.version.split()[0]}:", ", ".join(f"{k} {v}" for k, v in versions.items()))
    if os.environ.get("MLL_EXPECT_INSTALLED") == "1":
        package = pathlib.Path(mll.__file__).resolve()
        assert "site-packages" in package.parts, f"imported from {package}, not from the installed wheel"
    constraints = os.environ.get("MLL_EXPECT_CONSTRAINTS")
    if not constraints:
        return
    from packaging.requirements import Requirement  # pytest's own dependency

    checked = 0
    for line in pathlib.Path(constraints).read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        requirement = Requirement(line)
        if requirement.marker is not None and not requirement.marker.evaluate():
            continue
        try:
            installed = importlib.metadata.version(requirement.name)
        except importlib.metadata.PackageNotFoundError:
            continue  # An extra's package this run did not install (stable-baselines3).
        (pinned,) = requirement.specifier
        assert installed == pinned.version or re.fullmatch(re.escape(pinned.version) + r"(\.0)*", installed), (
            f"{requirement.name} {installed} is installed; the constraints say {pinned.version}"
        )
        checked += 1
    assert checked >= 6


@pytest.mark.parametrize("continuous", [False, True], ids=["discrete", "continuous"])
def test_parallel_env_flies_an_episode(address, continuous):
    env = mll.parallel_env(address=address, n_landers=2, continuous=continuous, max_cycles=200)
    observations, infos = env.reset(seed=3)
    assert set(observations) == set(env.possible_agents)
    steps = 0
    while env.agents:
        actions = {agent: mll.heuristic(observations[agent], continuous) for agent in env.agents}
        observations, rewards, terminations, truncations, infos = env.step(actions)
        for observation in observations.values():
            assert observation.shape == (12,) and observation.dtype == np.float32
        steps += 1
    assert 0 < steps <= 200
    env.close()


def test_vector_env_steps_and_autoresets(address):
    env = mll.vector_env(3, address=address, n_landers=2, max_cycles=20)
    observations, infos = env.reset(seed=0)
    assert observations.shape == (3, 2, 12) and observations.dtype == np.float32
    rng = np.random.default_rng(0)
    for _ in range(25):  # Past max_cycles: every env autoresets once.
        result = env.step(rng.integers(0, 4, size=(3, 2), dtype=np.int32))
        observations, rewards = result[0], result[1]
        assert observations.shape == (3, 2, 12) and rewards.shape == (3, 2)
    env.close()


def test_gym_vector_env_or_the_gymnasium_it_needs(address):
    if not GYMNASIUM_1:
        with pytest.raises(ImportError) as caught:
            mll.gym_vector_env(2, address=address, n_landers=2)
        message = str(caught.value)
        assert "gymnasium>=1.0" in message and gymnasium.__version__ in message, message
        return
    env = mll.gym_vector_env(2, address=address, n_landers=2)
    assert isinstance(env, gymnasium.vector.VectorEnv) and env.num_envs == 4
    observations, infos = env.reset(seed=0)
    assert observations.shape == (4, 12)
    for _ in range(5):
        observations, rewards, terminations, truncations, infos = env.step(env.action_space.sample())
        assert observations.shape == (4, 12) and rewards.shape == (4,) and "idle" in infos
    if hasattr(gymnasium.vector, "AutoresetMode"):  # gymnasium >= 1.1
        assert env.metadata["autoreset_mode"] == gymnasium.vector.AutoresetMode.NEXT_STEP
    env.close()


@pytest.mark.parametrize("continuous", [False, True], ids=["discrete", "continuous"])
def test_pettingzoo_api_tests(address, continuous):
    env = mll.env(address=address, n_landers=2, continuous=continuous)
    api_test(env, num_cycles=100)
    env.close()
    parallel = mll.parallel_env(address=address, n_landers=2, continuous=continuous)
    parallel_api_test(parallel, num_cycles=100)
    parallel.close()


def test_render_extra_human_window_and_gif(address):
    pytest.importorskip("pygame")
    image = pytest.importorskip("PIL.Image")
    env = mll.parallel_env(address=address, n_landers=2, render_mode="human", max_cycles=5)
    observations, _ = env.reset(seed=1)  # A pygame window (SDL's dummy driver, conftest.py).
    while env.agents:
        observations, *_ = env.step({agent: mll.heuristic(observations[agent]) for agent in env.agents})
    env.close()
    env = mll.parallel_env(address=address, n_landers=2, render_mode="rgb_array", max_cycles=3)
    env.reset(seed=1)
    frames = [env.render()]
    while env.agents:
        env.step({agent: 0 for agent in env.agents})
        frames.append(env.render())
    env.close()
    images = [image.fromarray(frame) for frame in frames]  # As examples/play.py writes its GIFs.
    gif = io.BytesIO()
    images[0].save(gif, format="GIF", save_all=True, append_images=images[1:], duration=40, loop=0)
    assert gif.getvalue().startswith(b"GIF89a")
