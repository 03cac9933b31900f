"""Learning curves of several runs in one figure: each CSV's `--y` column (default the running
50-episode mean score) against its `--x` column (default environment steps). Reads the
episodes CSVs of examples/dqn (`episodes.csv`) and of `examples/ppo_cleanrl.py --episodes-csv`.

    python examples/plot_curves.py examples/dqn/runs/Q2/episodes.csv:DQN out/ppo_paper_episodes.csv:PPO \
        --out ppo_vs_dqn.png
"""

from __future__ import annotations

import argparse
import csv

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", help="CSV path, optionally followed by :label")
    parser.add_argument("--x", default="env_steps")
    parser.add_argument("--y", default="mean50")
    parser.add_argument("--line", type=float, default=1400.0, help="a horizontal reference (the paper's score)")
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    figure, axes = plt.subplots(figsize=(8, 4.5))
    for run in args.runs:
        path, _, label = run.partition(":")
        with open(path) as file:
            rows = list(csv.DictReader(file))
        axes.plot([float(r[args.x]) for r in rows], [float(r[args.y]) for r in rows], label=label or path)
    axes.axhline(args.line, color="gray", linestyle="--", linewidth=1, label=f"{args.line:g}")
    axes.set_xlabel(args.x)
    axes.set_ylabel(args.y)
    axes.legend()
    axes.grid(alpha=0.3)
    figure.tight_layout()
    figure.savefig(args.out, dpi=100)


if __name__ == "__main__":
    main()
