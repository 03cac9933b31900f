"""Several seeds' runs side by side: a per-seed table with its spread, and
the mean and spread of the 50-episode mean score across seeds (run_seeds.sh
writes the runs; docs/dqn.md shows the result)."""

from __future__ import annotations

import json
import os
from typing import Dict, List, Sequence

import numpy as np

from mll_dqn.plot import PAPER_SCORE, read_scores, running_mean
from mll_dqn.train import LOG, SUMMARY

# The criteria of docs/dqn.md: 50-episode mean and last-200 mean at least
# PAPER_SCORE after 1,000 episodes, in at most this much wall time.
TIME_LIMIT_S = 600.0
# Written by run_seeds.sh beside each run: greedy evaluation of the
# exported network.
EVAL = "eval.json"


def _row(run_dir: str) -> Dict:
    with open(os.path.join(run_dir, SUMMARY)) as f:
        summary = json.load(f)
    landing = None
    if os.path.exists(os.path.join(run_dir, EVAL)):
        with open(os.path.join(run_dir, EVAL)) as f:
            landing = json.load(f)["landing_rate"]
    # The score criteria apart from the time limit, which depends on the
    # machine's load as well as on the run.
    met = (summary["episodes"] >= 1000
           and summary["final_mean50"] >= PAPER_SCORE
           and summary["mean_last200"] >= PAPER_SCORE)
    return dict(seed=summary["config"]["seed"],
                mean50=summary["final_mean50"],
                last200=summary["mean_last200"],
                first=summary["first_episode_mean50_ge_1400"],
                wall_s=summary["wall_s"], cpu_s=summary["trainer_cpu_s"],
                landing=landing, met=met,
                in_time=met and summary["wall_s"] <= TIME_LIMIT_S)


def _number(value, digits: int = 0) -> str:
    return "-" if value is None else f"{value:,.{digits}f}"


def table(rows: Sequence[Dict]) -> str:
    """Markdown: one line per seed, then mean, standard deviation and range."""
    lines = ["| seed | 50-episode mean at 1,000 | last-200 mean | first "
             "50-episode mean >= 1,400 | wall time (s) | trainer CPU (s) | "
             "greedy landing rate | score criteria |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        landing = "-" if r["landing"] is None else f"{100 * r['landing']:.0f}%"
        lines.append(
            f"| {r['seed']} | {_number(r['mean50'])} | {_number(r['last200'])}"
            f" | {_number(r['first'])} | {_number(r['wall_s'])} | "
            f"{_number(r['cpu_s'])} | {landing} | "
            f"{'met' if r['met'] else 'missed'} |")
    for name, reduce in (("mean", np.mean), ("std", np.std),
                         ("min", np.min), ("max", np.max)):
        cells = []
        for key, scale in (("mean50", 1), ("last200", 1), ("first", 1),
                           ("wall_s", 1), ("cpu_s", 1), ("landing", 100)):
            values = [r[key] for r in rows if r[key] is not None]
            cells.append(_number(scale * reduce(values)) if values else "-")
        cells[-1] += "%" if cells[-1] != "-" else ""
        met = sum(r["met"] for r in rows)
        in_time = sum(r["in_time"] for r in rows)
        lines.append(f"| {name} | " + " | ".join(cells) + " | "
                     + (f"{met} of {len(rows)} met, {in_time} of them "
                        f"within {TIME_LIMIT_S:.0f} s" if name == "mean"
                        else "")
                     + " |")
    return "\n".join(lines)


def plot_seeds(run_dirs: Sequence[str], out_path: str) -> None:
    """Mean over seeds of the 50-episode mean score, with a band of one
    standard deviation and the seeds' range."""
    import matplotlib
    matplotlib.use("Agg")  # Files only; no display needed.
    from matplotlib import pyplot as plt

    curves = [running_mean(read_scores(os.path.join(d, LOG)))
              for d in run_dirs]
    length = min(len(c) for c in curves)
    stack = np.stack([c[:length] for c in curves])
    episodes = np.arange(1, length + 1)
    mean, std = stack.mean(axis=0), stack.std(axis=0)
    fig, ax = plt.subplots(figsize=(8, 4.5))
    ax.fill_between(episodes, stack.min(axis=0), stack.max(axis=0),
                    color="tab:blue", alpha=0.12, label="range over seeds")
    ax.fill_between(episodes, mean - std, mean + std, color="tab:blue",
                    alpha=0.25, label="mean +- 1 std")
    ax.plot(episodes, mean, color="tab:blue", linewidth=2,
            label=f"mean over {len(curves)} seeds")
    ax.axhline(PAPER_SCORE, color="gray", linestyle="--", linewidth=1,
               label=f"paper: {PAPER_SCORE:.0f}")
    ax.set_xlabel("Episode")
    ax.set_ylabel("50-episode mean score")
    ax.set_title("DQN with parameter sharing, 3 landers, seeds "
                 + ", ".join(str(_row(d)["seed"]) for d in run_dirs))
    ax.legend(loc="lower right")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out_path, dpi=110)
    plt.close(fig)


def report(run_dirs: Sequence[str], out_dir: str) -> str:
    """Writes out_dir/seeds.md and out_dir/seeds.png; returns the table."""
    run_dirs = sorted(run_dirs, key=lambda d: _row(d)["seed"])
    rows: List[Dict] = [_row(d) for d in run_dirs]
    os.makedirs(out_dir, exist_ok=True)
    text = table(rows)
    with open(os.path.join(out_dir, "seeds.md"), "w") as f:
        f.write(text + "\n")
    plot_seeds(run_dirs, os.path.join(out_dir, "seeds.png"))
    return text
