"""The C++ batched API (mll::client::VectorEnv, through `mll_cli play --envs=N` and `mll_cli
bench`) and Python's vector_env fly the same bits: the same seeds and heuristic actions give the
same episode returns, lengths and outcomes, over every transport of either client."""

import json
import os
import pathlib
import subprocess

import numpy as np
import pytest

import multi_lunar_lander as mll
from multi_lunar_lander._server import checkout_build_path

CLI = pathlib.Path(os.environ.get("MLL_CLI_BIN") or checkout_build_path("client_cpp", "mll_cli"))
pytestmark = pytest.mark.skipif(not CLI.is_file(), reason=f"mll_cli is not built ({CLI})")
N_ENVS, N_LANDERS, SEED = 5, 3, 21


def _cli(*args, timeout=120):
    done = subprocess.run([str(CLI), *args], capture_output=True, text=True, timeout=timeout)
    assert done.returncode == 0, done.stderr
    return [json.loads(line) for line in done.stdout.splitlines()]


def _python_episode(vector):
    """One episode of every env from seeds SEED + j, heuristic actions, as mll_cli play flies it:
    an env whose episode is over flies on (auto-reset) outside the record."""
    observations, _ = vector.reset(seed=SEED)
    flying = np.ones(N_ENVS, bool)
    record = [None] * N_ENVS
    steps = np.zeros(N_ENVS, int)
    while flying.any():
        actions = mll.heuristic(observations).astype(np.int32)
        observations, _, _, _, _, infos = vector.step(actions)
        steps[flying] += 1
        for j in np.flatnonzero(flying & infos["episode_over"]):
            record[j] = (
                int(steps[j]),
                [float(r) for r in infos["episode_return"][j]],
                [int(n) for n in infos["episode_length"][j]],
                [mll.OUTCOMES[o] for o in infos["outcome"][j]],
            )
            flying[j] = False
    return record


def _cli_episode(lines):
    record = []
    for line in lines:
        if line.get("summary"):
            continue
        agents = [f"lander_{a}" for a in range(N_LANDERS)]
        record.append(
            (
                line["steps"],
                [float(np.float32(line["returns"][a])) for a in agents],
                [line["lengths"][a] for a in agents],
                [line["outcomes"][a] for a in agents],
            )
        )
    return record


@pytest.mark.parametrize("cpp_transport", ["shared_memory", "native"])
def test_mll_cli_play_and_python_vector_env_fly_the_same_bits(address, cpp_transport):
    lines = _cli(
        "play", f"--address={address}", f"--envs={N_ENVS}", f"--n_landers={N_LANDERS}",
        f"--seed={SEED}", "--policy=heuristic", f"--transport={cpp_transport}",
    )
    assert lines[-1]["transport"] == cpp_transport
    cpp = _cli_episode(lines)
    for transport in ("native", "shared_memory"):
        with mll.vector_env(N_ENVS, address=address, n_landers=N_LANDERS, transport=transport) as vector:
            assert _python_episode(vector) == cpp, transport
    assert all(steps > 20 for steps, *_ in cpp)  # Real flights.


def test_mll_cli_bench_reports_its_throughput_and_transport(address):
    (line,) = _cli(
        "bench", f"--address={address}", "--envs=8", "--n_landers=2", "--seconds=0.5", "--clients=2"
    )
    assert line["transport"] == "shared_memory" and line["clients"] == 2 and line["envs"] == 8
    assert line["env_steps"] > 0 and line["env_steps"] % 8 == 0
    assert 0 < line["agent_steps"] <= 2 * line["env_steps"]
    assert line["env_steps_per_second"] > 0 and line["agent_steps_per_second"] > 0
    (native,) = _cli("bench", f"--address={address}", "--envs=4", "--seconds=0.3", "--transport=native")
    assert native["transport"] == "native" and native["n_landers"] == 3


def test_mll_cli_refuses_an_unknown_transport(address):
    done = subprocess.run(
        [str(CLI), "bench", f"--address={address}", "--transport=carrier-pigeon"], capture_output=True, text=True
    )
    assert done.returncode == 2
    assert 'transport is "carrier-pigeon"; allowed: "auto", "shared_memory", "native"' in done.stderr
