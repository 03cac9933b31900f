#!/usr/bin/env python3
"""Benchmarks of the Python client, each against a floor measured in the same run:

1. vector_env throughput: agent-steps/s of `--envs` envs x `--n_landers` landers stepped from
   Python (one packed StepBatch per step, as one request on vector_env's open Session stream;
   random discrete actions, auto-reset), against the core
   stepping the same number of envs in-process on `--threads` threads (mll_core_batch_timing,
   built from bench/python/core_batch_timing.cc). Target: >= 70 %. Beside it, the same loop over
   the same envs with StepBatch's per-env form (what vector_env sent before the packed form), to
   show what the packed form saves on the client; and the same envs as two vector envs of half
   the size stepped alternately with step_async/step_wait (the server steps one half while the
   client handles the other), the pattern a trainer can use to hide the round trip.
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

from process_cpu import children_cpu_s, process_cpu_s

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


class PerEnvForm:
    """For comparison only: vector_env's step in StepBatch's per-env form, as the client did it
    before the packed form. One StepEnvRequest per env in `steps` (built once; each step replaces
    every env's action bytes), and the results read env by env and stacked per column (one join
    and one frombuffer per column), returning the same arrays as vector_env.step."""

    def __init__(self, vector):
        from multi_lunar_lander._stubs import pb

        self._connection = vector._servers[0].connection
        self._shape = (vector.num_envs, vector.n_landers)
        self.request = pb.StepBatchRequest()
        for name in vector.names:
            step = self.request.steps.add(name=name)
            step.actions.dtype = pb.DTYPE_INT32
            step.actions.shape.append(vector.n_landers)
        self._steps = list(self.request.steps)

    def step(self, actions: np.ndarray):
        raw = np.ascontiguousarray(actions, dtype="<i4").tobytes()
        size = len(raw) // len(self._steps)
        for index, step in enumerate(self._steps):
            step.actions.data = raw[index * size : (index + 1) * size]
        results = self._connection.call("StepBatch", self.request).results
        for index, result in enumerate(results):
            if result.HasField("error"):
                raise RuntimeError(f"env {index}: {result.error.message}")
        datas = [result.data for result in results]
        columns = {
            field: np.frombuffer(b"".join(getattr(data, field).data for data in datas), dtype).reshape(
                self._shape + trailing
            ).astype(result_dtype)
            for field, dtype, result_dtype, trailing in (
                ("observations", "<f4", np.float32, (12,)), ("rewards", "<f4", np.float32, ()),
                ("terminations", "u1", bool, ()), ("truncations", "u1", bool, ()), ("stepped", "u1", bool, ()),
                ("outcomes", "u1", np.uint8, ()), ("episode_returns", "<f4", np.float32, ()),
                ("episode_lengths", "<i4", np.int32, ()),
            )
        }
        auto_reset = np.fromiter((data.auto_reset for data in datas), dtype=bool, count=len(datas))
        episode_over = np.fromiter((data.episode_over for data in datas), dtype=bool, count=len(datas))
        active = columns["stepped"]
        active[auto_reset] = False
        infos = {"auto_reset": auto_reset, "episode_over": episode_over, "outcome": columns["outcomes"],
                 "episode_return": columns["episode_returns"], "episode_length": columns["episode_lengths"]}
        return columns["observations"], columns["rewards"], columns["terminations"], columns["truncations"], active, infos


class _RoundClock:
    """Wall time, the Python client's CPU and (given its pid) mll_server's CPU of one round,
    from construction to result()."""

    def __init__(self, server_pid: int | None):
        self.server_pid = server_pid
        self.server_before = process_cpu_s(server_pid) if server_pid else 0.0
        self.client_before = time.process_time()
        self.start = time.perf_counter()

    def result(self, steps: float, agent_steps: int) -> dict:
        elapsed = time.perf_counter() - self.start
        client = time.process_time() - self.client_before
        server = (process_cpu_s(self.server_pid) if self.server_pid else 0.0) - self.server_before
        return {"steps": steps, "agent_steps": agent_steps, "seconds": elapsed, "cpu_s": client + server,
                "client_cpu_s": client, "agent_steps_per_s": agent_steps / elapsed}


class VectorRunner:
    """Steps one vector_env with random discrete actions (a fixed table, so each round does the
    same kind of work); each call to run() is one bounded round, through vector_env.step or
    (per_env=True) PerEnvForm.step on the same envs."""

    def __init__(self, mll, address: str, envs: int, n_landers: int):
        self.env = mll.vector_env(envs, address=address, n_landers=n_landers)
        self.table = np.random.default_rng(0).integers(0, 4, size=(256, envs, n_landers), dtype=np.int32)
        self.per_env = PerEnvForm(self.env)
        self.env.reset(seed=0)
        self.done = 0
        self.run(20, 10.0)  # Warm-up.
        self.run(20, 10.0, per_env=True)

    def run(self, steps: int, seconds: float, server_pid: int | None = None, per_env: bool = False) -> dict:
        step = self.per_env.step if per_env else self.env.step
        agent_steps, count = 0, 0
        clock = _RoundClock(server_pid)
        deadline = clock.start + seconds
        while count < steps and time.perf_counter() < deadline:
            agent_steps += int(step(self.table[self.done % 256])[4].sum())
            count += 1
            self.done += 1
        return clock.result(count, agent_steps)


def bench_core(binary: str, envs: int, n_landers: int, threads: int, steps: int, seconds: float) -> dict:
    cpu_before = children_cpu_s()
    output = subprocess.run(
        [binary, f"--envs={envs}", f"--n_landers={n_landers}", f"--threads={threads}", f"--steps={steps}",
         f"--seconds={seconds}"],
        check=True, capture_output=True, text=True, timeout=seconds + 120,
    ).stdout
    result = json.loads(output.strip().splitlines()[-1])
    result["cpu_s"] = children_cpu_s() - cpu_before
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


class Halves:
    """The same envs as two vector envs of half the size in EnvPool's async pattern: each call
    sends one half's actions (step_async) and returns the other half's results (step_wait), so
    the server steps one half while the client handles the other. `sending` is the half whose
    actions the next call takes (its rows of the full batch: `rows[sending]`); half 1 starts in
    flight with no-op actions."""

    def __init__(self, mll, address: str, envs: int, n_landers: int):
        split = envs // 2
        self.halves = [mll.vector_env(split, address=address, n_landers=n_landers),
                       mll.vector_env(envs - split, address=address, n_landers=n_landers)]
        self.rows = [slice(0, split), slice(split, envs)]
        for half in self.halves:
            half.reset(seed=0)
        self.sending = 0
        self.halves[1].step_async(np.zeros((envs - split, n_landers), np.int32))

    def step(self, actions: np.ndarray):
        self.halves[self.sending].step_async(actions)
        self.sending = 1 - self.sending
        return self.halves[self.sending].step_wait()

    def close(self) -> None:
        self.halves[1 - self.sending].step_wait()
        for half in self.halves:
            half.close()


class HalvesRunner:
    """VectorRunner's envs as Halves, with the same action table; a round of `steps` steps moves
    every env `steps` times."""

    def __init__(self, mll, address: str, envs: int, n_landers: int):
        self.halves = Halves(mll, address, envs, n_landers)
        self.table = np.random.default_rng(0).integers(0, 4, size=(256, envs, n_landers), dtype=np.int32)
        self.done = 0
        self.run(20, 10.0)  # Warm-up.

    def run(self, steps: int, seconds: float, server_pid: int | None = None) -> dict:
        agent_steps, half_steps = 0, 0
        clock = _RoundClock(server_pid)
        deadline = clock.start + seconds
        while half_steps < 2 * steps and time.perf_counter() < deadline:
            rows = self.halves.rows[self.halves.sending]
            agent_steps += int(self.halves.step(self.table[self.done % 256][rows])[4].sum())
            half_steps += 1
            self.done += half_steps % 2 == 0
        return clock.result(half_steps / 2, agent_steps)

    def close(self) -> None:
        self.halves.close()


def bench_cli(binary: str, address: str, server_pid: int, envs: int, n_landers: int, seconds: float,
              transport: str, clients: int = 1) -> dict:
    """`mll_cli bench` (the C++ VectorEnv, random discrete actions, auto-reset) against the server at
    `address`: its JSON line, plus the CPU seconds of mll_cli (`client_cpu_s`) and of the server
    (`server_cpu_s`) over the whole run, warm-up included."""
    client_before, server_before = children_cpu_s(), process_cpu_s(server_pid)
    output = subprocess.run(
        [binary, "bench", f"--address={address}", f"--envs={envs}", f"--n_landers={n_landers}",
         f"--seconds={seconds}", f"--transport={transport}", f"--clients={clients}"],
        check=True, capture_output=True, text=True, timeout=seconds * 3 + 60,
    ).stdout
    result = json.loads(output.strip().splitlines()[-1])
    result["client_cpu_s"] = children_cpu_s() - client_before
    result["server_cpu_s"] = process_cpu_s(server_pid) - server_before
    return result


def add_binary_arguments(parser: argparse.ArgumentParser) -> None:
    """--server (mll_server), --core_timing (the in-process floor) and --cli (mll_cli), built by
    scripts/build.sh."""
    parser.add_argument("--server", default=os.environ.get("MLL_SERVER_BIN", str(REPO / "build/server/service/mll_server")))
    parser.add_argument("--core_timing", default=str(REPO / "build/bench/python/mll_core_batch_timing"))
    parser.add_argument("--cli", default=str(REPO / "build/client_cpp/mll_cli"))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_binary_arguments(parser)
    parser.add_argument("--envs", type=int, default=64)
    parser.add_argument("--n_landers", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=3, help="alternating rounds of each measurement")
    parser.add_argument(
        "--steps", type=int, default=2000,
        help="vector steps per round at most (each side); rounds of 500 (about 1 s) are dominated by start-up",
    )
    parser.add_argument("--latency_steps", type=int, default=1000, help="timed steps per round (each side)")
    parser.add_argument("--seconds", type=float, default=10.0, help="time bound of each round of each side")
    parser.add_argument("--echo_server", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.echo_server:
        _echo_server(args.echo_server)
        return 0

    import multi_lunar_lander as mll

    # Rounds alternate between ours and the floor so that a change of machine load hits both.
    load_before = os.getloadavg()
    rounds = []
    with mll.ServerProcess(args.server, threads=args.threads) as server:
        vector_runner = VectorRunner(mll, server.address, args.envs, args.n_landers)
        halves_runner = HalvesRunner(mll, server.address, args.envs, args.n_landers)
        latency_runner = LatencyRunner(mll, server.address, args.n_landers)
        echo_runner = EchoRunner(latency_runner.payload)
        latency_samples, echo_samples = [], []
        for _ in range(args.rounds):
            core = bench_core(args.core_timing, args.envs, args.n_landers, args.threads, args.steps, args.seconds)
            one = {"core": core}
            for form in ("packed", "per_env", "halves"):
                if form == "halves":
                    vector = one[form] = halves_runner.run(args.steps, args.seconds, server.pid)
                else:
                    vector = one[form] = vector_runner.run(args.steps, args.seconds, server.pid, form == "per_env")
                one[f"{form}_ratio"] = vector["agent_steps_per_s"] / core["agent_steps_per_s"]
                # CPU seconds per agent-step, core / (server + Python client): robust to machine load.
                one[f"{form}_cpu_ratio"] = (core["cpu_s"] / core["agent_steps"]) / (vector["cpu_s"] / vector["agent_steps"])
                one[f"{form}_client_us"] = 1e6 * vector["client_cpu_s"] / vector["agent_steps"]
            rounds.append(one)
            latency_samples += latency_runner.run(args.latency_steps, args.seconds)
            echo_samples += echo_runner.run(args.latency_steps, args.seconds)
        echo_runner.close()
        vector_runner.env.close()
        halves_runner.close()
        latency_runner.env.close()
    load_after = os.getloadavg()
    payload = latency_runner.payload

    def median(key, sub=None):
        return float(np.median([r[key][sub] if sub else r[key] for r in rounds]))

    def per_round(key):
        return ", ".join(f"{r[key]:.2f}" for r in rounds)

    latency, echo = _percentiles(latency_samples), _percentiles(echo_samples)
    latency_ratio = latency["p50_us"] / echo["p50_us"]
    core_rate = median("core", "agent_steps_per_s")
    core_us = float(np.median([1e6 * r["core"]["cpu_s"] / r["core"]["agent_steps"] for r in rounds]))
    print(f"load average {load_before[0]:.1f} at start, {load_after[0]:.1f} at the end (1-minute)")
    print("| measurement | ours | floor (same run) | ratio (median of per-round ratios) | target |")
    print("|---|---|---|---|---|")
    for form, what in (("packed", "vector_env (packed StepBatch)"), ("per_env", "same loop, per-env StepBatch form"),
                       ("halves", "two vector_env halves alternating step_async/step_wait,")):
        print(
            f"| {what} {args.envs} envs x {args.n_landers} landers, agent-steps/s (wall clock) "
            f"| {median(form, 'agent_steps_per_s'):,.0f} | core in-process, {args.threads} threads: {core_rate:,.0f} "
            f"| {median(form + '_ratio'):.0%} (rounds {per_round(form + '_ratio')}) | >= 70% |"
        )
        print(
            f"| same, CPU per agent-step: core / (mll_server + Python client); the client's own "
            f"| client {median(form + '_client_us'):.2f} us | core {core_us:.2f} us "
            f"| {median(form + '_cpu_ratio'):.0%} (rounds {per_round(form + '_cpu_ratio')}) | (load-robust view) |"
        )
    print(
        f"| parallel_env.step p50 ({args.n_landers} landers), us | {latency['p50_us']:.0f} (p99 {latency['p99_us']:.0f}) "
        f"| Python gRPC echo, {len(payload[0])} B / {len(payload[1])} B: {echo['p50_us']:.0f} (p99 {echo['p99_us']:.0f}) "
        f"| {latency_ratio:.2f}x | <= 1.5x |"
    )
    print(json.dumps({"rounds": rounds, "latency": latency, "echo": echo, "latency_ratio": latency_ratio,
                      "load_average": [load_before, load_after]}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
