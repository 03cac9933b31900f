"""The trainer examples run end to end, briefly (a few thousand lander steps), on an embedded
server: each writes its learning curve, one row per rollout."""

import csv
import json
import math
import pathlib
import subprocess
import sys
import time

import numpy as np
import pytest

import multi_lunar_lander as mll

EXAMPLES = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(EXAMPLES.parent / "client_py" / "tests"))  # The client's test helpers.

from mll_test_helpers import listed_names, without_log_files  # noqa: E402

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


@pytest.mark.parametrize(
    "script, extra",
    [("ppo_cleanrl.py", ()), ("ppo_cleanrl.py", ("--paper",)), ("ppo_sb3.py", ()), ("ppo_sb3.py", ("--supersuit",))],
)
def test_ppo_recipe_trains_saves_reloads_and_evaluates(script, extra, tmp_path):
    """Each PPO recipe briefly: it trains (curve, episode scores), saves, evaluates greedily, and
    the reloaded policy flies the same evaluation episodes (greedy, same seeds)."""
    model = tmp_path / ("model.zip" if script == "ppo_sb3.py" else "model.pt")
    episodes_csv = tmp_path / "episodes.csv"
    rows, output = _run(script, tmp_path, *extra, "--save", str(model), "--episodes-csv", str(episodes_csv),
                        "--eval-episodes", "3")
    assert [int(row["lander_steps"]) for row in rows] == [1536, 3072]  # 4 envs x 3 landers x 128 steps.
    # Random landers crash within 200 steps: episodes end in every rollout, with finite returns.
    assert int(rows[-1]["episodes"]) >= 12
    assert all(math.isfinite(float(row["mean_return"])) for row in rows)
    with open(episodes_csv) as file:  # Per env episode: the sum of its 3 landers' returns.
        episodes = list(csv.DictReader(file))
    assert len(episodes) >= 4 and [int(e["episode"]) for e in episodes] == list(range(1, len(episodes) + 1))
    scores = [float(e["score"]) for e in episodes]
    assert float(episodes[1]["mean50"]) == pytest.approx((scores[0] + scores[1]) / 2, abs=2e-3)
    assert all(score < 0 for score in scores)  # Untrained landers crash.
    evaluation = json.loads(output.splitlines()[-1])
    assert evaluation["evaluation_episodes"] == 3 and math.isfinite(evaluation["mean_score"])
    outcome_shares = [evaluation[name] for name in mll.OUTCOMES if name]
    assert sum(outcome_shares) == pytest.approx(1.0)  # Every lander of the 3 episodes ended somehow.

    reloaded = subprocess.run(
        [sys.executable, str(EXAMPLES / script), "--envs", "4", "--evaluate", str(model), "--eval-episodes", "3"],
        capture_output=True, text=True, timeout=300,
    )
    assert reloaded.returncode == 0, reloaded.stderr[-3000:]
    assert json.loads(reloaded.stdout.splitlines()[-1]) == evaluation
    if "--paper" in extra:  # Flown on the default environment, one crash ends the others' episodes.
        elsewhere = subprocess.run(
            [sys.executable, str(EXAMPLES / script), "--envs", "4", "--evaluate", str(model), "--eval-episodes", "3",
             "--evaluate-on", "default"],
            capture_output=True, text=True, timeout=300,
        )
        assert elsewhere.returncode == 0, elsewhere.stderr[-3000:]
        assert evaluation["aborted"] == 0 and json.loads(elsewhere.stdout.splitlines()[-1])["aborted"] > 0
    if script == "ppo_sb3.py":
        from stable_baselines3 import PPO

        assert PPO.load(model, device="cpu").num_timesteps == 3072


def test_sb3_minibatches_hold_real_transitions_only():
    """ppo_sb3's RealTransitionsBuffer leaves the idle rows (a finished lander waiting for its
    environment, the environment's reset step) out of SB3's minibatches: the rows marked idle are
    exactly those stored with the zero observation, and every transition sampled is a real one."""
    from stable_baselines3 import PPO

    sys.path.insert(0, str(EXAMPLES))
    import ppo_sb3

    env = mll.sb3_vec_env(2, n_landers=3, max_cycles=100)
    model = without_log_files(PPO("MlpPolicy", env, n_steps=128, batch_size=64, n_epochs=1, seed=1, device="cpu",
                                  rollout_buffer_class=ppo_sb3.RealTransitionsBuffer))
    model.learn(total_timesteps=128 * 6, callback=ppo_sb3.MarkSteps())  # One rollout of 6 landers.
    env.close()
    buffer = model.rollout_buffer
    real = buffer.real.swapaxes(0, 1).ravel()  # Env-major, as the buffer's rows after training.
    assert 0 < real.sum() < real.size  # Random landers crash at different steps: some rows idle.
    observations = buffer.observations
    assert np.all(observations[~real] == 0) and np.all(np.any(observations[real] != 0, axis=1))
    sampled = [batch.observations.numpy() for batch in buffer.get(64)]
    assert sum(len(batch) for batch in sampled) == real.sum()
    assert all(np.any(batch != 0, axis=1).all() for batch in sampled)


def test_team_credit_sums_each_step_and_bootstraps_a_lander_done_early_from_the_team():
    """ppo_common.team_credit on one environment of 3 landers over 2 steps: lander 0 lands on step
    0 while 1 and 2 fly on; on step 1 lander 1 crashes, lander 2 is cut off by the step limit and
    lander 0's row is idle."""
    sys.path.insert(0, str(EXAMPLES))
    import ppo_common
    import torch

    rewards = torch.tensor([[100.0, 2.0, 3.0], [5.0, -200.0, 1.0]])
    valid = torch.tensor([[True, True, True], [False, True, True]])
    next_values = torch.tensor([[7.0, 10.0, 20.0], [8.0, 30.0, 40.0]])
    goes_on = torch.tensor([[False, True, True], [False, False, True]])  # Landed; crashed; cut off (bootstraps).
    team_rewards, team_next = ppo_common.team_credit(rewards, valid, next_values, goes_on, landers=3)
    assert team_rewards.tolist() == [[105.0] * 3, [-199.0] * 3]  # The idle row's 5 is not counted.
    # Step 0: the landed lander bootstraps from the mean of its neighbours' values, the others from
    # their own. Step 1: only lander 2 (cut off) goes on, so the others bootstrap from its value.
    assert team_next.tolist() == [[15.0, 10.0, 20.0], [40.0, 40.0, 40.0]]
    _, nobody_next = ppo_common.team_credit(rewards, valid, next_values, torch.zeros_like(goes_on), landers=3)
    assert nobody_next.tolist() == [[0.0] * 3] * 2  # Every lander done: nothing to bootstrap from.


def test_sb3_team_credit_of_lone_landers_is_sb3s_own_gae():
    """With one lander per environment the team is the lander, so RealTransitionsBuffer's team
    credit (its own reading of rewards, episode ends and SB3's bootstrap of cut-off episodes) must
    give SB3's own advantages and returns, on a rollout with crashes and cut-off episodes."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.buffers import RolloutBuffer
    from stable_baselines3.common.callbacks import BaseCallback, CallbackList

    sys.path.insert(0, str(EXAMPLES))
    import ppo_sb3

    compared = []

    class CompareWithSb3(BaseCallback):
        def _on_step(self) -> bool:
            return True

        def _on_rollout_end(self) -> None:
            buffer = self.model.rollout_buffer
            team = (buffer.advantages.copy(), buffer.returns.copy())
            RolloutBuffer.compute_returns_and_advantage(buffer, self.locals["values"], self.locals["dones"])
            compared.append((team, (buffer.advantages, buffer.returns), buffer.ended.sum(), buffer.cut_off.sum()))

    env = mll.sb3_vec_env(4, n_landers=1, max_cycles=40)  # Random landers: some crash, some are cut off.
    model = without_log_files(PPO("MlpPolicy", env, n_steps=128, batch_size=64, n_epochs=1, seed=1, device="cpu",
                                  rollout_buffer_class=ppo_sb3.RealTransitionsBuffer,
                                  rollout_buffer_kwargs=dict(team_landers=1)))
    model.learn(total_timesteps=128 * 4 * 2, callback=CallbackList([ppo_sb3.MarkSteps(), CompareWithSb3()]))
    env.close()
    assert len(compared) == 2
    for (advantages, returns), (sb3_advantages, sb3_returns), ended, cut_off in compared:
        assert ended > cut_off > 0
        np.testing.assert_allclose(advantages, sb3_advantages, rtol=1e-5, atol=1e-4)
        np.testing.assert_allclose(returns, sb3_returns, rtol=1e-5, atol=1e-4)


def _env_count(address):
    return len(listed_names(address))


# The RLlib run's bound: about 2 min on 2 busy cores, over 5 min on one core shared with a CPU hog
# (Ray's start-up alone took 3.5 min there). Its iterations wait as long for their samples.
RLLIB_LIMIT_S = 900


def test_rllib_ppo_spreads_env_runners_over_two_servers(tmp_path):
    """RLlib PPO, one shared policy, 2 env runners (Ray actors) on a local Ray, 2 iterations;
    runner k's env lives on server k mod 2, so both servers hold an env while it trains."""

    with mll.ServerProcess(threads=1) as first, mll.ServerProcess(threads=1) as second:
        curve = tmp_path / "curve.csv"
        process = subprocess.Popen(
            [sys.executable, str(EXAMPLES / "rllib_ppo.py"), "--addresses", f"{first.address},{second.address}",
             "--env-runners", "2", "--iterations", "2", "--batch", "400", "--minibatch", "100", "--epochs", "1",
             "--max-cycles", "100", "--num-cpus", "2", "--csv", str(curve), "--sample-timeout-s", str(RLLIB_LIMIT_S)],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        )
        most = [0, 0]
        deadline = time.monotonic() + RLLIB_LIMIT_S
        while process.poll() is None and time.monotonic() < deadline:
            most = [max(most[0], _env_count(first.address)), max(most[1], _env_count(second.address))]
            time.sleep(0.2)
        if process.poll() is None:
            process.kill()
        output = process.communicate()[0]
        assert process.returncode == 0, output[-4000:]
        assert most[0] >= 1 and most[1] >= 1, (most, output[-2000:])
        with open(curve) as file:
            rows = list(csv.DictReader(file))
        assert [row["iteration"] for row in rows] == ["1", "2"]
        assert float(rows[-1]["agent_steps"]) > float(rows[0]["agent_steps"]) > 0
        assert math.isfinite(float(rows[-1]["episode_return_mean"]))
