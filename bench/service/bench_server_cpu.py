#!/usr/bin/env python3
"""The server's CPU per agent-step under concurrent full-batch clients, against the core's.

For each --threads T and --n_landers L: starts `mll_server --threads=T` on loopback (with
--metrics_address), runs `mll_cli bench --clients=C --envs=E` against it (C concurrent clients,
each stepping E auto-resetting envs with random actions, so every call carries all E envs), and
reads the server's CPU over a steady-state window inside the run (the first and last second
left out: env creation, resets and teardown are not steps) from two sources that must agree:
its /metrics `process_cpu_seconds_total` and /proc/<pid>/stat. The agent-steps of the same
window come from /metrics `mll_agent_steps_total`. The floor is `mll_core_batch_timing` (the
core alone, C x E envs on T threads, no gRPC): its CPU per agent-step. The ratio of the two is
what the server adds per agent-step (gRPC, protobuf, the worker pool, the registry); with more
threads it must not grow.

The floor runs `--lockstep`: every env is stepped once before any is stepped again, as the
clients step them. Free-running (each thread steps its share over and over), a floor with more
threads than cores steps a thread's share several times within one time slice, from the core's
cache, which no client's envs get (each is stepped once per call); its figure is reported
beside ("free-running core").

`mll_cli bench` is the load generator, so an operator can take the same figure against a
deployment: scrape process_cpu_seconds_total and mll_agent_steps_total while it runs.

--clients_kind python: the load is C Python processes instead, each a
`multi_lunar_lander.vector_env(E, address=..., transport=--transport, n_landers=L)` stepping
random discrete actions with auto-reset (what a trainer runs). They are started, create and
reset their envs, and only then are all told to go at once, so the window sees C clients
stepping. The server's fixed CPU per call is reported beside: from the server's and the floor's
CPU per agent-step, (server - floor) x E x L, the CPU a call costs beyond its physics.

--transport_floor measures, in each round, what the transport alone costs the server per call at
the same rate: `mll_echo_load` (bench/service/echo_load.cc), a bare gRPC stream served with the
Session's reactor shape, carrying the bytes of a Session StepBatch of E envs x L landers (request by
batch handle and answer), its server spinning for the floor's CPU per call (the physics) before each
answer and its C clients (one connection each) spinning for the Python clients' CPU per call after
each. Its server's CPU per call beyond what its spins took is the transport floor per call,
reported beside the fixed cost.

--pin (for a host with more than T cores): the server and the floor on cores 0..T-1, the
clients on the others.

--rounds N measures each configuration N times, the server and its floor alternating (server,
floor, server, floor, ...), and reports the median ratio and fixed cost with the range: on a
shared machine the load moves between one run and the next by more than the server's own
per-call work, and a single server run against a single floor run, taken one after the other,
says little. --compare_server PATH measures a second server binary in every round too (the order
of the two swapping each round), so that before and after a change are compared under the same
load.

Loopback only; every run is bounded by --seconds. Prints a Markdown table and one JSON line.

    .venv/bin/python bench/service/bench_server_cpu.py --seconds 8
    .venv/bin/python bench/service/bench_server_cpu.py --clients_kind python --threads 2,8 --n_landers 1,3
    .venv/bin/python bench/service/bench_server_cpu.py --clients_kind python --threads 2,8 --n_landers 1 \
        --rounds 3 --compare_server /tmp/mll_server_before
    .venv/bin/python bench/service/bench_server_cpu.py --clients_kind python --threads 2,8 --n_landers 1 \
        --rounds 4 --transport_floor
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import re
import statistics
import subprocess
import sys
import tempfile
import time
import urllib.request

REPO = pathlib.Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "bench" / "python"))
from process_cpu import children_cpu_s, process_cpu_s, threads_cpu_delta_s, threads_cpu_ns  # noqa: E402


def _pin(pid: int, cores: list[int]) -> None:
    """Pins every thread of `pid` (threads started later inherit their creator's mask)."""
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            os.sched_setaffinity(int(tid), cores)
        except ProcessLookupError:  # The thread ended meanwhile.
            pass


def _taskset(cores: list[int] | None) -> list[str]:
    return ["taskset", "-c", ",".join(map(str, cores))] if cores else []


class Server:
    """mll_server --threads=T on a free loopback port with /metrics on another."""

    def __init__(self, binary: str, threads: int, cores: list[int] | None, startup_s: float = 30.0):
        self._dir = tempfile.TemporaryDirectory(prefix="mll_bench_cpu_")
        port_file = os.path.join(self._dir.name, "port")
        self._log = open(os.path.join(self._dir.name, "log"), "w+b")  # noqa: SIM115 - closed in close().
        self.process = subprocess.Popen(
            _taskset(cores) + [binary, "--address=127.0.0.1:0", f"--port_file={port_file}",
                               "--metrics_address=127.0.0.1:0", f"--threads={threads}", "--max_envs=100000"],
            stdout=self._log, stderr=subprocess.STDOUT,
        )
        deadline = time.monotonic() + startup_s
        self.metrics_url = None
        while time.monotonic() < deadline and self.process.poll() is None:
            self._log.seek(0)
            found = re.search(rb"metrics on (http://\S+/metrics)", self._log.read())
            if found and os.path.exists(port_file) and os.path.getsize(port_file) > 0:
                self.metrics_url = found.group(1).decode()
                self.address = f"127.0.0.1:{pathlib.Path(port_file).read_text().strip()}"
                return
            time.sleep(0.05)
        self.close()
        raise RuntimeError(f"mll_server did not start in {startup_s} s")

    @property
    def pid(self) -> int:
        return self.process.pid

    def scrape(self) -> dict:
        """process_cpu_seconds_total, the agent-steps of every method, the calls (Session requests
        included), the context switches, and
        /proc's CPU seconds read right after."""
        with urllib.request.urlopen(self.metrics_url, timeout=10) as response:
            text = response.read().decode()
        proc_cpu_s = process_cpu_s(self.pid)
        sample = {"cpu_s": 0.0, "agent_steps": 0, "calls": 0, "voluntary": 0, "involuntary": 0,
                  "proc_cpu_s": proc_cpu_s}
        for line in text.splitlines():
            if line.startswith("#"):
                continue
            series, _, value = line.rpartition(" ")
            if series == "process_cpu_seconds_total":
                sample["cpu_s"] = float(value)
            elif series.startswith("mll_agent_steps_total{"):
                sample["agent_steps"] += int(float(value))
            elif series.startswith("mll_rpc_duration_seconds_count{"):  # Session requests count one each.
                sample["calls"] += int(float(value))
            elif series.startswith("mll_process_context_switches_total{"):
                sample["voluntary" if '"voluntary"' in series else "involuntary"] = int(float(value))
        return sample

    def close(self) -> None:
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=15)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self._log.close()
        self._dir.cleanup()


def python_client(address: str, envs: int, n_landers: int, seconds: float, transport: str, seed: int,
                  copy: bool | None = None) -> int:
    """One Python load client (--python_client): creates and resets its vector env (copy=: the
    package's default unless given), prints "ready", waits for a line on stdin, steps random
    discrete actions for `seconds` (auto-reset), prints one JSON line and closes the env."""
    import multi_lunar_lander as mll
    import numpy as np

    options = {} if copy is None else {"copy": copy}
    env = mll.vector_env(envs, address=address, transport=transport, n_landers=n_landers, **options)
    try:
        env.reset(seed=seed)
        random = np.random.default_rng(seed)
        table = random.integers(0, 4, size=(64, envs, n_landers), dtype=np.int32)
        print(json.dumps({"ready": True, "transport": env.transport}), flush=True)
        sys.stdin.readline()
        calls = 0
        began = time.monotonic()
        while time.monotonic() - began < seconds:
            env.step(table[calls % len(table)])
            calls += 1
        elapsed = time.monotonic() - began
        print(json.dumps({"calls": calls, "agent_steps": calls * envs * n_landers, "seconds": elapsed}), flush=True)
    finally:
        env.close()
    return 0


class PythonClients:
    """`args.clients` Python load clients (python_client) against `address`, started together;
    `env` is their environment (default: this process's), e.g. a PYTHONPATH that picks another
    checkout's multi_lunar_lander."""

    def __init__(self, args, address: str, n_landers: int, cores: list[int] | None, env: dict | None = None):
        self.processes = []
        command = _taskset(cores) + [
            sys.executable, str(pathlib.Path(__file__).resolve()), "--python_client", address,
            f"--envs={args.envs}", f"--seconds={args.seconds}", f"--transport={args.transport}"]
        if getattr(args, "copy", None) is not None:
            command.append(f"--copy={str(args.copy).lower()}")
        try:
            for client in range(args.clients):
                self.processes.append(subprocess.Popen(
                    command + [f"--n_landers={n_landers}", f"--seed={1000 * client}"],
                    stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env))
            for process in self.processes:  # Bounded: each client's own start-up is bounded by gRPC's.
                line = process.stdout.readline()
                if not line or not json.loads(line).get("ready"):
                    raise RuntimeError(f"a Python client did not start: {process.stderr.read().strip()}")
                self.transport = json.loads(line)["transport"]
        except BaseException:
            self.kill()
            raise

    @property
    def pids(self) -> list[int]:
        return [process.pid for process in self.processes]

    def go(self) -> None:
        for process in self.processes:
            process.stdin.write("go\n")
            process.stdin.flush()

    def poll(self):
        codes = [process.poll() for process in self.processes]
        return None if None in codes else max(codes)

    def results(self, timeout: float) -> dict:
        outputs = []
        for process in self.processes:
            out, err = process.communicate(timeout=timeout)
            if process.returncode != 0:
                raise RuntimeError(f"a Python client failed ({process.returncode}): {err.strip()}")
            outputs.append(json.loads(out.strip().splitlines()[-1]))
        return {"agent_steps": sum(out["agent_steps"] for out in outputs),
                "calls": sum(out["calls"] for out in outputs), "transport": self.transport}

    def kill(self) -> None:
        for process in self.processes:
            if process.poll() is None:
                process.kill()
                process.wait()


class CliClients:
    """`mll_cli bench --clients=C`: C clients in one process."""

    def __init__(self, args, address: str, n_landers: int, cores: list[int] | None):
        self.process = subprocess.Popen(
            _taskset(cores) + [
                args.cli, "bench", f"--address={address}", f"--envs={args.envs}", f"--n_landers={n_landers}",
                f"--seconds={args.seconds}", f"--clients={args.clients}", f"--transport={args.transport}"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

    @property
    def pids(self) -> list[int]:
        return [self.process.pid]

    def go(self) -> None:
        pass

    def poll(self):
        return self.process.poll()

    def results(self, timeout: float) -> dict:
        out, err = self.process.communicate(timeout=timeout)
        if self.process.returncode != 0:
            raise RuntimeError(f"mll_cli bench failed ({self.process.returncode}): {err.strip()}")
        return json.loads(out.strip().splitlines()[-1])

    def kill(self) -> None:
        if self.process.poll() is None:
            self.process.kill()
            self.process.wait()


def measure_window(args, server: Server, n_landers: int, clients_factory) -> dict:
    """Starts clients_factory() (PythonClients or CliClients against `server`, each stepping
    args.envs envs x n_landers for args.seconds) and measures a steady-state window inside their
    run: the server's CPU (from /metrics and from /proc), its agent-steps and calls, and the
    clients' own CPU (each client process's threads, /proc/<pid>/task) over the same window."""
    client_before = children_cpu_s()
    run_before = process_cpu_s(server.pid)
    clients = clients_factory()
    try:
        clients.go()
        # The window opens once stepping has begun, plus a second; it closes a second before
        # the clients stop.
        opened = time.monotonic()
        deadline = opened + args.seconds + 60
        while server.scrape()["agent_steps"] == 0 and time.monotonic() < deadline and clients.poll() is None:
            time.sleep(0.05)
        stepping = time.monotonic()
        time.sleep(1.0)
        first, first_clients = server.scrape(), [threads_cpu_ns(pid) for pid in clients.pids]
        first_clients_ticks = sum(process_cpu_s(pid) for pid in clients.pids)
        window_start = time.monotonic()
        time.sleep(max(1.0, args.seconds - (window_start - stepping) - 1.0))
        last, last_clients = server.scrape(), [threads_cpu_ns(pid) for pid in clients.pids]
        last_clients_ticks = sum(process_cpu_s(pid) for pid in clients.pids)
        window_s = time.monotonic() - window_start
        result = clients.results(timeout=args.seconds * 3 + 120)
    finally:
        clients.kill()
    agent_steps = last["agent_steps"] - first["agent_steps"]
    cpu_s = last["cpu_s"] - first["cpu_s"]
    proc_cpu_s = last["proc_cpu_s"] - first["proc_cpu_s"]
    calls = last["calls"] - first["calls"]
    clients_cpu_s = sum(threads_cpu_delta_s(before, after) for before, after in zip(first_clients, last_clients))
    return {
        "agent_steps_per_s": agent_steps / window_s,
        "window_s": window_s,
        "window_agent_steps": agent_steps,
        "window_calls": calls,
        "server_cpu_s": cpu_s,
        "server_proc_cpu_s": proc_cpu_s,
        "server_cpu_us_per_agent_step": cpu_s / agent_steps * 1e6,
        "server_proc_cpu_us_per_agent_step": proc_cpu_s / agent_steps * 1e6,
        # The server's threads blocking (each a later wake-up) per 64-env call (--envs per call).
        "voluntary_switches_per_call": (last["voluntary"] - first["voluntary"])
        / max(1, agent_steps / (args.envs * n_landers)),
        "involuntary_switches_per_s": (last["involuntary"] - first["involuntary"]) / window_s,
        # The clients' processes over the window, per call the server answered in it.
        "client_window_cpu_s": clients_cpu_s,
        "client_cpu_us_per_call": clients_cpu_s / max(1, calls) * 1e6,
        # The same from /proc/<pid>/stat (10 ms steps; counts threads that ended in the window).
        "client_window_proc_cpu_s": last_clients_ticks - first_clients_ticks,
        # The whole run (warm-up, env creation, teardown included), from the clients' own count.
        "run_agent_steps": result["agent_steps"],
        "run_server_cpu_us_per_agent_step": (process_cpu_s(server.pid) - run_before)
        / max(1, result["agent_steps"]) * 1e6,
        "client_cpu_s": children_cpu_s() - client_before,
        "cli": result,
    }


def measure_server(args, binary: str, threads: int, n_landers: int, server_cores, client_cores) -> dict:
    server = Server(binary, threads, server_cores)
    try:
        if server_cores:
            _pin(server.pid, server_cores)
        clients_type = PythonClients if args.clients_kind == "python" else CliClients
        return measure_window(args, server, n_landers, lambda: clients_type(args, server.address, n_landers, client_cores))
    finally:
        server.close()


def measure_core(args, threads: int, n_landers: int, cores, lockstep: bool) -> dict:
    envs = args.clients * args.envs
    cpu_before = children_cpu_s()
    output = subprocess.run(
        _taskset(cores) + [args.core_timing, f"--envs={envs}", f"--n_landers={n_landers}", f"--threads={threads}",
                           "--steps=1000000", f"--seconds={args.seconds}", f"--lockstep={str(lockstep).lower()}"],
        check=True, capture_output=True, text=True, timeout=args.seconds + 120,
    ).stdout
    result = json.loads(output.strip().splitlines()[-1])
    result["cpu_s"] = children_cpu_s() - cpu_before
    result["cpu_us_per_agent_step"] = result["cpu_s"] / result["agent_steps"] * 1e6
    return result


def session_message_bytes(envs: int, n_landers: int) -> tuple[int, int]:
    """Bytes of a packed Session StepBatch of `envs` envs x `n_landers` discrete landers: the
    request by batch handle (actions only) and its answer, built with the package's generated
    classes (the arrays zero-filled: their size does not depend on their values)."""
    from multi_lunar_lander._proto import multi_lunar_lander_pb2 as pb

    def array(dtype, shape, item_bytes):
        size = item_bytes
        for dimension in shape:
            size *= dimension
        return pb.Array(dtype=dtype, shape=shape, data=bytes(size))

    f32, u8, i32 = pb.DTYPE_FLOAT32, pb.DTYPE_UINT8, pb.DTYPE_INT32
    per_agent, per_env = [envs, n_landers], [envs]
    sequence = 1 << 20  # A sequence number of a long run.
    request = pb.SessionRequest(sequence=sequence, step_batch=pb.StepBatchRequest(
        packed=pb.PackedSteps(handle=1, actions=array(i32, per_agent, 4))))
    answer = pb.SessionResponse(sequence=sequence, step_batch=pb.StepBatchResponse(packed=pb.PackedStepData(
        observations=array(f32, per_agent + [12], 4), rewards=array(f32, per_agent, 4),
        terminations=array(u8, per_agent, 1), truncations=array(u8, per_agent, 1),
        stepped=array(u8, per_agent, 1), outcomes=array(u8, per_agent, 1),
        episode_returns=array(f32, per_agent, 4), episode_lengths=array(i32, per_agent, 4),
        episode_over=array(u8, per_env, 1), auto_reset=array(u8, per_env, 1), cycles=array(i32, per_env, 4))))
    return request.ByteSize(), answer.ByteSize()


def measure_transport(args, n_landers: int, work_us: float, client_cpu_us: float, server_cores,
                      client_cores) -> dict:
    """The transport floor (--transport_floor): `mll_echo_load --serve` spinning for `work_us`
    before each answer, loaded by args.clients C streams of the Session's bytes spinning for
    `client_cpu_us` after each; its CPU, its spins' CPU and its answers over a window a second
    inside either end of the run."""
    request_bytes, answer_bytes = session_message_bytes(args.envs, n_landers)
    with tempfile.TemporaryDirectory(prefix="mll_bench_echo_") as directory:
        port_file = os.path.join(directory, "port")
        server = subprocess.Popen(
            _taskset(server_cores) + [args.echo, "--serve", f"--port_file={port_file}", f"--work_us={round(work_us)}"],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        load = None
        try:
            deadline = time.monotonic() + 30
            while not (os.path.exists(port_file) and os.path.getsize(port_file) > 0):
                if time.monotonic() > deadline or server.poll() is not None:
                    raise RuntimeError("mll_echo_load --serve did not start in 30 s")
                time.sleep(0.05)
            address = f"127.0.0.1:{pathlib.Path(port_file).read_text().strip()}"
            load = subprocess.Popen(
                _taskset(client_cores) + [
                    args.echo, f"--load={address}", f"--clients={args.clients}", f"--seconds={args.seconds}",
                    f"--request_bytes={request_bytes}", f"--response_bytes={answer_bytes}",
                    f"--client_work_us={round(client_cpu_us)}"],
                stdout=subprocess.PIPE, text=True)

            def answered() -> tuple[int, float]:
                server.stdin.write("\n")
                server.stdin.flush()
                answers, work_cpu_s = server.stdout.readline().split()
                return int(answers), float(work_cpu_s)

            time.sleep(1.0)
            (first_answers, first_work_s), first_cpu = answered(), process_cpu_s(server.pid)
            window_start = time.monotonic()
            time.sleep(args.seconds - 2.0)
            (last_answers, last_work_s), last_cpu = answered(), process_cpu_s(server.pid)
            window_s = time.monotonic() - window_start
            load.communicate(timeout=args.seconds + 60)
            if load.returncode != 0:
                raise RuntimeError(f"mll_echo_load --load failed ({load.returncode})")
        finally:
            for process in (load, server):
                if process is not None and process.poll() is None:
                    process.kill()
                    process.wait()
    calls = max(1, last_answers - first_answers)
    cpu_us_per_call = (last_cpu - first_cpu) / calls * 1e6
    work_cpu_us_per_call = (last_work_s - first_work_s) / calls * 1e6
    return {"request_bytes": request_bytes, "answer_bytes": answer_bytes, "work_us": work_us,
            "work_cpu_us_per_call": work_cpu_us_per_call, "client_work_us": client_cpu_us,
            "calls_per_s": calls / window_s, "server_cpu_us_per_call": cpu_us_per_call,
            "transport_us_per_call": cpu_us_per_call - work_cpu_us_per_call}


def _label(binary: str, servers: list[str]) -> str:
    """"server" alone; with --compare_server, "server" and "compared"."""
    return "server" if binary == servers[0] else "compared"


def _or_blank(value: float | None, form: str, unit: str = "") -> str:
    """`value` in `form` with `unit`, or "" for none (a round without --transport_floor)."""
    return "" if value is None else f"{value:{form}}{unit}"


def _transport_ratio(transport: dict | None, core: dict, agent_steps_per_call: int) -> float | None:
    """The ratio to the lockstep floor of a server whose only cost beside the physics were the
    transport floor: 1 + transport per call / the floor's CPU for one call's agent-steps."""
    if transport is None:
        return None
    return 1.0 + transport["transport_us_per_call"] / (core["cpu_us_per_agent_step"] * agent_steps_per_call)


def _median_range(values: list[float], form: str, unit: str = "", separator: str = " to ") -> str:
    """"median<unit> (min<separator>max)" of `values` in `form`, or "" when there are none."""
    if not values:
        return ""
    return (f"{statistics.median(values):{form}}{unit} ({min(values):{form}}{separator}"
            f"{max(values):{form}})")


def _ints(text: str) -> list[int]:
    return [int(item) for item in text.split(",") if item]


def python_client_main() -> int:
    parser = argparse.ArgumentParser(description="one Python load client of bench_server_cpu.py")
    parser.add_argument("--python_client", required=True, metavar="ADDRESS")
    parser.add_argument("--envs", type=int, required=True)
    parser.add_argument("--n_landers", type=int, required=True)
    parser.add_argument("--seconds", type=float, required=True)
    parser.add_argument("--transport", required=True)
    parser.add_argument("--seed", type=int, required=True)
    parser.add_argument("--copy", choices=["true", "false"], help="vector_env copy= (default: the package's)")
    args = parser.parse_args()
    return python_client(args.python_client, args.envs, args.n_landers, args.seconds, args.transport, args.seed,
                         None if args.copy is None else args.copy == "true")


def main() -> int:
    if "--python_client" in sys.argv:
        return python_client_main()
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--server", default=os.environ.get("MLL_SERVER_BIN", str(REPO / "build/server/service/mll_server")))
    parser.add_argument("--cli", default=str(REPO / "build/client_cpp/mll_cli"))
    parser.add_argument("--core_timing", default=str(REPO / "build/bench/python/mll_core_batch_timing"))
    parser.add_argument("--echo", default=str(REPO / "build/bench/service/mll_echo_load"))
    parser.add_argument("--transport_floor", action="store_true",
                        help="measure the transport floor per call in each round (see above; sizes its "
                             "messages with the multi_lunar_lander package)")
    parser.add_argument("--threads", type=_ints, default=[1, 2, 4, 8], help="server threads, comma-separated")
    parser.add_argument("--n_landers", type=_ints, default=[1, 3], help="landers per env, comma-separated")
    parser.add_argument("--clients", type=int, default=8, help="concurrent clients (mll_cli bench --clients)")
    parser.add_argument("--clients_kind", default="cli", choices=["cli", "python"],
                        help="the load: mll_cli bench, or Python vector_env processes")
    parser.add_argument("--envs", type=int, default=64, help="envs per client")
    parser.add_argument("--seconds", type=float, default=8.0, help="each run's length (server and floor), >= 4")
    parser.add_argument("--transport", default="native", choices=["native", "shared_memory"])
    parser.add_argument("--pin", action="store_true",
                        help="server and floor on cores 0..T-1, clients on the other cores")
    parser.add_argument("--rounds", type=int, default=1,
                        help="measurements of each configuration, server and floor alternating; medians reported")
    parser.add_argument("--compare_server", default="",
                        help="a second mll_server binary measured in every round too (e.g. before a change)")
    parser.add_argument("--max_ratio", type=float, default=0.0,
                        help="exit 1 if a ratio exceeds this (0: report only)")
    args = parser.parse_args()
    if args.seconds < 4:
        parser.error("--seconds: at least 4 (a second either side of the window is left out)")
    if args.rounds < 1:
        parser.error("--rounds: at least 1")
    cores = sorted(os.sched_getaffinity(0))

    servers = [args.server] + ([args.compare_server] if args.compare_server else [])
    rows = []
    load_before = os.getloadavg()
    for threads in args.threads:
        server_cores = client_cores = None
        if args.pin:
            if len(cores) <= threads:
                print(f"--pin: T={threads} leaves no core for the clients of {len(cores)}; skipped", file=sys.stderr)
                continue
            server_cores, client_cores = cores[:threads], cores[threads:]
        for n_landers in args.n_landers:
            for round_index in range(args.rounds):
                # The binaries take turns going first.
                order = servers if round_index % 2 == 0 else servers[::-1]
                measured = {binary: measure_server(args, binary, threads, n_landers, server_cores, client_cores)
                            for binary in order}
                core = measure_core(args, threads, n_landers, server_cores, lockstep=True)
                transport = None
                if args.transport_floor:
                    client_cpu_us = statistics.mean(
                        measured[binary]["client_cpu_us_per_call"] for binary in servers)
                    transport = measure_transport(
                        args, n_landers, core["cpu_us_per_agent_step"] * args.envs * n_landers,
                        client_cpu_us, server_cores, client_cores)
                for binary in servers:
                    server = measured[binary]
                    # What a call costs the server beyond its physics: its CPU over the window less
                    # the floor's CPU for the same agent-steps, per call.
                    fixed_us = (server["server_cpu_s"] * 1e6
                                - core["cpu_us_per_agent_step"] * server["window_agent_steps"]) / max(
                        1, server["window_calls"])
                    rows.append({"threads": threads, "n_landers": n_landers, "round": round_index,
                                 "binary": binary, "server": server, "core": core, "transport": transport,
                                 "fixed_us_per_call": fixed_us,
                                 "transport_ratio": _transport_ratio(transport, core, args.envs * n_landers),
                                 "ratio": server["server_cpu_us_per_agent_step"] / core["cpu_us_per_agent_step"],
                                 "throughput_vs_core": server["agent_steps_per_s"] / core["agent_steps_per_s"],
                                 "load": os.getloadavg()[0]})
                    disagreement = abs(server["server_cpu_s"] - server["server_proc_cpu_s"])
                    if disagreement > max(0.05, 0.03 * server["server_proc_cpu_s"]):
                        print(f"warning: /metrics CPU {server['server_cpu_s']:.3f} s vs /proc "
                              f"{server['server_proc_cpu_s']:.3f} s", file=sys.stderr)
            free_running = measure_core(args, threads, n_landers, server_cores, lockstep=False)
            for row in rows:
                if row["threads"] == threads and row["n_landers"] == n_landers:
                    row["free_running_core"] = free_running
                    row["ratio_free_running"] = (row["server"]["server_cpu_us_per_agent_step"]
                                                 / free_running["cpu_us_per_agent_step"])
    load_after = os.getloadavg()

    load = "mll_cli bench" if args.clients_kind == "cli" else "Python vector_env"
    print(f"{args.clients} clients x {args.envs} envs ({load}, {args.transport}), {args.seconds:g} s runs, "
          f"{len(cores)} cores{' pinned' if args.pin else ''}; load average {load_before[0]:.2f} before, "
          f"{load_after[0]:.2f} after\n")
    print("| T | landers | server | round | load | agent-steps/s | vs core | server CPU us/agent-step "
          "| core CPU us/agent-step | ratio | free-running core us/agent-step | ratio to it "
          "| server CPU per call beyond the floor, us | transport floor per call, us | the bare stream's ratio "
          "| context switches/call |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for row in rows:
        server, core = row["server"], row["core"]
        print(f"| {row['threads']} | {row['n_landers']} | {_label(row['binary'], servers)} | {row['round'] + 1} "
              f"| {row['load']:.1f} | {server['agent_steps_per_s']:,.0f} "
              f"| {row['throughput_vs_core']:.2f} | {server['server_cpu_us_per_agent_step']:.2f} "
              f"| {core['cpu_us_per_agent_step']:.2f} | {row['ratio']:.2f}x "
              f"| {row['free_running_core']['cpu_us_per_agent_step']:.2f} | {row['ratio_free_running']:.2f}x "
              f"| {row['fixed_us_per_call']:.0f} "
              f"| {_or_blank(row['transport'] and row['transport']['transport_us_per_call'], '.0f')} "
              f"| {_or_blank(row['transport_ratio'], '.2f', 'x')} "
              f"| {server['voluntary_switches_per_call']:.1f} |")
    if args.rounds > 1:
        print("\nMedians over the rounds (range in brackets):\n")
        print("| T | landers | server | ratio to the lockstep floor | server CPU per call beyond the floor, us "
              "| transport floor per call, us | the bare stream's ratio | beyond the transport floor, us "
              "| context switches/call |")
        print("|---|---|---|---|---|---|---|---|---|")
        for threads in args.threads:
            for n_landers in args.n_landers:
                for binary in servers:
                    group = [row for row in rows if (row["threads"], row["n_landers"], row["binary"])
                             == (threads, n_landers, binary)]
                    if not group:
                        continue
                    ratios = [row["ratio"] for row in group]
                    fixed = [row["fixed_us_per_call"] for row in group]
                    switches = [row["server"]["voluntary_switches_per_call"] for row in group]
                    with_transport = [row for row in group if row["transport"]]
                    transports = [row["transport"]["transport_us_per_call"] for row in with_transport]
                    transport_ratios = [row["transport_ratio"] for row in with_transport]
                    # The server's per-call CPU beyond the bare stream's of the same round.
                    beyond = [row["fixed_us_per_call"] - row["transport"]["transport_us_per_call"]
                              for row in with_transport]
                    print(f"| {threads} | {n_landers} | {_label(binary, servers)} "
                          f"| {_median_range(ratios, '.2f', 'x', '-')} "
                          f"| {_median_range(fixed, '.0f')} | {_median_range(transports, '.0f')} "
                          f"| {_median_range(transport_ratios, '.2f', 'x', '-')} "
                          f"| {_median_range(beyond, '.0f')} | {statistics.median(switches):.2f} |")
    print(json.dumps({"benchmark": "server_cpu", "clients": args.clients, "clients_kind": args.clients_kind,
                      "envs": args.envs,
                      "transport": args.transport, "seconds": args.seconds, "pin": args.pin, "cores": len(cores),
                      "rounds": args.rounds, "servers": servers,
                      "load_before": load_before, "load_after": load_after, "rows": rows}))
    if args.max_ratio:
        # Each configuration's median over its rounds, of the server under test.
        for threads in args.threads:
            for n_landers in args.n_landers:
                ratios = [row["ratio"] for row in rows if (row["threads"], row["n_landers"], row["binary"])
                          == (threads, n_landers, servers[0])]
                if ratios and statistics.median(ratios) > args.max_ratio:
                    return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
