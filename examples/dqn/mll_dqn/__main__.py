"""Command line: train, evaluate, plot, gif.

  python -m mll_dqn train --preset fast --out runs/fast
  python -m mll_dqn train --preset paper --out runs/paper --resume
  python -m mll_dqn evaluate --checkpoint runs/fast/checkpoint.pt
  python -m mll_dqn evaluate --policy heuristic
  python -m mll_dqn plot runs/fast/episodes.csv --out fig.png
  python -m mll_dqn gif --checkpoint runs/fast/checkpoint.pt --out fast.gif
  python -m mll_dqn summary runs/fast
  python -m mll_dqn export runs/fast/checkpoint.pt runs/fast/best.pt --out fast.qnet
  python -m mll_dqn evaluate --policy trained --weights fast.qnet
  python -m mll_dqn report runs/default/seed* --out runs/default

Every command takes --address host:port; without it the client starts an
embedded server for the run.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys

from mll_dqn.config import PAPER_ENV_CONFIG, PRESETS, TrainConfig, preset
from mll_dqn.qnet_file import SHIPPED

# Fields of TrainConfig that are not plain scalars, set by other means.
_NOT_FLAGS = ("env_config", "hidden")


def _parse_bool(text: str) -> bool:
    if text.lower() in ("1", "true", "yes", "on"):
        return True
    if text.lower() in ("0", "false", "no", "off"):
        return False
    raise argparse.ArgumentTypeError(
        f"{text!r} is not a boolean; allowed: true/false")


def _add_config_flags(parser: argparse.ArgumentParser) -> None:
    """One --flag per scalar TrainConfig field, overriding the preset."""
    defaults = TrainConfig()
    for field in dataclasses.fields(TrainConfig):
        if field.name in _NOT_FLAGS:
            continue
        default = getattr(defaults, field.name)
        kind = {bool: _parse_bool, int: int, float: float,
                str: str}.get(type(default), int)
        parser.add_argument("--" + field.name.replace("_", "-"),
                            dest=field.name, type=kind, default=None,
                            help=f"overrides the preset (paper: {default})")


def _config_from_args(args) -> TrainConfig:
    config = preset(args.preset)
    overrides = {f.name: getattr(args, f.name)
                 for f in dataclasses.fields(TrainConfig)
                 if f.name not in _NOT_FLAGS
                 and getattr(args, f.name) is not None}
    return dataclasses.replace(config, **overrides)


def _policy(args):
    """(policy, env_config) for evaluate and gif."""
    from mll_dqn import evaluate
    if args.checkpoint:
        policy, config = evaluate.load_policy(args.checkpoint)
        return policy, config.env_config
    if args.policy == "heuristic":
        return evaluate.heuristic_policy, dict(PAPER_ENV_CONFIG)
    if args.policy == "random":
        return evaluate.random_policy(args.seed), dict(PAPER_ENV_CONFIG)
    if args.policy == "trained":
        from mll_dqn.qnet_file import TrainedPilot
        return TrainedPilot(args.weights), dict(PAPER_ENV_CONFIG)
    raise SystemExit(
        "give --checkpoint PATH or --policy heuristic|random|trained")


# The environments --env names: the paper's experiment, and the
# environment's own defaults (3 landers, 500 steps, shared rewards, a crash
# ends every lander's episode).
EVALUATION_ENVS = {"paper": PAPER_ENV_CONFIG, "default": {}}


# Names of the time split's parts in the headline, in order.
_SPLIT_NAMES = (("env", "environment"), ("act", "action selection"),
                ("sample", "replay sampling"), ("learn", "gradient steps"),
                ("store", "replay store"), ("other", "other"))


def headline(summary) -> str:
    """The run's figures in two lines: wall and CPU time, counts, time split
    (fractions of wall time) and the score criteria."""
    split = summary["time_split_fraction"]
    parts = ", ".join(f"{label} {100 * split[key]:.0f}%"
                      for key, label in _SPLIT_NAMES if key in split)
    overlapped = summary.get("env_call_overlapped_s")
    if overlapped:
        parts += (f" (environment calls overlapped with the above: "
                  f"{overlapped:.0f} s)")

    def number(value):
        return "-" if value is None else f"{value:,.0f}"

    return (f"wall {summary['wall_s']:.0f} s, trainer CPU "
            f"{summary['trainer_cpu_s']:.0f} s, {summary['episodes']} episodes, "
            f"{summary['env_steps']:,} env steps, {summary['updates']:,} "
            f"updates; time split: {parts}\n"
            f"50-episode mean at the end {number(summary['final_mean50'])}, "
            f"last-200 mean {number(summary['mean_last200'])}, first 50-episode "
            f"mean >= 1,400 at episode "
            f"{number(summary['first_episode_mean50_ge_1400'])}")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m mll_dqn",
                                     description=__doc__.split("\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)

    train_cmd = commands.add_parser("train", help="train a shared DQN")
    train_cmd.add_argument("--preset", default="default",
                           choices=sorted(PRESETS),
                           help="default: the robust preset of docs/dqn.md; "
                           "paper: the paper's algorithm as is")
    train_cmd.add_argument("--out", required=True, help="run directory")
    train_cmd.add_argument("--resume", action="store_true",
                           help="continue from OUT/checkpoint.pt")
    train_cmd.add_argument("--no-progress", action="store_true",
                           help="no tqdm bar")
    _add_config_flags(train_cmd)

    for name, help_text in (("evaluate", "greedy evaluation"),
                            ("gif", "animated GIF of one episode")):
        cmd = commands.add_parser(name, help=help_text)
        cmd.add_argument("--checkpoint", help="a training checkpoint")
        cmd.add_argument("--policy", choices=("heuristic", "random", "trained"),
                         help="a baseline, or a .qnet file's network, instead "
                         "of a checkpoint")
        cmd.add_argument("--weights", default=SHIPPED,
                         help="--policy trained: the .qnet file (default: the "
                         "shipped examples/dqn/trained.qnet)")
        cmd.add_argument("--seed", type=int, default=None,
                         help="first episode's seed")
        cmd.add_argument("--env", choices=sorted(EVALUATION_ENVS),
                         help="fly on this environment instead of the one "
                         "the policy was trained on (the baselines and "
                         "--policy trained: the paper's)")
    commands.choices["evaluate"].add_argument("--episodes", type=int,
                                              default=100)
    commands.choices["evaluate"].add_argument("--json",
                                              help="also write results here")
    commands.choices["gif"].add_argument("--out", required=True)

    export_cmd = commands.add_parser(
        "export", help="a checkpoint's network as a .qnet file (numpy/C++)")
    export_cmd.add_argument("checkpoints", nargs="+",
                            help="checkpoints; with several, the one whose "
                            "greedy policy lands most often is exported")
    export_cmd.add_argument("--out", required=True, help=".qnet file")
    export_cmd.add_argument("--episodes", type=int, default=30,
                            help="greedy episodes per checkpoint when choosing")

    report_cmd = commands.add_parser(
        "report", help="per-seed table and mean/spread plot of several runs")
    report_cmd.add_argument("runs", nargs="+", help="run directories")
    report_cmd.add_argument("--out", required=True,
                            help="directory for seeds.md and seeds.png")

    summary_cmd = commands.add_parser(
        "summary", help="a finished run's figures in two lines")
    summary_cmd.add_argument("run", help="run directory (holding summary.json)")

    plot_cmd = commands.add_parser("plot", help="score per episode (figure 2)")
    plot_cmd.add_argument("logs", nargs="+", help="episodes.csv files")
    plot_cmd.add_argument("--labels", nargs="*")
    plot_cmd.add_argument("--title", default="")
    plot_cmd.add_argument("--out", required=True)

    for cmd in commands.choices.values():
        cmd.add_argument("--address", default=None,
                         help="host:port of a server (default: embedded)")
    args = parser.parse_args(argv)

    if args.command == "train":
        from mll_dqn.train import train
        config = _config_from_args(args)
        try:
            config.validate()
        except ValueError as error:
            parser.error(str(error))
        summary = train(config, args.out, args.address,
                        resume=args.resume, progress_bar=not args.no_progress)
        summary.pop("config")
        print(json.dumps(summary, indent=2))
        print(headline(summary))
    elif args.command == "summary":
        from mll_dqn.train import SUMMARY
        with open(os.path.join(args.run, SUMMARY)) as f:
            print(headline(json.load(f)))
    elif args.command in ("evaluate", "gif"):
        from mll_dqn import evaluate
        from mll_dqn.train import use_one_thread
        use_one_thread()
        policy, env_config = _policy(args)
        if args.env:
            env_config = dict(EVALUATION_ENVS[args.env])
        seed = evaluate.EVAL_SEED if args.seed is None else args.seed
        if args.command == "evaluate":
            result = evaluate.evaluate(policy, env_config, args.episodes,
                                       args.address, seed)
            if args.json:
                with open(args.json, "w") as f:
                    json.dump(result, f, indent=2)
        else:
            result = evaluate.save_gif(policy, env_config, args.out,
                                       args.address, seed)
        print(json.dumps(result, indent=2))
    elif args.command == "export":
        from mll_dqn import evaluate
        from mll_dqn.train import use_one_thread
        use_one_thread()
        result = evaluate.export_best(args.checkpoints, args.out,
                                      args.episodes, args.address)
        print(json.dumps(result, indent=2))
    elif args.command == "report":
        from mll_dqn.report import report
        print(report(args.runs, args.out))
    else:
        from mll_dqn.plot import plot
        plot(args.logs, args.out, args.labels, args.title)
        print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
