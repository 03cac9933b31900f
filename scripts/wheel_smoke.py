"""The binary wheel as a trainer meets it: scripts/wheel-test.sh runs this with the Python of a
fresh venv (no system site packages) into which it pip-installed dist/'s wheel, inside a clean
Debian 12 chroot (no compiler, no -dev package, no checkout), from /, with no MLL_* variable,
in a network namespace of its own whose loopback also carries --remote_host (an address that is
not 127.0.0.0/8, so that a server there sees its clients as remote).

Checks: mll_server and mll_cli on the venv's PATH print the package's version for --version;
parallel_env() starts the embedded server (the wheel's binary, beside the package) and steps,
and GetServerInfo reports the same version; vector_env(64) steps over shared memory with the
wheel's native library; a vector env of a server at --remote_host (the wheel's mll_server,
started through the venv's `mll_server`) steps over the native library without shared memory;
both give the same bits for the same seed and actions. Prints the installed size and the import
time of the package.
Exit code 0 only if every check passed.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import os
import pathlib
import shutil
import signal
import subprocess
import sys
import tempfile
import time

import numpy as np

STEPS = 50
NUM_ENVS = 64
N_LANDERS = 2
SEED = 7


def ok(what: str) -> None:
    print(f"wheel-smoke: ok: {what}", flush=True)


def check(condition: bool, what: str) -> None:
    if not condition:
        sys.exit(f"wheel-smoke: FAIL: {what}")
    ok(what)


def import_time_s(repeats: int = 5) -> tuple[float, float]:
    """The best of `repeats` wall times of a fresh interpreter importing the package, and of one
    importing nothing (the interpreter's own start)."""

    def best(code: str) -> float:
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            subprocess.run([sys.executable, "-c", code], check=True)
            times.append(time.perf_counter() - start)
        return min(times)

    return best("import multi_lunar_lander"), best("pass")


def rollout(mll, transport_expected: str, **options) -> tuple[np.ndarray, np.ndarray]:
    """STEPS steps of NUM_ENVS envs with seeded random actions; the observations and rewards."""
    vector = mll.vector_env(NUM_ENVS, n_landers=N_LANDERS, **options)
    try:
        check(vector.transport == transport_expected, f"vector_env({NUM_ENVS}, {options}) steps over "
              f"{vector.transport!r} (expected {transport_expected!r})")
        observations = [vector.reset(seed=SEED)[0]]
        rewards = []
        actions = np.random.default_rng(SEED).integers(0, 4, size=(STEPS, NUM_ENVS, N_LANDERS), dtype=np.int32)
        for step_actions in actions:
            result = vector.step(step_actions)
            observations.append(result[0])
            rewards.append(result[1])
        return np.stack(observations), np.stack(rewards)
    finally:
        vector.close()


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--remote_host", required=True)
    args = parser.parse_args()

    check(not [k for k in os.environ if k.startswith("MLL_")], "no MLL_* variable is set")
    check(not any((d / ".git").exists() or (d / "CMakeLists.txt").exists() for d in [pathlib.Path.cwd(),
          *pathlib.Path.cwd().parents]), f"the working directory {os.getcwd()} is in no checkout")
    check(sys.prefix != sys.base_prefix, f"a venv: {sys.prefix}")

    import multi_lunar_lander as mll
    from multi_lunar_lander import _native, _server

    package = pathlib.Path(mll.__file__).resolve().parent
    check(package.is_relative_to(pathlib.Path(sys.prefix).resolve()), f"the package is installed: {package}")
    version = importlib.metadata.version("multi_lunar_lander")
    bin_dir = pathlib.Path(sys.prefix) / "bin"
    for program in ("mll_server", "mll_cli"):
        found = shutil.which(program)
        check(found == str(bin_dir / program), f"{program} on PATH is the venv's: {found}")
        printed = subprocess.run([program, "--version"], capture_output=True, text=True, timeout=60)
        check(
            printed.returncode == 0 and printed.stdout.strip() == f"{program} {version}",
            f"`{program} --version` prints {printed.stdout.strip()!r} (the package is {version})",
        )

    env = mll.parallel_env(n_landers=N_LANDERS)
    observations, _ = env.reset(seed=SEED)
    for _ in range(STEPS):
        if not env.agents:
            break
        observations, *_ = env.step({agent: mll.heuristic(observations[agent]) for agent in env.agents})
    binary = pathlib.Path(mll.embedded_server().binary)
    check(binary == package.with_name("multi_lunar_lander.scripts") / "mll_server",
          f"parallel_env() stepped on the embedded server {binary}")
    check(env.server_info.server_version == version,
          f"GetServerInfo's server_version {env.server_info.server_version!r} is the package's")
    env.close()

    shared = rollout(mll, "shared_memory")
    library = pathlib.Path(_native._load()[0]._name)
    check(library == package / _native.LIBRARY_NAME, f"the native library is the wheel's: {library}")

    workdir = tempfile.mkdtemp()
    port_file = os.path.join(workdir, "port")
    server = subprocess.Popen(
        ["mll_server", f"--address={args.remote_host}:0", f"--port_file={port_file}"],
        stdin=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 60
        while not _server._read_port(port_file):  # Bounded: the server's exit or the deadline.
            if server.poll() is not None or time.monotonic() >= deadline:
                sys.exit(f"wheel-smoke: FAIL: mll_server --address={args.remote_host}:0 wrote no port "
                         f"(exit status {server.poll()})")
            time.sleep(0.01)
        address = f"{args.remote_host}:{_server._read_port(port_file)}"
        _server.wait_until_serving(address, 60)
        remote = rollout(mll, "native", address=address)
        check(all(np.array_equal(a, b) and a.tobytes() == b.tobytes() for a, b in zip(shared, remote)),
              f"the same bits over shared memory and from {address} over the native library "
              f"({STEPS} steps of {NUM_ENVS} envs)")
    finally:
        server.send_signal(signal.SIGTERM)
        code = server.wait(timeout=60)
        shutil.rmtree(workdir, ignore_errors=True)
    check(code == 0, f"the separate mll_server exited {code} on SIGTERM")

    sizes = {
        directory.name: sum(f.stat().st_size for f in directory.rglob("*") if f.is_file())
        for directory in (package, package.with_name("multi_lunar_lander.libs"),
                          package.with_name("multi_lunar_lander.scripts"))
    }
    print(f"wheel-smoke: installed: {sum(sizes.values()) / 1e6:.1f} MB (" +
          ", ".join(f"{name} {size / 1e6:.1f} MB" for name, size in sizes.items()) + ")")
    imported, bare = import_time_s()
    print(f"wheel-smoke: import multi_lunar_lander: {imported:.2f} s in a fresh interpreter "
          f"(the interpreter alone: {bare:.2f} s; best of 5)")


if __name__ == "__main__":
    main()
