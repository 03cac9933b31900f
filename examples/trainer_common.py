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
    parser.add_argument("--paper", action="store_true",
                        help="the environment of the paper's DQN experiment (docs/dqn.md) "
                        "instead of --landers/--max-cycles")
    return parser


# The environment of the paper's DQN experiment (docs/dqn.md).
PAPER_OPTIONS = dict(
    n_landers=3, max_cycles=2000, damage_reward=-300.0, successful_reward=700.0, terminate_reward=-100.0,
    shared_reward=False, terminate_on_damage=False, remove_on_damage=True,
)


def environment_options(args: argparse.Namespace) -> dict:
    """The environment options the flags select: the paper's (--paper) or --landers/--max-cycles."""
    return dict(PAPER_OPTIONS) if args.paper else dict(n_landers=args.landers, max_cycles=args.max_cycles)


def write_csv(path: str | None, header: list[str], rows) -> None:
    """Writes `rows` under `header` to `path` (nothing when path is None)."""
    if path:
        with open(path, "w", newline="") as file:
            writer = csv.writer(file)
            writer.writerow(header)
            writer.writerows(rows)
