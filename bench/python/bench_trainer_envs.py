#!/usr/bin/env python3
"""The trainers' adapters against the raw vector env they are built on, in the same run:
agent-steps/s of `gym_vector_env` (gymnasium.vector.VectorEnv) and `sb3_vec_env` (SB3 VecEnv)
at `--envs` envs x `--n_landers` landers, each against `vector_env` with the same envs, options
and random discrete actions (auto-reset), on one server with `--threads` threads. Target for
gym_vector_env: >= 90% of vector_env.

The three sides alternate in every round (so that a change of machine load hits all of them),
each bounded by `--steps` steps and `--seconds` seconds per round. Beside wall-clock
throughput, the CPU time per agent-step (this process + the server process), which a loaded
machine does not distort: the adapters only add client work. Loopback only. Prints a Markdown
table and JSON.

    .venv/bin/python bench/python/bench_trainer_envs.py --server build/server/service/mll_server
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import time

import numpy as np

from process_cpu import process_cpu_s

REPO = pathlib.Path(__file__).resolve().parents[2]


def run(step, actions: np.ndarray, steps: int, seconds: float, server_pid: int | None) -> tuple[int, float, float]:
    """(steps done, wall seconds, CPU seconds of this process and the server, if any) of
    stepping with the rows of `actions` in turn."""

    def cpu_s() -> float:
        return time.process_time() + (process_cpu_s(server_pid) if server_pid else 0.0)

    deadline = time.perf_counter() + seconds
    started, cpu = time.perf_counter(), cpu_s()
    done = 0
    while done < steps and time.perf_counter() < deadline:
        step(actions[done % len(actions)])
        done += 1
    return done, time.perf_counter() - started, cpu_s() - cpu


def alternate(sides: dict, rounds: int, steps: int, seconds: float) -> tuple[dict, dict]:
    """Steps every side in turn in each of `rounds` rounds (so that a change of machine load hits
    all of them), each bounded by `steps` calls and `seconds`. sides: name -> (step, actions,
    counted steps per call, server pid or None). Returns per-round lists of counted steps per
    second and of CPU microseconds per counted step (this process + the server), by name."""
    rates: dict[str, list[float]] = {name: [] for name in sides}
    cpu_us: dict[str, list[float]] = {name: [] for name in sides}
    for _ in range(rounds):
        for name, (step, actions, per_call, server_pid) in sides.items():
            done, wall, cpu = run(step, actions, steps, seconds, server_pid)
            rates[name].append(done * per_call / wall)
            cpu_us[name].append(cpu * 1e6 / (done * per_call))
    return rates, cpu_us


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--server", default=os.environ.get("MLL_SERVER_BIN", str(REPO / "build/server/service/mll_server")))
    parser.add_argument("--envs", type=int, default=64)
    parser.add_argument("--n_landers", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--steps", type=int, default=500, help="steps per round and side")
    parser.add_argument("--seconds", type=float, default=10.0, help="time bound per round and side")
    args = parser.parse_args()
    os.environ["MLL_SERVER_BIN"] = args.server
    import multi_lunar_lander as mll

    rows = args.envs * args.n_landers
    table = np.random.default_rng(0).integers(0, 4, size=(256, rows), dtype=np.int32)
    with mll.ServerProcess(threads=args.threads) as server:
        options = dict(address=server.address, n_landers=args.n_landers)
        raw = mll.vector_env(args.envs, **options)
        gym_env = mll.gym_vector_env(args.envs, **options)
        sb3_env = mll.sb3_vec_env(args.envs, **options)
        raw.reset(seed=0)
        gym_env.reset(seed=0)
        sb3_env.seed(0)
        sb3_env.reset()
        sides = {
            "vector_env": (raw.step, table.reshape(len(table), args.envs, args.n_landers), rows, server.pid),
            "gym_vector_env": (gym_env.step, table, rows, server.pid),
            "sb3_vec_env": (sb3_env.step, table, rows, server.pid),
        }
        rates, cpu_us = alternate(sides, args.rounds, args.steps, args.seconds)
        for env in (raw, gym_env, sb3_env):
            env.close()
    sides = ("gym_vector_env", "sb3_vec_env")
    ratios = {name: [side / base for side, base in zip(rates[name], rates["vector_env"])] for name in sides}
    cpu_ratios = {name: [base / side for side, base in zip(cpu_us[name], cpu_us["vector_env"])] for name in sides}
    print(
        f"| side | agent-steps/s (median of {args.rounds} rounds) | vs vector_env (median; per round) "
        "| CPU us per agent-step, client + server | vs vector_env, CPU (median; per round) |"
    )
    print("|---|---|---|---|---|")
    print(f"| vector_env | {np.median(rates['vector_env']):,.0f} | 100% | {np.median(cpu_us['vector_env']):.2f} | 100% |")
    for name in sides:
        wall = ", ".join(f"{value:.2f}" for value in ratios[name])
        cpu = ", ".join(f"{value:.2f}" for value in cpu_ratios[name])
        print(
            f"| {name} | {np.median(rates[name]):,.0f} | {np.median(ratios[name]):.0%} ({wall}) "
            f"| {np.median(cpu_us[name]):.2f} | {np.median(cpu_ratios[name]):.0%} ({cpu}) |"
        )
    print(json.dumps({"args": vars(args), "agent_steps_per_s": rates, "cpu_us_per_agent_step": cpu_us,
                      "ratios": ratios, "cpu_ratios": cpu_ratios}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
