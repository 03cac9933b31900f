#!/usr/bin/env python3
"""Our vector env against EnvPool, and gym_vector_env against vector_env, in one run.

1. EnvPool (PyPI `envpool`, bench/python/requirements.txt): its in-process C++ LunarLander-v3,
   `--envs` envs on `--threads` threads, random discrete actions, stepped through its sync API
   (`step`, all envs per call) and its async API (`recv` of `--async_batch` envs, then `send` of
   their actions). The faster of the two is the floor.
   Ours: `vector_env(--envs, n_landers=1)`, the same random discrete actions, auto-reset, on an
   `mll_server --threads=--threads`, over loopback TCP (what the embedded server uses) with each
   step transport (`transport="shared_memory"`, what "auto" picks for a server on this host where
   the native library is built; `"native"`, the library's gRPC stream; `"grpc"`, grpcio's, where
   the package's vector envs have it: a transport they refuse gets no row), and
   over a Unix-domain socket (`mll_server --address=unix:PATH`) with the two stream transports;
   and over TCP (default transport) as two vector envs of
   half the size stepped alternately with step_async/step_wait (each call sends one half's
   actions and returns the other half's results: EnvPool's async pattern with the same batch).
   The C++ client's batched API (mll::client::VectorEnv, as `mll_cli bench --envs=--envs
   --n_landers=1`: random discrete actions, auto-reset, no Python on our side) against the TCP
   side's server, over shared memory and over the native gRPC stream, once per round for
   `--cli_seconds` (after its own warm-up of a tenth of that); its CPU is mll_cli's plus the
   server's over the run, warm-up included.
   For reference (not a floor of this comparison): our core stepping the same 64 one-lander envs
   in-process on the same threads (mll_core_batch_timing, as in bench_client.py; it counts the
   env-steps that stepped a lander, i.e. without the auto-reset steps, about 1 in 100), which
   bounds what any transport can reach.
2. `gym_vector_env` against `vector_env`, `--envs` envs x `--gym_n_landers` landers, on one
   TCP server: target >= 90%.

Counting: env-steps per second on every side, i.e. calls x envs per call / wall seconds (an
EnvPool step and a vector_env step of one env are both one env-step, auto-resets included). Beside
it, CPU microseconds per env-step (this process, plus the server's for ours), which machine load
distorts less. Every side runs in each of `--rounds` rounds, alternating, each bounded by
`--steps` calls and `--seconds`. Loopback only. Prints a Markdown table and JSON.

    .venv/bin/pip install -r bench/python/requirements.txt
    .venv/bin/python bench/python/bench_envpool.py --server build/server/service/mll_server \
        --core_timing build/bench/python/mll_core_batch_timing
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

from bench_client import Halves, add_binary_arguments, bench_cli, bench_core
from bench_trainer_envs import alternate

ENVPOOL_TASK = "LunarLander-v3"


class EnvPoolAsync:
    """EnvPool's async API as one call per batch: recv the next `batch` envs, send their actions."""

    def __init__(self, envpool, envs: int, batch: int, threads: int):
        self.env = envpool.make(ENVPOOL_TASK, env_type="gymnasium", num_envs=envs, batch_size=batch,
                                num_threads=threads, seed=0)
        self.env.async_reset()

    def step(self, actions: np.ndarray) -> None:
        info = self.env.recv()[-1]
        self.env.send(actions, info["env_id"])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_binary_arguments(parser)
    parser.add_argument("--envs", type=int, default=64)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--async_batch", type=int, default=32, help="EnvPool's batch_size in its async API")
    parser.add_argument("--gym_n_landers", type=int, default=3)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--steps", type=int, default=1000, help="calls per round and side")
    parser.add_argument("--seconds", type=float, default=10.0, help="time bound per round and side")
    parser.add_argument("--cli_seconds", type=float, default=1.0, help="mll_cli bench's run per round and transport")
    parser.add_argument("--no_halves", action="store_true", help="leave out the vector_env_tcp_halves side")
    args = parser.parse_args()
    if args.envs % 2 or args.envs // 2 != args.async_batch:
        parser.error("--async_batch must be half of --envs (the halves side steps the same batches)")
    import envpool
    import multi_lunar_lander as mll

    rng = np.random.default_rng(0)
    table = rng.integers(0, 4, size=(256, args.envs), dtype=np.int32)
    half_table = table[:, : args.async_batch]
    gym_rows = args.envs * args.gym_n_landers
    gym_table = rng.integers(0, 4, size=(256, gym_rows), dtype=np.int32)
    load_before = os.getloadavg()
    # The TCP and socket sides each have a server of their own with nothing else on it, so that
    # the two transports are compared on equal servers; the other sides share a third.
    with mll.ServerProcess(args.server, threads=args.threads) as tcp, \
            mll.ServerProcess(args.server, threads=args.threads, unix_socket=True) as unix, \
            mll.ServerProcess(args.server, threads=args.threads) as other:
        sync = envpool.make(ENVPOOL_TASK, env_type="gymnasium", num_envs=args.envs, num_threads=args.threads, seed=0)
        sync.reset()
        pool_async = EnvPoolAsync(envpool, args.envs, args.async_batch, args.threads)
        servers = {"tcp": tcp, "unix": unix}
        ours = {}
        for name, transport in (("tcp", "shared_memory"), ("tcp", "native"), ("tcp", "grpc"), ("unix", "native"),
                                ("unix", "grpc")):
            try:
                ours[name, transport] = mll.vector_env(args.envs, address=servers[name].address, n_landers=1,
                                                       transport=transport)
            except mll.MLLError as error:  # A package whose vector envs lack this transport: no row.
                print(f"vector_env over {name} with transport={transport!r}: {error}", file=sys.stderr)
        for env in ours.values():
            env.reset(seed=0)
        halves = None if args.no_halves else Halves(mll, other.address, args.envs, 1)
        raw = mll.vector_env(args.envs, address=other.address, n_landers=args.gym_n_landers)
        gym_env = mll.gym_vector_env(args.envs, address=other.address, n_landers=args.gym_n_landers)
        raw.reset(seed=0)
        gym_env.reset(seed=0)
        column = table[..., None]
        sides = {
            "envpool_sync": (sync.step, table, args.envs, None),
            "envpool_async": (pool_async.step, half_table, args.async_batch, None),
            **{f"vector_env_{name}_{transport}": (env.step, column, args.envs, servers[name].pid)
               for (name, transport), env in ours.items()},
            **({"vector_env_tcp_halves": (halves.step, half_table[..., None], args.async_batch, other.pid)}
               if halves else {}),
            "raw_vector_env_x3": (raw.step, gym_table.reshape(256, args.envs, args.gym_n_landers), args.envs, other.pid),
            "gym_vector_env_x3": (gym_env.step, gym_table, args.envs, other.pid),
        }
        alternate(sides, 1, 50, args.seconds)  # Warm-up.
        cpp_sides = {f"cpp_vector_env_tcp_{transport}": transport for transport in ("shared_memory", "native")}
        rates = {name: [] for name in (*sides, *cpp_sides, "core_in_process")}
        cpu_us = {name: [] for name in rates}
        for _ in range(args.rounds):
            core = bench_core(args.core_timing, args.envs, 1, args.threads, args.steps, args.seconds)
            rates["core_in_process"].append(core["agent_steps_per_s"])
            cpu_us["core_in_process"].append(core["cpu_s"] * 1e6 / core["agent_steps"])
            for name, transport in cpp_sides.items():
                cpp = bench_cli(args.cli, tcp.address, tcp.pid, args.envs, 1, args.cli_seconds, transport)
                assert cpp["transport"] == transport, cpp
                rates[name].append(cpp["env_steps_per_second"])
                # Its CPU over the whole run, warm-up included, per env-step of the measured part
                # scaled to the whole run.
                run_steps = cpp["env_steps"] * (1 + 0.1 * args.cli_seconds / cpp["seconds"])
                cpu_us[name].append((cpp["client_cpu_s"] + cpp["server_cpu_s"]) * 1e6 / run_steps)
            one_round = alternate(sides, 1, args.steps, args.seconds)
            for name in sides:
                rates[name] += one_round[0][name]
                cpu_us[name] += one_round[1][name]
        for env in (*ours.values(), *([halves] if halves else []), raw, gym_env):
            env.close()
    load_after = os.getloadavg()

    # The floor of each round: EnvPool's faster API in that round.
    floor = [max(pair) for pair in zip(rates["envpool_sync"], rates["envpool_async"])]
    floor_cpu = [min(pair) for pair in zip(cpu_us["envpool_sync"], cpu_us["envpool_async"])]
    print(f"load average {load_before[0]:.1f} at start, {load_after[0]:.1f} at the end (1-minute); "
          f"{args.envs} envs, {args.threads} threads, {args.rounds} rounds")
    print("| side | env-steps/s (median) | vs floor (median; per round) | CPU us per env-step | "
          "vs floor, CPU (median) |")
    print("|---|---|---|---|---|")

    def row(name: str, base: list[float], base_cpu: list[float]) -> None:
        ratios = [ours / floor for ours, floor in zip(rates[name], base)]
        cpu_ratios = [floor / ours for ours, floor in zip(cpu_us[name], base_cpu)]
        print(f"| {name} | {np.median(rates[name]):,.0f} | {np.median(ratios):.2f} "
              f"({', '.join(f'{value:.2f}' for value in ratios)}) | {np.median(cpu_us[name]):.1f} "
              f"| {np.median(cpu_ratios):.2f} |")

    for name in ("envpool_sync", "envpool_async", *cpp_sides, "vector_env_tcp_shared_memory", "vector_env_tcp_native",
                 "vector_env_tcp_grpc",
                 "vector_env_unix_native", "vector_env_unix_grpc", "vector_env_tcp_halves", "core_in_process"):
        if name in rates:
            row(name, floor, floor_cpu)
    print("| (floor above: EnvPool's faster API per round; below: raw_vector_env_x3) | | | | |")
    row("gym_vector_env_x3", rates["raw_vector_env_x3"], cpu_us["raw_vector_env_x3"])
    print(json.dumps({"args": vars(args), "env_steps_per_s": rates, "cpu_us_per_env_step": cpu_us,
                      "floor": floor, "load_average": [load_before, load_after]}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
