#!/usr/bin/env python3
"""Client cost per 64-env vector step in CPU instructions (valgrind callgrind), which unlike CPU
time does not depend on what else the machine is running: the Python vector env beside the C++
`VectorEnv` (`mll_cli bench`) doing the same work on the same transport.

One real mll_server (not under valgrind) holds the envs; each client runs under callgrind:

  C++       `mll_cli bench --envs=--envs --n_landers=--n_landers --transport=T`: the instructions
            inside `VectorEnv::Step` per call (callgrind's inclusive count of its calls);
  library   Python calling the C interface's `mll_vector_env_step` through ctypes, nothing else
            (the actions copied into the adapter's buffer, the call): vector_env.step's floor;
  nocopy    `vector_env(copy=False).step(actions)`;
  copy      `vector_env().step(actions)` (each result array copied for the caller).

A Python client makes `--steps` calls of one kind after the same set-up, and a run with no calls
gives the set-up's count, so (run - set-up) / steps is one step's cost in the calling thread
(Python, ctypes, NumPy and the library). Beside it, the instructions inside `mll_vector_env_step`
per call in the same run (the library's share, the same engine as C++'s `VectorEnv::Step`).
Loopback only; bounded by --steps, --seconds and a timeout per run.

    .venv/bin/python bench/python/client_instructions.py --server build/server/service/mll_server
"""

from __future__ import annotations

import argparse
import ctypes
import os
import pathlib
import re
import subprocess
import sys
import tempfile

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
REPO = HERE.parents[1]
KINDS = ("none", "library", "nocopy", "copy")
CPP_STEP = r"mll::client::VectorEnv::Step\(absl::[^)]*Span<int const>\)"
LIBRARY_STEP = r"mll_vector_env_step(_async|_wait)?"
LIBRARY_CALL = r"mll_vector_env_step(_wait)?"


def client(kind: str, steps: int, address: str, envs: int, n_landers: int, transport: str) -> None:
    """Child process (run under callgrind): the same set-up for every kind, then `steps` calls."""
    import multi_lunar_lander as mll
    from multi_lunar_lander import _native

    env = mll.vector_env(envs, address=address, n_landers=n_landers, transport=transport, copy=kind != "nocopy")
    env.reset(seed=0)
    table = np.random.default_rng(0).integers(0, 4, size=(256, envs, n_landers), dtype=np.int32)
    env.step(table[0])  # Every kind's first step is made here, outside the count.
    block = env._fast[0]
    call, handle = _native.bare(env._lib).mll_vector_env_step, ctypes.c_void_p(env._handle)
    address_of_block, count, continuous = ctypes.c_void_p(block.ctypes.data), ctypes.c_size_t(block.size), int(env.continuous)
    for i in range(steps if kind != "none" else 0):
        if kind == "library":
            block[...] = table[i % 256]
            if call(handle, address_of_block, count, continuous, _native.READ_SLICE_MS):
                raise RuntimeError("mll_vector_env_step failed")
        else:
            env.step(table[i % 256])
    env.close()


def callgrind_totals(path: pathlib.Path) -> int:
    return int(re.search(r"^totals: (\d+)", path.read_text(), re.M).group(1))


def inclusive(path: pathlib.Path, function: str, counted: str | None = None) -> tuple[int, int]:
    """(calls, instructions inside them) of the functions whose name matches `function`, summed
    over their call sites in callgrind file `path` from functions that do not match it (names are
    compressed to "(id)" after their first appearance). Calls are counted for the names matching
    `counted` (default: `function`): ctypes' libffi enters mll_vector_env_step by a jump, which
    callgrind shows as libffi calling mll_vector_env_step_async and mll_vector_env_step_wait."""
    names, caller, callee, calls, cost, pending = {}, "", "", 0, 0, False
    for line in path.read_text().splitlines():
        named = re.match(r"c?fn=\((\d+)\)(?: (.*))?$", line)
        if named:
            if named.group(2):
                names[named.group(1)] = named.group(2)
            if line.startswith("cfn="):
                callee = names.get(named.group(1), "")
            else:
                caller = names.get(named.group(1), "")
            continue
        if line.startswith("calls="):
            pending = re.fullmatch(function, callee) is not None and re.fullmatch(function, caller) is None
            if pending and re.fullmatch(counted or function, callee):
                calls += int(line.split("=", 1)[1].split()[0])
            continue
        if pending:  # The call line's cost: "<position> <inclusive Ir>".
            cost += int(line.split()[-1])
            pending = False
    return calls, cost


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--server", default=os.environ.get("MLL_SERVER_BIN", str(REPO / "build/server/service/mll_server")))
    parser.add_argument("--cli", default=str(REPO / "build/client_cpp/mll_cli"))
    parser.add_argument("--envs", type=int, default=64)
    parser.add_argument("--n_landers", type=int, default=1)
    parser.add_argument("--transport", choices=("shared_memory", "native"), default="shared_memory")
    parser.add_argument("--steps", type=int, default=1000, help="calls of each Python kind")
    parser.add_argument("--seconds", type=float, default=10.0, help="how long mll_cli bench steps")
    parser.add_argument("--client", choices=KINDS, help=argparse.SUPPRESS)
    parser.add_argument("--address", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.client:
        client(args.client, args.steps, args.address, args.envs, args.n_landers, args.transport)
        return 0

    import multi_lunar_lander as mll

    python, library = {}, {}
    with mll.ServerProcess(args.server, threads=2) as server, tempfile.TemporaryDirectory() as tmp:
        folder = pathlib.Path(tmp)
        cli_file = folder / "cli"
        subprocess.run(
            ["valgrind", "--tool=callgrind", f"--callgrind-out-file={cli_file}", args.cli, "bench",
             f"--address={server.address}", f"--envs={args.envs}", f"--n_landers={args.n_landers}",
             f"--transport={args.transport}", f"--seconds={args.seconds}"],
            capture_output=True, text=True, timeout=args.seconds * 10 + 300, check=True,
        )
        cpp_calls, cpp_cost = inclusive(cli_file, CPP_STEP)
        for kind in KINDS:
            subprocess.run(
                ["valgrind", "--tool=callgrind", "--separate-threads=yes", f"--callgrind-out-file={folder / kind}",
                 sys.executable, __file__, f"--client={kind}", f"--steps={args.steps}", f"--address={server.address}",
                 f"--envs={args.envs}", f"--n_landers={args.n_landers}", f"--transport={args.transport}"],
                capture_output=True, text=True, timeout=900, check=True,
            )
            main_thread = folder / f"{kind}-01"  # The calling thread's file.
            python[kind] = callgrind_totals(main_thread)
            library[kind] = inclusive(main_thread, LIBRARY_STEP, LIBRARY_CALL)
    if cpp_calls == 0:
        raise RuntimeError("mll_cli bench made no VectorEnv::Step call under callgrind")
    cpp = cpp_cost / cpp_calls
    print(f"client instructions per call, {args.envs} envs x {args.n_landers} landers, {args.transport}, "
          f"C++ over {cpp_calls} calls, Python {args.steps} calls of each kind:")
    print("| client | instructions per call | inside mll_vector_env_step / VectorEnv::Step | vs C++ |")
    print("|---|---|---|---|")
    print(f"| C++ `VectorEnv::Step` (`mll_cli bench`) | {cpp:,.0f} | {cpp:,.0f} | 1.00 |")
    for kind, what in (("library", "Python, ctypes `mll_vector_env_step` alone"),
                       ("nocopy", "Python `vector_env(copy=False).step`"), ("copy", "Python `vector_env().step`")):
        per_call = (python[kind] - python["none"]) / args.steps
        # The set-up run's calls (reset's none, the first step's one) are outside the count.
        calls = library[kind][0] - library["none"][0]
        inside = (library[kind][1] - library["none"][1]) / calls if calls else float("nan")
        print(f"| {what} | {per_call:,.0f} | {inside:,.0f} | {per_call / cpp:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
