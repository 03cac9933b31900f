#!/usr/bin/env python3
"""Throughput across a slow link: our vector envs through delay_proxy at several round-trip times.

For each RTT in --rtts_ms (default 0, 0.5, 2 and 10 ms) a delay_proxy (bench/latency/delay_proxy.cc,
one-way delay RTT/2; RTT 0 still goes through the proxy) stands between the client and one
`mll_server --threads=--threads` on loopback, and each configuration steps random discrete actions
with auto-reset, one lander per env, over the native gRPC stream (`transport="native"`: shared
memory would bypass the link):

  sync        vector_env(--envs).step: every env each call, one round trip per call.
  halves      two vector_env(--envs / 2) stepped alternately with step_async/step_wait: each call
              sends one half's actions and waits for the other half's results (the pattern of
              bench/python/bench_client.py's Halves, before the async API).
  async NxK   vector_env(N, batch_size=K) through EnvPool's async API: async_reset, then recv() K
              envs' results and send() their actions for info["env_id"]; N - K envs stay in flight
              while the client handles K. --async lists the N x K configurations (default 256x64,
              and 1024x128 for 10 ms: N envs in flight sustain at most N / RTT env-steps/s).
  cpp         mll_cli bench --envs=--envs --transport=native (the C++ VectorEnv, synchronous),
              and `--batch_size=K` for each async configuration once mll_cli bench has that flag.
  envpool     EnvPool 1.2.5's async API in this process (--envs envs, batch_size 64, --threads
              threads; no link at all), for reference, at RTT 0 only.

The proxies run under SCHED_FIFO (delay_proxy --realtime) unless --no-proxy_realtime: on a machine
whose cores the server and client keep busy, a proxy that waits for a CPU would add to the delay.

With --direct every configuration is also measured straight to the server's address (column
"direct (no proxy)"): what a client on the server's host gets over TCP, with no proxy's CPU or
hand-off in the way.

Each measurement: a fresh env (created through the link), a warm-up of --warmup calls, then up to
--steps calls or --seconds, whichever ends first; env-steps = calls x envs per call. --rounds rounds,
each running every configuration at every RTT in turn (one proxy per RTT for the whole run);
figures are medians over rounds, and the ratio to RTT 0 is the median of each round's ratio to the
same configuration's RTT-0 figure, measured seconds before. CPU is this
process (or mll_cli) plus the server, per env-step; the proxy's own CPU is reported apart.
Loopback only. Prints a Markdown table and a JSON line.

    .venv/bin/pip install -r bench/python/requirements.txt   # EnvPool, for its row
    .venv/bin/python bench/latency/bench_latency.py
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import resource
import signal
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

REPO = pathlib.Path(__file__).resolve().parents[2]
TRANSPORT = "native"


def process_cpu_s(pid: int) -> float:
    """user + system CPU seconds of a process so far (/proc/<pid>/stat)."""
    fields = pathlib.Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def cpu_pressure() -> str:
    """The share of time some runnable task waited for a CPU over the last 10 s and 60 s
    (/proc/pressure/cpu; a better sign of a busy machine than the load average)."""
    try:
        fields = dict(item.split("=") for item in pathlib.Path("/proc/pressure/cpu").read_text().split()[1:3])
        return f"{fields['avg10']}% / {fields['avg60']}%"
    except (OSError, KeyError, ValueError):
        return "unknown"


def cpu_ticks() -> list[int]:
    """The machine's CPU time by state (/proc/stat: user nice system idle iowait irq softirq steal)."""
    return [int(value) for value in pathlib.Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:9]]


def steal_share(before: list[int], after: list[int]) -> float:
    """The share of CPU time the hypervisor took from this VM between two cpu_ticks()."""
    delta = [b - a for a, b in zip(before, after)]
    return delta[7] / max(sum(delta), 1)


def children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


class DelayProxy:
    """A delay_proxy child in front of `target` ("127.0.0.1:PORT") with a one-way delay."""

    def __init__(self, binary: str, target: str, delay_us: int, realtime: bool = False):
        self._workdir = tempfile.mkdtemp(prefix="delay_proxy_")
        port_file = os.path.join(self._workdir, "port")
        self._out = open(os.path.join(self._workdir, "out"), "w+")
        self.process = subprocess.Popen(
            [binary, "--listen=127.0.0.1:0", f"--target={target}", f"--delay_us={delay_us}",
             f"--port_file={port_file}", f"--parent_pid={os.getpid()}", f"--realtime={str(realtime).lower()}"],
            stdin=subprocess.DEVNULL, stdout=self._out, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 10
        while not os.path.exists(port_file):
            if self.process.poll() is not None or time.monotonic() > deadline:
                self._out.seek(0)
                raise RuntimeError(f"delay_proxy did not start: {self._out.read().strip()}")
            time.sleep(0.005)
        self.address = f"127.0.0.1:{int(pathlib.Path(port_file).read_text())}"
        self.stats: dict = {}

    def close(self) -> None:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self._out.seek(0)
        lines = [line for line in self._out.read().splitlines() if line.startswith("{")]
        self.stats = json.loads(lines[-1]) if lines else {}
        self._out.close()
        for name in os.listdir(self._workdir):
            os.remove(os.path.join(self._workdir, name))
        os.rmdir(self._workdir)


class Sync:
    """vector_env(envs).step: all envs per call."""

    def __init__(self, mll, address: str, envs: int, table: np.ndarray):
        self.env = mll.vector_env(envs, address=address, n_landers=1, transport=TRANSPORT)
        assert self.env.transport == TRANSPORT, self.env.transport
        self.env.reset(seed=0)
        self.table, self.per_call, self.calls = table[:, :envs, None], envs, 0

    def step(self) -> None:
        self.env.step(self.table[self.calls % len(self.table)])
        self.calls += 1

    def close(self) -> None:
        self.env.close()


class Halves:
    """Two vector envs of half the size, alternating step_async/step_wait; a call sends one half's
    actions and returns the other's results (the other half starts in flight)."""

    def __init__(self, mll, address: str, envs: int, table: np.ndarray):
        half = envs // 2
        self.halves = [mll.vector_env(half, address=address, n_landers=1, transport=TRANSPORT) for _ in range(2)]
        for env in self.halves:
            env.reset(seed=0)
        self.table, self.per_call, self.calls, self.sending = table[:, :half, None], half, 0, 0
        self.halves[1].step_async(self.table[0])

    def step(self) -> None:
        self.halves[self.sending].step_async(self.table[self.calls % len(self.table)])
        self.sending = 1 - self.sending
        self.halves[self.sending].step_wait()
        self.calls += 1

    def close(self) -> None:
        self.halves[1 - self.sending].step_wait()
        for env in self.halves:
            env.close()


class Async:
    """vector_env(envs, batch_size=batch) through EnvPool's async API: recv, then send actions for
    info["env_id"]."""

    def __init__(self, mll, address: str, envs: int, batch: int, table: np.ndarray):
        self.env = mll.vector_env(envs, address=address, n_landers=1, transport=TRANSPORT, batch_size=batch)
        assert self.env.transport == TRANSPORT, self.env.transport
        self.env.async_reset(seed=0)
        self.table, self.per_call, self.calls = table[:, :batch, None], batch, 0

    def step(self) -> None:
        info = self.env.recv()[-1]
        self.env.send(self.table[self.calls % len(self.table)], info["env_id"])
        self.calls += 1

    def close(self) -> None:
        for _ in range(self.env.num_envs // self.env.batch_size):  # Drain what is in flight.
            self.env.recv()
        self.env.close()


class EnvPoolAsync:
    """EnvPool's in-process LunarLander-v3 through its async API (no link)."""

    def __init__(self, envpool, envs: int, batch: int, threads: int, table: np.ndarray):
        self.env = envpool.make("LunarLander-v3", env_type="gymnasium", num_envs=envs, batch_size=batch,
                                num_threads=threads, seed=0)
        self.env.async_reset()
        self.table, self.per_call, self.calls = table[:, :batch], batch, 0

    def step(self) -> None:
        info = self.env.recv()[-1]
        self.env.send(self.table[self.calls % len(self.table)], info["env_id"])
        self.calls += 1

    def close(self) -> None:
        self.env.close()


def has_async_api(mll) -> bool:
    return all(hasattr(mll.VectorEnv, name) for name in ("async_reset", "send", "recv"))


def measure(side, server_pid: int | None, warmup: int, steps: int, seconds: float) -> dict:
    """Up to `steps` calls of side.step() or `seconds`, after `warmup` calls."""
    for _ in range(warmup):
        side.step()
    server_before = process_cpu_s(server_pid) if server_pid else 0.0
    client_before = time.process_time()
    start = time.perf_counter()
    deadline = start + seconds
    calls = 0
    while calls < steps and time.perf_counter() < deadline:
        side.step()
        calls += 1
    wall = time.perf_counter() - start
    cpu = time.process_time() - client_before + ((process_cpu_s(server_pid) if server_pid else 0.0) - server_before)
    env_steps = calls * side.per_call
    return {"env_steps_per_s": env_steps / wall, "cpu_us_per_env_step": cpu * 1e6 / env_steps}


def cli_supports_batch_size(cli: str) -> bool:
    try:
        help_text = subprocess.run([cli, "bench", "--help"], capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return "--batch_size" in help_text.stdout + help_text.stderr


def measure_cli(cli: str, address: str, server_pid: int, envs: int, seconds: float, batch: int | None) -> dict:
    """mll_cli bench (the C++ VectorEnv) against `address`: its throughput; CPU of mll_cli and the
    server over the whole run (warm-up included) per env-step of the measured part. A run that
    stepped nothing (its warm-up took all its time: a stalled machine) runs once more."""
    command = [cli, "bench", f"--address={address}", f"--envs={envs}", "--n_landers=1", f"--seconds={seconds}",
               f"--transport={TRANSPORT}"]
    if batch is not None:
        command.append(f"--batch_size={batch}")
    for _ in range(2):
        client_before, server_before = children_cpu_s(), process_cpu_s(server_pid)
        output = subprocess.run(command, check=True, capture_output=True, text=True, timeout=seconds * 3 + 120).stdout
        result = json.loads(output.strip().splitlines()[-1])
        cpu = children_cpu_s() - client_before + process_cpu_s(server_pid) - server_before
        if result["env_steps"]:
            return {"env_steps_per_s": result["env_steps_per_second"], "cpu_us_per_env_step": cpu * 1e6 / result["env_steps"]}
        print(f"mll_cli bench stepped nothing in {seconds} s ({output.strip()}); once more", file=sys.stderr)
    raise RuntimeError(f"mll_cli bench stepped nothing twice: {' '.join(command)}")


def parse_async(text: str) -> list[tuple[int, int]]:
    configs = []
    for item in filter(None, text.split(",")):
        envs, batch = (int(part) for part in item.lower().split("x"))
        if not 1 <= batch <= envs or envs % batch:
            raise argparse.ArgumentTypeError(f"--async {item}: batch must divide envs")
        configs.append((envs, batch))
    return configs


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    build = REPO / "build"
    parser.add_argument("--server", default=os.environ.get("MLL_SERVER_BIN", str(build / "server/service/mll_server")))
    parser.add_argument("--proxy", default=str(build / "bench/latency/delay_proxy"))
    parser.add_argument("--cli", default=str(build / "client_cpp/mll_cli"), help="mll_cli ('' skips the C++ rows)")
    parser.add_argument("--rtts_ms", default="0,0.5,2,10", help="round-trip times added by the proxy, ms")
    parser.add_argument("--envs", type=int, default=256, help="envs of the sync, halves, cpp and envpool rows")
    parser.add_argument("--async", dest="async_configs", type=parse_async, default=parse_async("256x64,1024x128"),
                        help="async API configurations, NxK (num_envs x batch_size), comma-separated")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--steps", type=int, default=2000, help="calls per measurement, at most")
    parser.add_argument("--seconds", type=float, default=3.0, help="time per measurement, at most")
    parser.add_argument("--warmup", type=int, default=20, help="calls before each measurement")
    parser.add_argument("--no_envpool", action="store_true", help="skip EnvPool's row")
    parser.add_argument("--direct", action="store_true",
                        help="also measure every configuration straight to the server, no proxy (column 'direct')")
    parser.add_argument("--proxy_realtime", action=argparse.BooleanOptionalAction, default=True,
                        help="run the proxies under SCHED_FIFO (delay_proxy --realtime; without CAP_SYS_NICE they "
                        "warn and run normally): a link's delay should not grow with the endpoints' CPU load")
    args = parser.parse_args()
    rtts = [float(value) for value in args.rtts_ms.split(",")]
    if not rtts or rtts[0] != 0:
        parser.error("--rtts_ms must start with 0 (the figures are ratios to it)")
    if args.envs % 2:
        parser.error("--envs must be even (the halves row)")
    for binary in (args.server, args.proxy):
        if not os.access(binary, os.X_OK):
            parser.error(f"{binary} is not built (scripts/build.sh builds it)")
    import multi_lunar_lander as mll

    async_api = has_async_api(mll)
    if not async_api:
        print("vector_env has no async API (async_reset/send/recv) in this checkout: the async rows are skipped",
              file=sys.stderr)
    cli_async = bool(args.cli) and cli_supports_batch_size(args.cli)
    envpool = None
    if not args.no_envpool:
        try:
            import envpool
        except ImportError:
            print("envpool is not installed (pip install -r bench/python/requirements.txt): its row is skipped",
                  file=sys.stderr)

    table = np.random.default_rng(0).integers(0, 4, size=(256, max([args.envs, *(n for n, _ in args.async_configs)])),
                                              dtype=np.int32)
    sides: dict[str, object] = {
        f"sync {args.envs}": lambda address: Sync(mll, address, args.envs, table),
        f"halves 2x{args.envs // 2}": lambda address: Halves(mll, address, args.envs, table),
    }
    if async_api:
        for envs, batch in args.async_configs:
            sides[f"async {envs}x{batch}"] = (lambda e, b: lambda address: Async(mll, address, e, b, table))(envs, batch)
    cli_sides: dict[str, tuple[int, int | None]] = {}  # name -> (envs, batch_size or None: sync)
    if args.cli:
        cli_sides[f"cpp sync {args.envs}"] = (args.envs, None)
        if cli_async:
            for envs, batch in args.async_configs:
                cli_sides[f"cpp async {envs}x{batch}"] = (envs, batch)
    names = [*sides, *cli_sides]
    # The columns: "direct" (no proxy) with --direct, then each RTT through its proxy.
    columns: list[float | str] = (["direct"] if args.direct else []) + rtts
    results: dict[str, dict[float | str, list[dict]]] = {name: {column: [] for column in columns} for name in names}
    envpool_results: list[dict] = []
    load_before, pressure_before, ticks_before = os.getloadavg(), cpu_pressure(), cpu_ticks()
    proxies: dict[float, DelayProxy] = {}
    with mll.ServerProcess(args.server, threads=args.threads) as server:
        try:
            for rtt in rtts:
                proxies[rtt] = DelayProxy(args.proxy, server.address, round(rtt * 500), args.proxy_realtime)

            def link(column) -> str:
                return server.address if column == "direct" else proxies[column].address

            for _ in range(args.rounds):
                # Each configuration at every RTT in turn: its ratios compare runs seconds apart.
                for name, make in sides.items():
                    for column in columns:
                        side = make(link(column))
                        try:
                            results[name][column].append(measure(side, server.pid, args.warmup, args.steps,
                                                                 args.seconds))
                        finally:
                            side.close()
                for name, (envs, batch) in cli_sides.items():
                    for column in columns:
                        results[name][column].append(measure_cli(args.cli, link(column), server.pid, envs,
                                                                 args.seconds, batch))
                if envpool is not None:
                    side = EnvPoolAsync(envpool, args.envs, 64, args.threads, table)
                    try:
                        envpool_results.append(measure(side, None, args.warmup, args.steps, args.seconds))
                    finally:
                        side.close()
            proxy_cpu = {rtt: process_cpu_s(proxy.process.pid) for rtt, proxy in proxies.items()}
        finally:
            for proxy in proxies.values():
                proxy.close()
    load_after, pressure_after, steal = os.getloadavg(), cpu_pressure(), steal_share(ticks_before, cpu_ticks())

    def median(values):
        return statistics.median(values) if values else float("nan")

    print(f"load average {load_before[0]:.1f} at start, {load_after[0]:.1f} at the end (1-minute); CPU pressure "
          f"(10 s / 60 s) {pressure_before} at start, {pressure_after} at the end; CPU time stolen by the "
          f"hypervisor {steal:.1%}; "
          f"mll_server --threads={args.threads}, {args.rounds} rounds, transport={TRANSPORT}, 1 lander per env")
    header = " | ".join(["direct (no proxy)"] * args.direct + [f"RTT {rtt:g} ms" + (" (proxy)" if rtt == 0 else "")
                                                                 for rtt in rtts])
    print(f"| configuration | {header} | CPU us per env-step, RTT 0 |")
    print("|---" * (len(columns) + 2) + "|")
    summary: dict[str, dict] = {}
    for name in names:
        cells = []
        summary[name] = {}
        if args.direct:
            rate = median([run["env_steps_per_s"] for run in results[name]["direct"]])
            summary[name]["direct"] = {"env_steps_per_s": rate}
            cells.append(f"{rate:,.0f}")
        for rtt in rtts:
            rates = [run["env_steps_per_s"] for run in results[name][rtt]]
            ratios = [run["env_steps_per_s"] / base["env_steps_per_s"]
                      for run, base in zip(results[name][rtt], results[name][rtts[0]]) if base["env_steps_per_s"]]
            summary[name][rtt] = {"env_steps_per_s": median(rates), "ratio_to_rtt0": median(ratios)}
            cells.append(f"{median(rates):,.0f}" + ("" if rtt == rtts[0] else f" ({median(ratios):.2f})"))
        cpu = median([run["cpu_us_per_env_step"] for run in results[name][rtts[0]]])
        print(f"| {name} | {' | '.join(cells)} | {cpu:.1f} |")
    if envpool_results:
        rate = median([run["env_steps_per_s"] for run in envpool_results])
        cpu = median([run["cpu_us_per_env_step"] for run in envpool_results])
        summary["envpool async (in-process)"] = {0.0: {"env_steps_per_s": rate}}
        print(f"| EnvPool {envpool.__version__} async {args.envs}x64, in-process, {args.threads} threads | "
              f"{'|' * args.direct} {rate:,.0f} |{' |' * (len(rtts) - 1)} {cpu:.1f} |")
    print()
    for rtt in rtts:
        stats = proxies[rtt].stats
        print(f"proxy at RTT {rtt:g} ms: {stats.get('chunks', 0):,} chunks written late by p50 "
              f"{stats.get('late_us_p50')} us, p99 {stats.get('late_us_p99')} us, max {stats.get('late_us_max')} us; "
              f"its CPU {proxy_cpu[rtt]:.1f} s in all")
    sync_name = f"sync {args.envs}"
    for envs, batch in args.async_configs if async_api else ():
        name = f"async {envs}x{batch}"
        if 2.0 in rtts:
            print(f"{name}: at RTT 2 ms, {summary[name][2.0]['ratio_to_rtt0']:.2f} of its RTT-0 throughput "
                  "(target >= 0.8)")
        for column in columns[: 1 + args.direct]:  # Direct (with --direct), then RTT 0.
            ratio = median([run["env_steps_per_s"] / sync["env_steps_per_s"]
                            for run, sync in zip(results[name][column], results[sync_name][column])])
            summary[name][f"ratio_to_sync_{'direct' if column == 'direct' else 'at_rtt0'}"] = ratio
            where = "directly (no proxy)" if column == "direct" else "at RTT 0"
            print(f"{name}: {where}, {ratio:.2f} x sync {args.envs} (median of the rounds' ratios; target >= 1 at RTT 0)")
    print(json.dumps({"args": {**vars(args), "async_configs": [f"{n}x{k}" for n, k in args.async_configs]},
                      "load_average": [load_before, load_after],
                      "cpu_pressure": [pressure_before, pressure_after], "steal": steal, "summary": {n: {str(r): v for r, v in s.items()}
                                                                             for n, s in summary.items()},
                      "runs": {n: {str(r): v for r, v in s.items()} for n, s in results.items()},
                      "envpool_runs": envpool_results,
                      "proxy": {str(r): {**p.stats, "cpu_s": proxy_cpu[r]} for r, p in proxies.items()}}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
