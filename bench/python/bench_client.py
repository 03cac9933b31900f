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
import resource
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


class VectorRunner:
    """Steps one vector_env with random discrete actions (a fixed table, so each round does the
    same kind of work); each call to run() is one bounded round."""

    def __init__(self, mll, address: str, envs: int, n_landers: int):
        self.env = mll.vector_env(envs, address=address, n_landers=n_landers)
        self.table = np.random.default_rng(0).integers(0, 4, size=(256, envs, n_landers), dtype=np.int32)
        self.env.reset(seed=0)
        self.done = 0
        self.run(20, 10.0)  # Warm-up.

    def run(self, steps: int, seconds: float, server_pid: int | None = None) -> dict:
        agent_steps, count = 0, 0
        cpu_before = time.process_time() + (_process_cpu_s(server_pid) if server_pid else 0.0)
        start = time.perf_counter()
        deadline = start + seconds
        while count < steps and time.perf_counter() < deadline:
            agent_steps += int(self.env.step(self.table[self.done % 256])[4].sum())
            count += 1
            self.done += 1
        elapsed = time.perf_counter() - start
        cpu = time.process_time() + (_process_cpu_s(server_pid) if server_pid else 0.0) - cpu_before
        return {"steps": count, "agent_steps": agent_steps, "seconds": elapsed, "cpu_s": cpu,
                "agent_steps_per_s": agent_steps / elapsed}


def _process_cpu_s(pid: int) -> float:
    """user + system CPU seconds of a process so far (/proc/<pid>/stat)."""
    fields = pathlib.Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def bench_core(binary: str, envs: int, n_landers: int, threads: int, steps: int, seconds: float) -> dict:
    cpu_before = _children_cpu_s()
    output = subprocess.run(
        [binary, f"--envs={envs}", f"--n_landers={n_landers}", f"--threads={threads}", f"--steps={steps}",
         f"--seconds={seconds}"],
        check=True, capture_output=True, text=True, timeout=seconds + 120,
    ).stdout
    result = json.loads(output.strip().splitlines()[-1])
    result["cpu_s"] = _children_cpu_s() - cpu_before
    return result


class LatencyRunner:
    """Times parallel_env.step of one env with random actions, resetting between episodes
    (untimed); also keeps a real StepEnv request/response pair for the echo."""

    def __init__(self, mll, address: str, n_landers: int):
        from multi_lunar_lander import _arrays
        from multi_lunar_lander._stubs import pb

        self.env = mll.parallel_env(address=address, n_landers=n_landers)
        self.env.reset(seed=0)
        request = pb.StepEnvRequest(name=self.env.name)
        _arrays.to_proto(np.zeros(n_landers, np.int32), pb.DTYPE_INT32, request.actions)
        response = self.env._connection.call("StepEnv", request)
        self.payload = (request.SerializeToString(), response.SerializeToString())
        self.rng = np.random.default_rng(1)
        self.env.reset(seed=0)
        self.run(50, 10.0)  # Warm-up.

    def run(self, count: int, seconds: float) -> list[int]:
        samples = []
        deadline = time.perf_counter() + seconds
        while len(samples) < count and time.perf_counter() < deadline:
            if not self.env.agents:
                self.env.reset()
            actions = {agent: int(self.rng.integers(0, 4)) for agent in self.env.agents}
            begin = time.perf_counter_ns()
            self.env.step(actions)
            samples.append(time.perf_counter_ns() - begin)
        return samples


class EchoRunner:
    """A bare Python gRPC echo in a child process: same request bytes in, same response bytes
    out, no protobuf on either side."""

    def __init__(self, payload: tuple[bytes, bytes]):
        self.request, self.response = payload
        with tempfile.NamedTemporaryFile(suffix=".bin", delete=False) as file:
            file.write(self.response)
        self._path = file.name
        self._child = subprocess.Popen(
            [sys.executable, __file__, "--echo_server", file.name], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
            text=True,
        )
        self._channel = grpc.insecure_channel(f"127.0.0.1:{int(self._child.stdout.readline())}")
        self._echo = self._channel.unary_unary(ECHO_METHOD)
        self._echo(self.request, wait_for_ready=True, timeout=30)
        self.run(50, 10.0)  # Warm-up.

    def run(self, count: int, seconds: float) -> list[int]:
        samples = []
        deadline = time.perf_counter() + seconds
        while len(samples) < count and time.perf_counter() < deadline:
            begin = time.perf_counter_ns()
            reply = self._echo(self.request)
            samples.append(time.perf_counter_ns() - begin)
        assert len(reply) == len(self.response)
        return samples

    def close(self) -> None:
        self._channel.close()
        self._child.stdin.close()
        self._child.wait(timeout=30)
        os.unlink(self._path)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--server", default=os.environ.get("MLL_SERVER_BIN", str(REPO / "build/server/service/mll_server")))
    parser.add_argument("--core_timing", default=str(REPO / "build/bench/python/mll_core_batch_timing"))
    parser.add_argument("--envs", type=int, default=64)
    parser.add_argument("--n_landers", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=3, help="alternating rounds of each measurement")
    parser.add_argument("--steps", type=int, default=500, help="vector steps per round at most (each side)")
    parser.add_argument("--latency_steps", type=int, default=1000, help="timed steps per round (each side)")
    parser.add_argument("--seconds", type=float, default=10.0, help="time bound of each round of each side")
    parser.add_argument("--echo_server", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.echo_server:
        _echo_server(args.echo_server)
        return 0

    import multi_lunar_lander as mll

    # Rounds alternate between ours and the floor so that a change of machine load hits both.
    rounds = []
    with mll.ServerProcess(args.server, threads=args.threads) as server:
        vector_runner = VectorRunner(mll, server.address, args.envs, args.n_landers)
        latency_runner = LatencyRunner(mll, server.address, args.n_landers)
        echo_runner = EchoRunner(latency_runner.payload)
        latency_samples, echo_samples = [], []
        for _ in range(args.rounds):
            core = bench_core(args.core_timing, args.envs, args.n_landers, args.threads, args.steps, args.seconds)
            vector = vector_runner.run(args.steps, args.seconds, server.pid)
            rounds.append({
                "vector": vector, "core": core,
                "ratio": vector["agent_steps_per_s"] / core["agent_steps_per_s"],
                # CPU seconds per agent-step, core / (server + Python client): robust to machine load.
                "cpu_ratio": (core["cpu_s"] / core["agent_steps"]) / (vector["cpu_s"] / vector["agent_steps"]),
            })
            latency_samples += latency_runner.run(args.latency_steps, args.seconds)
            echo_samples += echo_runner.run(args.latency_steps, args.seconds)
        echo_runner.close()
        vector_runner.env.close()
        latency_runner.env.close()
    payload = latency_runner.payload
    vector = {"agent_steps_per_s": float(np.median([r["vector"]["agent_steps_per_s"] for r in rounds]))}
    core = {"agent_steps_per_s": float(np.median([r["core"]["agent_steps_per_s"] for r in rounds]))}
    latency, echo = _percentiles(latency_samples), _percentiles(echo_samples)
    throughput_ratio = float(np.median([r["ratio"] for r in rounds]))  # Median of per-round ratios.
    cpu_ratio = float(np.median([r["cpu_ratio"] for r in rounds]))
    latency_ratio = latency["p50_us"] / echo["p50_us"]
    print(f"| measurement | ours | floor (same run) | ratio | target |")
    print(f"|---|---|---|---|---|")
    print(
        f"| vector_env {args.envs} envs x {args.n_landers} landers, agent-steps/s | {vector['agent_steps_per_s']:,.0f} "
        f"| core in-process, {args.threads} threads: {core['agent_steps_per_s']:,.0f} | {throughput_ratio:.0%} | >= 70% |"
    )
    print(
        f"| same, CPU time per agent-step: core / (mll_server + Python client) | | | {cpu_ratio:.0%} | (load-robust view) |"
    )
    print(
        f"| parallel_env.step p50 ({args.n_landers} landers), us | {latency['p50_us']:.0f} (p99 {latency['p99_us']:.0f}) "
        f"| Python gRPC echo, {len(payload[0])} B / {len(payload[1])} B: {echo['p50_us']:.0f} (p99 {echo['p99_us']:.0f}) "
        f"| {latency_ratio:.2f}x | <= 1.5x |"
    )
    print(json.dumps({"rounds": rounds, "latency": latency, "echo": echo,
                      "throughput_ratio": throughput_ratio, "cpu_ratio": cpu_ratio, "latency_ratio": latency_ratio}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
