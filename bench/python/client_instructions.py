#!/usr/bin/env python3
"""The Python client's own cost per vector_env step in CPU instructions (valgrind callgrind),
which unlike CPU time does not depend on what else the machine is running.

One real mll_server (not under valgrind) holds `--envs` envs x `--n_landers` landers; a client
process under callgrind makes `--steps` calls of one kind after the same set-up, and a run with
no calls gives the set-up's count, so (run - set-up) / steps is the cost of one step:

  packed   vector_env.step: actions array in, numpy columns out (one packed StepBatch)
  per_env  the same step in StepBatch's per-env form (bench_client.PerEnvForm, what vector_env
           did before the packed form)
  raw      the floor: the packed request's bytes sent as bytes and the response's bytes
           returned unparsed, through the same gRPC Python channel (no protobuf, no numpy)

Counts are given for the calling thread (Python, protobuf, numpy and gRPC's synchronous part
of the call) and for all threads of the client process: gRPC's background threads wake on
timers, so their share grows with the run's wall time under valgrind, not only with the work.
Loopback only; bounded by --steps and a timeout per run.

    .venv/bin/python bench/python/client_instructions.py --server build/server/service/mll_server
"""

from __future__ import annotations

import argparse
import os
import pathlib
import re
import subprocess
import sys
import tempfile

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
REPO = HERE.parents[1]
KINDS = ("none", "raw", "packed", "per_env")


def client(kind: str, steps: int, address: str, envs: int, n_landers: int) -> None:
    """Child process (run under callgrind): the same set-up for every kind, then `steps` calls."""
    import grpc

    import multi_lunar_lander as mll

    sys.path.insert(0, str(HERE))
    from bench_client import PerEnvForm

    env = mll.vector_env(envs, address=address, n_landers=n_landers)
    env.reset(seed=0)
    table = np.random.default_rng(0).integers(0, 4, size=(256, envs, n_landers), dtype=np.int32)
    per_env = PerEnvForm(env)
    server = env._servers[0]
    raw_requests = []
    for actions in table:  # Each step's packed request, as bytes.
        server.actions.data = actions.astype("<i4").tobytes()
        raw_requests.append(server.message.step_batch.SerializeToString())
    channel = grpc.insecure_channel(address)
    raw = channel.unary_unary("/mll.v1.MultiLunarLander/StepBatch")
    raw(raw_requests[0])  # Every kind's first call is made here, outside the count.
    env.step(table[0])
    per_env.step(table[0])
    for i in range(steps if kind != "none" else 0):
        if kind == "raw":
            raw(raw_requests[i % 256])
        elif kind == "packed":
            env.step(table[i % 256])
        else:
            per_env.step(table[i % 256])
    channel.close()
    env.close()


def thread_counts(folder: pathlib.Path, kind: str) -> dict[str, int]:
    """Instructions of the calling (main) thread and of all threads, from callgrind's per-thread
    files `<kind>-01` (the main thread), `<kind>-02`, ..."""
    counts = {}
    for path in sorted(folder.glob(f"{kind}-*")):
        counts[path.name.rsplit("-", 1)[1]] = int(re.search(r"^totals: (\d+)", path.read_text(), re.M).group(1))
    return {"main": counts["01"], "all": sum(counts.values())}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--server", default=os.environ.get("MLL_SERVER_BIN", str(REPO / "build/server/service/mll_server")))
    parser.add_argument("--envs", type=int, default=64)
    parser.add_argument("--n_landers", type=int, default=3)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--client", choices=KINDS, help=argparse.SUPPRESS)
    parser.add_argument("--address", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.client:
        client(args.client, args.steps, args.address, args.envs, args.n_landers)
        return 0

    import multi_lunar_lander as mll

    counts = {}
    with mll.ServerProcess(args.server, threads=2) as server, tempfile.TemporaryDirectory() as tmp:
        for kind in KINDS:
            subprocess.run(
                ["valgrind", "--tool=callgrind", "--separate-threads=yes", f"--callgrind-out-file={tmp}/{kind}",
                 sys.executable, __file__, f"--client={kind}", f"--steps={args.steps}", f"--address={server.address}",
                 f"--envs={args.envs}", f"--n_landers={args.n_landers}"],
                capture_output=True, text=True, timeout=900, check=True,
            )
            counts[kind] = thread_counts(pathlib.Path(tmp), kind)
    agent_steps = args.envs * args.n_landers
    print(f"client instructions per step, {args.envs} envs x {args.n_landers} landers, {args.steps} steps each:")
    print("| form | calling thread per step | per agent-step | vs floor | all client threads per step | vs floor |")
    print("|---|---|---|---|---|---|")
    per_step = {
        kind: {thread: (counts[kind][thread] - counts["none"][thread]) / args.steps for thread in ("main", "all")}
        for kind in KINDS[1:]
    }
    floor = per_step["raw"]
    for kind, what in (("raw", "raw bytes StepBatch (floor)"), ("packed", "vector_env.step, packed"),
                       ("per_env", "same step, per-env form")):
        main, every = per_step[kind]["main"], per_step[kind]["all"]
        print(f"| {what} | {main:,.0f} | {main / agent_steps:,.0f} | {main / floor['main']:.2f} "
              f"| {every:,.0f} | {every / floor['all']:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
