#!/usr/bin/env python3
"""Benchmarks of the Python client, each against a floor measured in the same run:

1. vector_env throughput: agent-steps/s of `--envs` envs x `--n_landers` landers stepped from
   Python (one StepBatch per step, random discrete actions, auto-reset), against the core
   stepping the same number of envs in-process on `--threads` threads (mll_core_batch_timing,
   built from bench/python/core_batch_timing.cc). Target: >= 70 %.
2. parallel_env step latency: p50 of one `step()` of a `--n_landers` env (actions dict in,
   five dicts out), against a bare Python gRPC echo (a Python grpc server in another process
   returning a real StepEnvResponse's bytes for a real StepEnvRequest's bytes, no protobuf
   parsing on either side). Target: <= 1.5x.

Loopback only; every loop is bounded in count and time. Prints a Markdown table and JSON.

    .venv/bin/python bench/python/bench_client.py \
        --server build/server/service/mll_server --core_timing build/bench/python/mll_core_batch_timing
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys
import tempfile
import time
from concurrent import futures

import grpc
import numpy as np

REPO = pathlib.Path(__file__).resolve().parents[2]
ECHO_METHOD = "/mll.bench.Echo/Echo"


def _echo_server(response_path: str) -> None:
    """Child process: serves ECHO_METHOD, answering every request with the given bytes."""
    response = pathlib.Path(response_path).read_bytes()
    handler = grpc.method_handlers_generic_handler(
        "mll.bench.Echo", {"Echo": grpc.unary_unary_rpc_method_handler(lambda request, context: response)}
    )
    server = grpc.server(futures.ThreadPoolExecutor(max_workers=2))
    server.add_generic_rpc_handlers((handler,))
    port = server.add_insecure_port("127.0.0.1:0")
    server.start()
    print(port, flush=True)
    sys.stdin.read()  # Runs until the parent closes our stdin.
    server.stop(0)


def _percentiles(samples_ns: list[int]) -> dict:
    array = np.array(samples_ns, dtype=np.float64) / 1000.0
    return {"p50_us": float(np.percentile(array, 50)), "p99_us": float(np.percentile(array, 99)), "n": len(samples_ns)}


def bench_vector(mll, address: str, envs: int, n_landers: int, steps: int, seconds: float) -> dict:
    vector = mll.vector_env(envs, address=address, n_landers=n_landers)
    rng = np.random.default_rng(0)
    table = rng.integers(0, 4, size=(256, envs, n_landers), dtype=np.int32)
    vector.reset(seed=0)
    for step in range(20):  # Warm-up.
        vector.step(table[step % 256])
    agent_steps, done = 0, 0
    start = time.perf_counter()
    deadline = start + seconds
    while done < steps and time.perf_counter() < deadline:
        active = vector.step(table[done % 256])[4]
        agent_steps += int(active.sum())
        done += 1
    elapsed = time.perf_counter() - start
    vector.close()
    return {"steps": done, "agent_steps": agent_steps, "seconds": elapsed, "agent_steps_per_s": agent_steps / elapsed}


def bench_core(binary: str, envs: int, n_landers: int, threads: int, steps: int, seconds: float) -> dict:
    output = subprocess.run(
        [binary, f"--envs={envs}", f"--n_landers={n_landers}", f"--threads={threads}", f"--steps={steps}",
         f"--seconds={seconds}"],
        check=True, capture_output=True, text=True, timeout=seconds + 120,
    ).stdout
    return json.loads(output.strip().splitlines()[-1])


def bench_latency(mll, address: str, n_landers: int, count: int, seconds: float):
    """p50 of parallel_env.step; also returns a real request/response pair for the echo."""
    from multi_lunar_lander import _arrays
    from multi_lunar_lander._stubs import pb

    env = mll.parallel_env(address=address, n_landers=n_landers)
    env.reset(seed=0)
    request = pb.StepEnvRequest(name=env.name)
    _arrays.to_proto(np.zeros(n_landers, np.int32), pb.DTYPE_INT32, request.actions)
    response = env._connection.call("StepEnv", request)
    payload = (request.SerializeToString(), response.SerializeToString())
    rng = np.random.default_rng(1)
    samples = []
    env.reset(seed=0)
    deadline = time.perf_counter() + seconds
    while len(samples) < count and time.perf_counter() < deadline:
        if not env.agents:
            env.reset()
        actions = {agent: int(rng.integers(0, 4)) for agent in env.agents}
        begin = time.perf_counter_ns()
        env.step(actions)
        samples.append(time.perf_counter_ns() - begin)
    env.close()
    return _percentiles(samples[20:]), payload


def bench_echo(payload: tuple[bytes, bytes], count: int, seconds: float) -> dict:
    request, response = payload
    with tempfile.NamedTemporaryFile(suffix=".bin", delete=False) as file:
        file.write(response)
    child = subprocess.Popen(
        [sys.executable, __file__, "--echo_server", file.name], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    try:
        port = int(child.stdout.readline())
        with grpc.insecure_channel(f"127.0.0.1:{port}") as channel:
            echo = channel.unary_unary(ECHO_METHOD)
            echo(request, wait_for_ready=True, timeout=30)
            samples = []
            deadline = time.perf_counter() + seconds
            while len(samples) < count and time.perf_counter() < deadline:
                begin = time.perf_counter_ns()
                reply = echo(request)
                samples.append(time.perf_counter_ns() - begin)
            assert len(reply) == len(response)
    finally:
        child.stdin.close()
        child.wait(timeout=30)
        os.unlink(file.name)
    return _percentiles(samples[20:])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--server", default=os.environ.get("MLL_SERVER_BIN", str(REPO / "build/server/service/mll_server")))
    parser.add_argument("--core_timing", default=str(REPO / "build/bench/python/mll_core_batch_timing"))
    parser.add_argument("--envs", type=int, default=64)
    parser.add_argument("--n_landers", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--steps", type=int, default=1500, help="vector steps at most (each side)")
    parser.add_argument("--latency_steps", type=int, default=3000)
    parser.add_argument("--seconds", type=float, default=20.0, help="time bound of each measurement")
    parser.add_argument("--echo_server", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.echo_server:
        _echo_server(args.echo_server)
        return 0

    import multi_lunar_lander as mll

    with mll.ServerProcess(args.server, threads=args.threads) as server:
        vector = bench_vector(mll, server.address, args.envs, args.n_landers, args.steps, args.seconds)
        latency, payload = bench_latency(mll, server.address, args.n_landers, args.latency_steps, args.seconds)
    core = bench_core(args.core_timing, args.envs, args.n_landers, args.threads, args.steps, args.seconds)
    echo = bench_echo(payload, args.latency_steps, args.seconds)

    throughput_ratio = vector["agent_steps_per_s"] / core["agent_steps_per_s"]
    latency_ratio = latency["p50_us"] / echo["p50_us"]
    print(f"| measurement | ours | floor (same run) | ratio | target |")
    print(f"|---|---|---|---|---|")
    print(
        f"| vector_env {args.envs} envs x {args.n_landers} landers, agent-steps/s | {vector['agent_steps_per_s']:,.0f} "
        f"| core in-process, {args.threads} threads: {core['agent_steps_per_s']:,.0f} | {throughput_ratio:.0%} | >= 70% |"
    )
    print(
        f"| parallel_env.step p50 ({args.n_landers} landers), us | {latency['p50_us']:.0f} (p99 {latency['p99_us']:.0f}) "
        f"| Python gRPC echo, {len(payload[0])} B / {len(payload[1])} B: {echo['p50_us']:.0f} (p99 {echo['p99_us']:.0f}) "
        f"| {latency_ratio:.2f}x | <= 1.5x |"
    )
    print(json.dumps({"vector": vector, "core": core, "latency": latency, "echo": echo,
                      "throughput_ratio": throughput_ratio, "latency_ratio": latency_ratio}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
