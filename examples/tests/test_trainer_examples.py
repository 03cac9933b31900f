"""The trainer examples run end to end, briefly (a few thousand lander steps), on an embedded
server: each writes its learning curve, one row per rollout."""

import csv
import math
import pathlib
import subprocess
import sys

import pytest

EXAMPLES = pathlib.Path(__file__).resolve().parents[1]
SHORT = ["--envs", "4", "--landers", "3", "--total-steps", "3072", "--num-steps", "128", "--max-cycles", "200"]


def _run(script, tmp_path, *extra):
    curve = tmp_path / "curve.csv"
    done = subprocess.run(
        [sys.executable, str(EXAMPLES / script), *SHORT, "--csv", str(curve), *extra],
        capture_output=True, text=True, timeout=300,
    )
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-3000:]
    with open(curve) as file:
        rows = list(csv.DictReader(file))
    return rows, done.stdout


@pytest.mark.parametrize("script", ["ppo_cleanrl.py", "ppo_sb3.py"])
def test_ppo_example_trains_and_writes_its_curve(script, tmp_path):
    extra = ("--save", str(tmp_path / "model.zip")) if script == "ppo_sb3.py" else ()
    rows, _ = _run(script, tmp_path, *extra)
    assert [int(row["lander_steps"]) for row in rows] == [1536, 3072]  # 4 envs x 3 landers x 128 steps.
    # Random landers crash within 200 steps: episodes end in every rollout, with finite returns.
    assert int(rows[-1]["episodes"]) >= 12
    assert all(math.isfinite(float(row["mean_return"])) for row in rows)
    if script == "ppo_sb3.py":
        from stable_baselines3 import PPO

        assert PPO.load(tmp_path / "model.zip", device="cpu").num_timesteps == 3072
