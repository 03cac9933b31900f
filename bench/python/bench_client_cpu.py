#!/usr/bin/env python3
"""Client CPU per vector call: the Python vector env against the C++ VectorEnv doing the same
work on the same transport, in one run; and the lines of client code of each checkout measured.

One `mll_server --threads=--threads` on loopback serves every measurement, one at a time. Each
measurement is one client process stepping `--envs` auto-resetting one-lander envs with random
discrete actions, every env on every call (sync step), for `--seconds`:

  Python  bench/service/bench_server_cpu.py's load client: `vector_env(--envs, n_landers=1,
          transport=T)` of the engine's multi_lunar_lander, `step()` in a loop;
  C++     `mll_cli bench --envs=--envs --n_landers=1 --transport=T` (mll::client::VectorEnv).

for each transport T of --transports: "shared_memory", "native" (the native library's gRPC
stream over TCP) and "grpc" (grpcio's stream over TCP; the C++ client has no grpcio, so its
figure beside it is its own gRPC stream, "native", on the same TCP connection kind).

The figure: the client process's CPU (user + system, all its threads, /proc/<pid>/stat) over a
steady-state window inside its run (bench_server_cpu.measure_window: from a second after the
server saw the first step to a second before the end), divided by the calls the server answered
in that window (its /metrics). Start-up, env creation and teardown are outside the window; both
clients are measured the same way. Every transport and engine runs once in each of `--rounds`
rounds, in turn, so that a change of machine load hits all of them; the ratio Python / C++ is
taken per round and reported as the median with its range.

Engines (`--engine NAME=PYTHONPATH[,NATIVE_LIBRARY[,MLL_CLI]]`, repeatable): the Python package
found on PYTHONPATH (a checkout's client_py with its generated stubs, _proto/), the native
library it loads (MLL_NATIVE_LIBRARY) and the mll_cli measured beside it (default --cli). With
no --engine: "current", this checkout's installed package and build. To compare a change with
an older commit in one run, check the older commit out beside this one and keep its build:

    git worktree add /tmp/before <commit>      # plus its build's client_cpp/ binaries and _proto/
    .venv/bin/python bench/python/bench_client_cpu.py \\
        --engine before=/tmp/before/client_py,/tmp/before-bin/libmll_native_stream.so,/tmp/before-bin/mll_cli \\
        --engine after=client_py,build/client_cpp/libmll_native_stream.so,build/client_cpp/mll_cli

`--reused NAME` measures engine NAME's Python client a second time with `vector_env(copy=False)`
(the arrays the engine writes in place, handed out without the per-call copy), beside the same
C++ figure.

Lines of client code (`wc -l`) of each engine's checkout (the folder above its client_py) are
printed too: the Python package, the C++ client (src, include, native) and, of these, the files
of the vector engine. Loopback only; every run is bounded by --seconds. Prints Markdown tables
and one JSON line.

    .venv/bin/python bench/python/bench_client_cpu.py --rounds 5
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import statistics
import sys

from bench_client import REPO, add_binary_arguments

sys.path.insert(0, str(REPO / "bench" / "service"))
from bench_server_cpu import CliClients, PythonClients, Server, measure_window  # noqa: E402

TRANSPORTS = ("shared_memory", "native", "grpc")
# The C++ client's transport beside each Python one.
CPP_TRANSPORT = {"shared_memory": "shared_memory", "native": "native", "grpc": "native"}
# Client code, by part: (folder, file name pattern) under a checkout.
CLIENT_CODE = {
    "Python package (client_py/multi_lunar_lander/*.py)": [("client_py/multi_lunar_lander", "*.py")],
    "C++ client (client_cpp/src, include, native)": [
        ("client_cpp/src", "*"), ("client_cpp/include", "**/*"), ("client_cpp/native", "*")],
}
# The files of the vector engine (placement, pipelining, failover record, state, auto-reset, the
# binding between the two languages), in either language; a file a checkout lacks counts 0.
VECTOR_ENGINE = (
    "client_py/multi_lunar_lander/vector.py", "client_py/multi_lunar_lander/_record.py",
    "client_py/multi_lunar_lander/_native.py", "client_cpp/src/vector_env.cc", "client_cpp/src/env_record.cc",
    "client_cpp/src/env_record.h", "client_cpp/include/mll/vector_env.h", "client_cpp/native/vector_c_api.h",
    "client_cpp/native/vector_c_api.cc", "client_cpp/native/fast_calls_module.c",
)


class Engine:
    """A Python client package with its native library and the mll_cli measured beside it."""

    def __init__(self, name: str, python_path: str | None, library: str | None, cli: str):
        self.name, self.cli = name, cli
        self.env = None
        self.root = REPO
        if python_path:
            self.env = dict(os.environ, PYTHONPATH=str(pathlib.Path(python_path).resolve()))
            self.root = pathlib.Path(python_path).resolve().parent
        if library:
            self.env = dict(self.env or os.environ, MLL_NATIVE_LIBRARY=str(pathlib.Path(library).resolve()))

    @classmethod
    def parse(cls, text: str, default_cli: str) -> Engine:
        name, _, rest = text.partition("=")
        parts = rest.split(",")
        if not name or not parts[0] or len(parts) > 3:
            raise argparse.ArgumentTypeError(f"--engine {text}: expected NAME=PYTHONPATH[,NATIVE_LIBRARY[,MLL_CLI]]")
        return cls(name, parts[0], parts[1] if len(parts) > 1 and parts[1] else None,
                   parts[2] if len(parts) > 2 and parts[2] else default_cli)


def _lines(path: pathlib.Path) -> int:
    with path.open("rb") as file:
        return sum(1 for _ in file)


def client_lines(root: pathlib.Path) -> dict[str, int]:
    """Lines of client code under a checkout, by part, plus each vector-engine file's."""
    counts = {}
    for part, globs in CLIENT_CODE.items():
        counts[part] = sum(_lines(path) for folder, pattern in globs for path in (root / folder).glob(pattern)
                           if path.is_file())
    for name in VECTOR_ENGINE:
        counts[name] = _lines(root / name) if (root / name).is_file() else 0
    counts["vector engine (the files above)"] = sum(counts[name] for name in VECTOR_ENGINE)
    return counts


def measure(server: Server, engine: Engine, kind: str, transport: str, args) -> dict:
    """One measurement: a Python (kind "python"; "python_reused": with copy=False) or C++ ("cpp")
    client of `engine` on `transport`; {"refused": why} when the engine's vector_env does not start
    on that transport."""
    options = argparse.Namespace(clients=1, envs=args.envs, seconds=args.seconds, transport=transport,
                                 cli=engine.cli, copy=False if kind == "python_reused" else None)
    if kind.startswith("python"):
        def clients():
            return PythonClients(options, server.address, 1, None, env=engine.env)
    else:
        def clients():
            return CliClients(options, server.address, 1, None)
    try:
        window = measure_window(options, server, 1, clients)
    except RuntimeError as error:  # E.g. a package whose vector envs have no grpcio transport.
        if not kind.startswith("python"):
            raise
        # The exception's last line, its first clause: "MLLError: INVALID_ARGUMENT: transport is 'grpc': ...".
        why = str(error).strip().splitlines()[-1].split(";")[0].rpartition("._errors.")[2]
        print(f"{engine.name} vector_env on {transport}: {why}", file=sys.stderr)
        return {"refused": why}
    ticks, precise = window["client_window_proc_cpu_s"], window["client_window_cpu_s"]
    if abs(ticks - precise) > 0.03 + 0.05 * precise:
        print(f"warning: {engine.name} {kind} {transport}: client CPU {precise:.3f} s (threads) against "
              f"{ticks:.3f} s (/proc/<pid>/stat) over the window", file=sys.stderr)
    used = window["cli"]["transport"]
    if used != transport:
        raise RuntimeError(f"{engine.name} {kind} asked for transport {transport} and got {used}")
    return {"client_us_per_call": window["client_cpu_us_per_call"],
            "server_us_per_call": window["server_proc_cpu_s"] / max(1, window["window_calls"]) * 1e6,
            "calls_per_s": window["window_calls"] / window["window_s"], "window_calls": window["window_calls"]}


def _summary(values: list[float], digits: int = 0) -> str:
    """median (min-max)."""
    return f"{statistics.median(values):.{digits}f} ({min(values):.{digits}f}-{max(values):.{digits}f})"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_binary_arguments(parser)
    parser.add_argument("--engine", action="append", default=[], metavar="NAME=PYTHONPATH[,LIBRARY[,MLL_CLI]]",
                        help="a Python client package to measure (repeatable; default: this checkout's)")
    parser.add_argument("--transports", default=",".join(TRANSPORTS), help="comma-separated, of " + ", ".join(TRANSPORTS))
    parser.add_argument("--envs", type=int, default=64, help="envs per call")
    parser.add_argument("--threads", type=int, default=2, help="mll_server --threads")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--seconds", type=float, default=4.0, help="each client's run, >= 4 (window: 2 s less)")
    parser.add_argument("--reused", action="append", default=[], metavar="NAME",
                        help="also measure engine NAME's Python client with vector_env(copy=False), the arrays "
                             "reused between calls (repeatable; a package that has copy=)")
    args = parser.parse_args()
    transports = args.transports.split(",")
    if not set(transports) <= set(TRANSPORTS):
        parser.error(f"--transports: each of {', '.join(TRANSPORTS)}")
    if args.seconds < 4:
        parser.error("--seconds: at least 4 (a second either side of the window is left out)")
    engines = [Engine.parse(text, args.cli) for text in args.engine] or [Engine("current", None, None, args.cli)]
    if len({engine.name for engine in engines}) != len(engines):
        parser.error("--engine: the names must differ")
    if not set(args.reused) <= {engine.name for engine in engines}:
        parser.error("--reused: the name of an engine measured")

    # results[engine][kind][transport] -> one dict per round.
    kinds = {engine.name: ["python"] + (["python_reused"] if engine.name in args.reused else []) + ["cpp"]
             for engine in engines}
    results = {engine.name: {kind: {t: [] for t in transports} for kind in kinds[engine.name]} for engine in engines}
    load = [os.getloadavg()]
    server = Server(args.server, args.threads, None)
    try:
        for _ in range(args.rounds):
            for transport in transports:
                for engine in engines:
                    for kind in kinds[engine.name]:
                        results[engine.name][kind][transport].append(
                            measure(server, engine, kind, CPP_TRANSPORT[transport] if kind == "cpp" else transport, args))
            load.append(os.getloadavg())
    finally:
        server.close()

    one_minute = [entry[0] for entry in load]
    print(f"{args.envs} envs x 1 lander per call, sync step, random discrete actions, auto-reset; mll_server "
          f"--threads={args.threads}; {os.cpu_count()} cores; {args.rounds} rounds of {args.seconds:g} s runs; "
          f"load average (1 min) {min(one_minute):.1f}-{max(one_minute):.1f} over the run\n")
    print("| transport | engine | Python client CPU us/call | C++ client CPU us/call (its transport) "
          "| Python / C++ | calls/s Python / C++ | server CPU us/call Python / C++ |")
    print("|---|---|---|---|---|---|---|")
    ratios = {}

    def column(rounds: list[dict], key: str) -> list[float]:
        return [one[key] for one in rounds]

    for transport in transports:
        for engine in engines:
            cpp = results[engine.name]["cpp"][transport]
            for kind in kinds[engine.name][:-1]:
                python = results[engine.name][kind][transport]
                name = engine.name + (" (copy=False)" if kind == "python_reused" else "")
                if any("refused" in one for one in python):
                    print(f"| {transport} | {name} | not measured: {python[0].get('refused', 'refused')} "
                          f"| {_summary([one['client_us_per_call'] for one in cpp])} ({CPP_TRANSPORT[transport]}) "
                          "| | | |")
                    continue
                ratio = [p["client_us_per_call"] / c["client_us_per_call"] for p, c in zip(python, cpp)]
                ratios[f"{name}/{transport}"] = ratio
                print(f"| {transport} | {name} | {_summary(column(python, 'client_us_per_call'))} "
                      f"| {_summary(column(cpp, 'client_us_per_call'))} ({CPP_TRANSPORT[transport]}) "
                      f"| {_summary(ratio, 2)} | {statistics.median(column(python, 'calls_per_s')):,.0f} / "
                      f"{statistics.median(column(cpp, 'calls_per_s')):,.0f} "
                      f"| {statistics.median(column(python, 'server_us_per_call')):.0f} / "
                      f"{statistics.median(column(cpp, 'server_us_per_call')):.0f} |")

    lines = {engine.name: client_lines(engine.root) for engine in engines}
    print(f"\nLines of client code (wc -l) | {' | '.join(engine.name for engine in engines)} |")
    print("|---|" + "---|" * len(engines))
    for part in next(iter(lines.values())):
        print(f"| {part} | {' | '.join(str(lines[engine.name][part]) for engine in engines)} |")
    print(json.dumps({"args": {key: value for key, value in vars(args).items()}, "load_average": load,
                      "results": results, "ratios": ratios, "lines": lines,
                      "engines": {engine.name: str(engine.root) for engine in engines}}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
