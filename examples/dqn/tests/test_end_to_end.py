"""The quick preset end to end against the real embedded server
(MLL_SERVER_BIN, set by scripts/test.sh): training in both collection modes,
resume, evaluation, GIF and plot."""

import csv
import dataclasses
import json
import os

import numpy as np
import pytest
import torch
from PIL import Image

from mll_dqn import evaluate
from mll_dqn.__main__ import main
from mll_dqn.config import preset
from mll_dqn.train import BEST, CHECKPOINT, LOG, SCORE_WINDOW, SUMMARY, train

OUTCOME_NAMES = {"landed", "crashed", "out_of_bounds", "truncated", "aborted"}


def _rows(run_dir):
    with open(os.path.join(run_dir, LOG), newline="") as f:
        return list(csv.DictReader(f))


def _check_log(rows, config):
    n = config.env_config["n_landers"]
    assert [int(r["episode"]) for r in rows] == list(range(1, len(rows) + 1))
    for r in rows:
        returns = [float(r[f"return_{i}"]) for i in range(n)]
        assert float(r["score"]) == pytest.approx(sum(returns), abs=0.01)
        assert {r[f"outcome_{i}"] for i in range(n)} <= OUTCOME_NAMES
        assert 1 <= int(r["steps"]) <= config.env_config["max_cycles"]
    assert int(rows[-1]["updates"]) > 0
    env_steps = [int(r["env_steps"]) for r in rows]
    assert env_steps == sorted(env_steps)


@pytest.mark.parametrize("mode", ["parallel", "vector"])
def test_quick_training_logs_and_checkpoints(tmp_path, mode):
    config = preset("quick")
    if mode == "vector":
        config = dataclasses.replace(config, mode="vector", num_envs=3,
                                     n_step=3, double_dqn=True, loss="huber")
    summary = train(config, str(tmp_path), progress_bar=False)
    rows = _rows(tmp_path)
    assert len(rows) == config.episodes
    _check_log(rows, config)
    assert os.path.exists(tmp_path / CHECKPOINT)
    saved = json.loads((tmp_path / SUMMARY).read_text())
    assert saved["episodes"] == config.episodes
    assert summary["updates"] == int(rows[-1]["updates"]) or mode == "vector"
    assert summary["env_steps"] >= int(rows[-1]["env_steps"])
    split = summary["time_split_s"]
    assert {"env", "act", "sample", "learn"} <= set(split)


def test_best_network_is_kept_with_its_running_mean(tmp_path):
    """best.pt holds the network at the episode of the highest full-window
    running mean, which the log and the summary agree on."""
    config = dataclasses.replace(
        preset("quick"), episodes=SCORE_WINDOW + 8, checkpoint_every=100,
        env_config=dict(preset("quick").env_config, max_cycles=20),
        lr_end=1e-4)
    summary = train(config, str(tmp_path), progress_bar=False)
    rows = _rows(tmp_path)
    means = [float(r["mean50"]) for r in rows][SCORE_WINDOW - 1:]
    best = int(np.argmax(means)) + SCORE_WINDOW
    assert summary["best_mean50_episode"] == best
    assert summary["best_mean50"] == pytest.approx(max(means), abs=1e-3)
    saved = torch.load(tmp_path / BEST)
    assert saved["episode"] == best
    policy, loaded = evaluate.load_policy(str(tmp_path / BEST))
    assert loaded == config
    assert policy(np.zeros((3, 12), np.float32)).shape == (3,)
    # The learning rate was decayed to lr_end by the last episode.
    last = torch.load(tmp_path / CHECKPOINT)["agent"]["optimizer"]
    assert last["lr"] == pytest.approx(1e-4)


@pytest.mark.parametrize("mode", ["parallel", "vector"])
def test_overlapped_learning_is_deterministic_and_owes_nothing(tmp_path,
                                                              mode):
    """With overlap the gradient steps run during the environment calls: the
    same seed still gives the same scores, and at the end every transition's
    gradient steps have been made."""
    config = dataclasses.replace(preset("quick"), episodes=3, overlap=True)
    if mode == "vector":
        config = dataclasses.replace(config, mode="vector", num_envs=2)
    first = train(config, str(tmp_path / "a"), progress_bar=False)
    train(config, str(tmp_path / "b"), progress_bar=False)
    scores = [[r["score"] for r in _rows(tmp_path / d)] for d in "ab"]
    assert scores[0] == scores[1]
    # Every trigger after the buffer first held more than learn_start (one
    # batch) was made, none is left owed; the step that crosses learn_start
    # may hold up to one step's transitions (num_envs x 2 landers).
    triggers = first["transitions"] // config.update_every
    per_step = config.num_envs * config.env_config["n_landers"]
    assert first["updates"] <= triggers
    assert first["updates"] >= (first["transitions"] - config.batch_size
                                - per_step) // config.update_every - 1 > 0
    saved = torch.load(tmp_path / "a" / CHECKPOINT)
    assert saved["progress"]["owed_updates"] == 0
    assert first["env_call_overlapped_s"] > 0
    assert {"env", "act", "sample", "learn", "other"} == set(
        first["time_split_s"]) - {"store"}


@pytest.mark.parametrize("mode,explore_zeta,prioritized_alpha,explore_guide",
                         [("parallel", 0.0, 0.0, 0.0), ("parallel", 2.0, 0.0, 0.0),
                          ("vector", 2.0, 0.0, 0.0), ("vector", 0.0, 0.6, 0.0),
                          ("vector", 0.0, 0.0, 1.0)])
def test_same_seed_same_scores(tmp_path, mode, explore_zeta, prioritized_alpha,
                               explore_guide):
    config = dataclasses.replace(preset("quick"), episodes=3, mode=mode,
                                 num_envs=2 if mode == "vector" else 1,
                                 explore_zeta=explore_zeta, eps_decay=0.9,
                                 prioritized_alpha=prioritized_alpha,
                                 explore_guide=explore_guide)
    train(config, str(tmp_path / "a"), progress_bar=False)
    train(config, str(tmp_path / "b"), progress_bar=False)
    scores = [[r["score"] for r in _rows(tmp_path / d)] for d in "ab"]
    assert scores[0] == scores[1]


@pytest.mark.parametrize("prioritized_alpha", [0.0, 0.6])
def test_resume_continues_the_run(tmp_path, prioritized_alpha):
    short = dataclasses.replace(preset("quick"), episodes=3,
                                prioritized_alpha=prioritized_alpha)
    first = train(short, str(tmp_path), progress_bar=False)
    longer = dataclasses.replace(short, episodes=6)
    second = train(longer, str(tmp_path), resume=True, progress_bar=False)
    rows = _rows(tmp_path)
    assert len(rows) == 6
    _check_log(rows, longer)
    assert second["updates"] > first["updates"]
    assert second["env_steps"] > first["env_steps"]
    changed = dataclasses.replace(longer, lr=1e-3)
    with pytest.raises(ValueError, match=r"other values of \['lr'\]"):
        train(changed, str(tmp_path), resume=True, progress_bar=False)


def test_command_line_evaluate_gif_and_plot(tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["train", "--preset", "quick", "--episodes", "2", "--out",
                 str(run), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    summary = json.loads((run / SUMMARY).read_text())
    assert (f"{summary['env_steps']:,} env steps, {summary['updates']:,} "
            "updates; time split: environment") in printed
    assert "gradient steps" in printed and "replay sampling" in printed
    assert main(["summary", str(run)]) == 0
    # The same two lines that ended the training command's output.
    again = capsys.readouterr().out.strip()
    assert again.count("\n") == 1 and printed.rstrip().endswith(again)
    policy, config = evaluate.load_policy(str(run / CHECKPOINT))
    result = evaluate.evaluate(policy, config.env_config, episodes=2)
    assert result["episodes"] == 2
    rates = (result["landing_rate"] + result["crash_rate"]
             + result["out_of_bounds_rate"] + result["truncated_rate"])
    assert rates == pytest.approx(1.0)
    heuristic = evaluate.evaluate(evaluate.heuristic_policy,
                                  config.env_config, episodes=2)
    assert np.isfinite(heuristic["mean_score"])
    gif = tmp_path / "episode.gif"
    info = evaluate.save_gif(policy, config.env_config, str(gif))
    with Image.open(gif) as image:
        assert image.size == (600, 400)
        assert image.n_frames == info["frames"] > 1
    png = tmp_path / "fig.png"
    capsys.readouterr()
    assert main(["plot", str(run / LOG), "--out", str(png)]) == 0
    assert png.stat().st_size > 1000


def test_command_line_refuses_a_bad_flag_naming_it_and_its_range(tmp_path,
                                                                  capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["train", "--preset", "quick", "--explore-guide", "1.5", "--out",
              str(tmp_path / "run")])
    assert exit_info.value.code == 2
    assert ("explore_guide = 1.5 is out of range; allowed: [0, 1]"
            in capsys.readouterr().err)
    assert not (tmp_path / "run").exists()


def test_resume_after_the_server_restarted(tmp_path):
    """The server dies mid-run (its environments with it): the trainer stops
    with the server's error, and `--resume` against a new server re-creates
    the environments and finishes from the last checkpoint."""
    import threading
    import time

    import multi_lunar_lander as mll

    config = dataclasses.replace(preset("quick"), episodes=400)
    checkpoint = tmp_path / CHECKPOINT
    first = mll.ServerProcess(threads=1)

    def stop_after_first_checkpoint():
        deadline = time.monotonic() + 60
        while not checkpoint.exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        first.stop()

    killer = threading.Thread(target=stop_after_first_checkpoint)
    killer.start()
    try:
        with pytest.raises(mll.MLLError):
            train(config, str(tmp_path), first.address, progress_bar=False)
    finally:
        killer.join()
        first.stop()
    saved = torch.load(checkpoint)["progress"]["episodes"]
    assert 0 < saved < config.episodes
    finished = dataclasses.replace(config, episodes=saved + 4)
    with mll.ServerProcess(threads=1) as second:
        summary = train(finished, str(tmp_path), second.address, resume=True,
                        progress_bar=False)
    assert summary["episodes"] == saved + 4
    rows = _rows(tmp_path)
    assert len(rows) == saved + 4
    _check_log(rows, finished)


def test_export_chooses_and_report_tabulates_seeds(tmp_path, capsys):
    """export picks the checkpoint that lands most on its selection episodes;
    report tables two seeds' runs with their greedy landing rates and plots
    their mean and spread."""
    runs = []
    for seed in (0, 1):
        run = tmp_path / f"seed{seed}"
        train(dataclasses.replace(preset("quick"), episodes=3, seed=seed),
              str(run), progress_bar=False)
        runs.append(run)
    checkpoints = [str(run / CHECKPOINT) for run in runs]
    result = evaluate.export_best(checkpoints, str(tmp_path / "x.qnet"),
                                  episodes=2)
    assert set(result["landing_rates"]) == set(checkpoints)
    assert result["landing_rates"][result["checkpoint"]] == max(
        result["landing_rates"].values())
    for run in runs:
        assert main(["export", str(run / CHECKPOINT), "--out",
                     str(run / "trained.qnet")]) == 0
        assert main(["evaluate", "--policy", "trained", "--weights",
                     str(run / "trained.qnet"), "--episodes", "2", "--json",
                     str(run / "eval.json")]) == 0
    # --env default: there one lander's crash ends its neighbours' episodes
    # (aborted); the paper's environment flies them on.
    for env, aborts in (("default", True), ("paper", False)):
        assert main(["evaluate", "--policy", "random", "--env", env,
                     "--episodes", "3", "--json", str(tmp_path / "r.json")]) == 0
        result = json.loads((tmp_path / "r.json").read_text())
        assert (result["aborted_rate"] > 0) == aborts
        assert sum(result[rate] for rate in (
            "landing_rate", "crash_rate", "out_of_bounds_rate",
            "truncated_rate", "aborted_rate")) == pytest.approx(1.0)
    capsys.readouterr()
    assert main(["report", *map(str, runs), "--out", str(tmp_path)]) == 0
    lines = (tmp_path / "seeds.md").read_text().splitlines()
    assert [line.split(" | ")[0] for line in lines[2:]] == [
        "| 0", "| 1", "| mean", "| std", "| min", "| max"]
    for line, run in zip(lines[2:4], runs):
        landing = json.loads((run / "eval.json").read_text())["landing_rate"]
        assert f"| {100 * landing:.0f}% | missed |" in line
    assert "0 of 2 met, 0 of them within 600 s" in lines[4]
    assert (tmp_path / "seeds.png").stat().st_size > 1000
