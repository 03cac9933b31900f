"""examples/async_ppo.py runs end to end, briefly (2 updates of 8 envs x 3 landers x 128 steps),
against two servers (env i on server i mod 2) with K = 2 envs per recv, saves its policy, and
the saved policy reloads and evaluates greedily."""

import csv
import json
import math
import pathlib
import subprocess
import sys

import numpy as np

import multi_lunar_lander as mll

EXAMPLES = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(EXAMPLES))

import ppo_common  # noqa: E402

SHORT = ["--envs", "8", "--batch-size", "2", "--landers", "3", "--num-steps", "128", "--max-cycles", "200"]


def _run(*args):
    done = subprocess.run([sys.executable, str(EXAMPLES / "async_ppo.py"), *SHORT, *args],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-3000:]
    return [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]


def test_async_ppo_trains_on_two_servers_saves_and_evaluates(tmp_path):
    model, curve = tmp_path / "policy.pt", tmp_path / "curve.csv"
    with mll.ServerProcess(threads=1) as first, mll.ServerProcess(threads=1) as second:
        address = f"{first.address},{second.address}"
        lines = _run("--address", address, "--total-steps", "6144", "--save", str(model), "--csv", str(curve),
                     "--eval-episodes", "4")
        updates, evaluation = lines[:-1], lines[-1]
        assert [line["update"] for line in updates] == [1, 2]
        assert [line["env_steps"] for line in updates] == [1024, 2048]  # 8 envs x 128 steps per rollout.
        assert [line["lander_steps"] for line in updates] == [3072, 6144]
        # Most rows carry a transition; done landers' and auto-reset rows do not.
        assert 0.8 * 6144 < updates[-1]["transitions"] < 6144
        for line in updates:  # Random landers crash within 200 steps: episodes end in every rollout.
            assert line["episodes"] > 0 and math.isfinite(line["mean_return"])
            assert all(math.isfinite(line[name]) for name in ("policy_loss", "value_loss", "entropy"))
            assert line["env_steps_per_s"] > 0
        assert evaluation["evaluation_episodes"] == 4 and math.isfinite(evaluation["mean_score"])
        with open(curve) as file:
            assert [int(row["lander_steps"]) for row in csv.DictReader(file)] == [3072, 6144]

        act, config = ppo_common.load(str(model))
        assert (config["options"]["n_landers"], config["options"]["max_cycles"], config["args"]["batch_size"]) == (3, 200, 2)
        assert config["observation_scale"] is not None  # The recipe normalises observations.
        actions = act(np.zeros((5, 3, 12), np.float32))
        assert actions.shape == (5, 3) and ((0 <= actions) & (actions < 4)).all()

        reloaded = _run("--address", address, "--evaluate", str(model), "--eval-episodes", "4")
        assert len(reloaded) == 1 and reloaded[0] == evaluation  # Greedy, same seeds: the same episodes.
