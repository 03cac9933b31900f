"""What the trainer examples share: their common command-line flags and the CSV file of a
learning curve."""

from __future__ import annotations

import argparse
import csv


def parser(description: str, rollout: str) -> argparse.ArgumentParser:
    """The flags of every single-agent (parameter-sharing) example; `rollout` names what
    --num-steps is in that trainer."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--envs", type=int, default=16, help="Multi Lunar Lander environments")
    parser.add_argument("--landers", type=int, default=3, help="landers per environment")
    parser.add_argument("--address", default=None, help="mll_server address(es); default: embedded")
    parser.add_argument("--total-steps", type=int, default=2_000_000, help="lander steps (all rows) in total")
    parser.add_argument("--num-steps", type=int, default=128, help=f"steps per rollout ({rollout})")
    parser.add_argument("--epochs", type=int, default=4)
    parser.add_argument("--lr", type=float, default=2.5e-4)
    parser.add_argument("--max-cycles", type=int, default=500, help="episode step limit")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--csv", default=None, help="write one row per rollout: steps, episodes, mean return")
    return parser


def write_csv(path: str | None, header: list[str], rows) -> None:
    """Writes `rows` under `header` to `path` (nothing when path is None)."""
    if path:
        with open(path, "w", newline="") as file:
            writer = csv.writer(file)
            writer.writerow(header)
            writer.writerows(rows)
