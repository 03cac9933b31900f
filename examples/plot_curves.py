"""Learning curves of several runs in one figure: each CSV's `--y` column (default the running
50-episode mean score) against its `--x` column (default environment steps; `wall_s` for wall
time). Reads the episodes CSVs of examples/dqn (`episodes.csv`) and of the PPO recipes'
`--episodes-csv`. Runs given the same label (e.g. one recipe's seeds) are drawn as one curve:
their mean, with the band between the lowest and the highest, over the x range they share.

    python examples/plot_curves.py examples/dqn/runs/Q2/episodes.csv:DQN \
        s1.csv:"PPO recipe" s2.csv:"PPO recipe" s3.csv:"PPO recipe" --out ppo_vs_dqn.png
"""

from __future__ import annotations

import argparse
import csv

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def read_curve(path: str, x: str, y: str) -> tuple[np.ndarray, np.ndarray]:
    with open(path) as file:
        rows = list(csv.DictReader(file))
    return np.array([float(r[x]) for r in rows]), np.array([float(r[y]) for r in rows])


def group_band(curves: list[tuple[np.ndarray, np.ndarray]], points: int = 400):
    """(x, mean, low, high) of several curves on a common x grid over the range all of them cover."""
    start = max(float(x[0]) for x, _ in curves)
    stop = min(float(x[-1]) for x, _ in curves)
    grid = np.linspace(start, stop, points)
    values = np.stack([np.interp(grid, x, y) for x, y in curves])
    return grid, values.mean(axis=0), values.min(axis=0), values.max(axis=0)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", help="CSV path, optionally followed by :label")
    parser.add_argument("--x", default="env_steps")
    parser.add_argument("--y", default="mean50")
    parser.add_argument("--line", type=float, default=1400.0, help="a horizontal reference (the paper's score)")
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    groups: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
    for run in args.runs:
        path, _, label = run.partition(":")
        groups.setdefault(label or path, []).append(read_curve(path, args.x, args.y))
    figure, axes = plt.subplots(figsize=(8, 4.5))
    for label, curves in groups.items():
        if len(curves) == 1:
            axes.plot(*curves[0], label=label)
            continue
        grid, mean, low, high = group_band(curves)
        (line,) = axes.plot(grid, mean, label=f"{label} (mean of {len(curves)}, band: min-max)")
        axes.fill_between(grid, low, high, color=line.get_color(), alpha=0.2)
    axes.axhline(args.line, color="gray", linestyle="--", linewidth=1, label=f"{args.line:g}")
    axes.set_xlabel(args.x)
    axes.set_ylabel(args.y)
    axes.legend()
    axes.grid(alpha=0.3)
    figure.tight_layout()
    figure.savefig(args.out, dpi=100)


if __name__ == "__main__":
    main()
