"""Finding, starting and stopping `mll_server` processes on loopback.

`ServerProcess` runs one server on a free 127.0.0.1 port (`--address=127.0.0.1:0
--port_file=F`), or with unix_socket=True on a Unix-domain socket in its own temporary directory
(`--address=unix:DIR/mll.sock`), waits until its gRPC health service answers SERVING, and stops
it (SIGTERM, then SIGKILL after a grace period) on `stop()`, when garbage-collected, or at
interpreter exit (`weakref.finalize`, which registers with atexit). When started from the main
thread on Linux the child also gets PR_SET_PDEATHSIG, so a parent killed with SIGKILL does not
leave it behind.

The embedded default of the environments (`address=None`) is ONE server per Python process,
shared by every environment that uses it and reference-counted: `acquire_embedded()` starts it
on first use, and it stops when the last lease is released (the environment's `close()`, or its
garbage collection).
"""

from __future__ import annotations

import os
import pathlib
import shutil
import signal
import subprocess
import sysconfig
import tempfile
import threading
import time
import weakref

import grpc
from grpc_health.v1 import health_pb2, health_pb2_grpc

from ._channel import Security, open_channel
from ._errors import MLLError

SERVER_BIN_ENV = "MLL_SERVER_BIN"
SERVER_BIN_NAME = "mll_server"
# sockaddr_un.sun_path holds 108 bytes with the NUL: the server refuses a longer socket path.
_MAX_UNIX_PATH_BYTES = 107
# A source checkout's build tree (scripts/build.sh), seen from client_py/multi_lunar_lander/.
_CHECKOUT_BUILD_DIR = pathlib.Path(__file__).resolve().parents[2] / "build"


def checkout_build_path(*parts: str) -> pathlib.Path:
    """Where a source checkout's build tree (scripts/build.sh) puts a built file, e.g.
    checkout_build_path("server", "service", "mll_server"); it may not exist."""
    return _CHECKOUT_BUILD_DIR.joinpath(*parts)


_CHECKOUT_BUILD_BIN = checkout_build_path("server", "service", SERVER_BIN_NAME)
# The binary wheel's (scripts/wheel.sh): auditwheel moves the programs out of the scripts
# directory into multi_lunar_lander.scripts/ beside the package, where their RPATH reaches the
# libraries it bundles (multi_lunar_lander.libs/), and leaves in the scripts directory a Python
# shim that execs them; the embedded server runs the binary itself, not the shim.
_WHEEL_BIN = pathlib.Path(__file__).resolve().parent.with_name("multi_lunar_lander.scripts") / SERVER_BIN_NAME


def _is_executable_file(path: str | os.PathLike) -> bool:
    return os.path.isfile(path) and os.access(path, os.X_OK)


def find_server_binary() -> str:
    """The `mll_server` an embedded server runs: $MLL_SERVER_BIN; else the binary wheel's, beside
    this package; else the one installed beside this Python (`pip install .` puts it in the
    environment's scripts directory, which need not be on PATH); else `mll_server` on PATH; else,
    in a source checkout, its build tree."""
    from_env = os.environ.get(SERVER_BIN_ENV)
    if from_env:
        if _is_executable_file(from_env):
            return from_env
        raise MLLError(
            grpc.StatusCode.UNAVAILABLE,
            f"cannot start an embedded mll_server: ${SERVER_BIN_ENV}={from_env} is not an "
            "executable file",
        )
    if _is_executable_file(_WHEEL_BIN):
        return str(_WHEEL_BIN)
    scripts_dir = sysconfig.get_path("scripts")
    beside_python = os.path.join(scripts_dir, SERVER_BIN_NAME) if scripts_dir else ""
    if beside_python and _is_executable_file(beside_python):
        return beside_python
    on_path = shutil.which(SERVER_BIN_NAME)
    if on_path:
        return on_path
    if _is_executable_file(_CHECKOUT_BUILD_BIN):
        return str(_CHECKOUT_BUILD_BIN)
    raise MLLError(
        grpc.StatusCode.UNAVAILABLE,
        f"cannot start an embedded mll_server: none in {scripts_dir}, none on PATH, and "
        f"${SERVER_BIN_ENV} is unset. Install the package with the server (its binary wheel, or "
        "pip install . in a clone of the repository), set $MLL_SERVER_BIN to an mll_server "
        "binary, or pass address='host:port' of a running server.",
    )


def _terminate(process: subprocess.Popen, workdir: str, grace_s: float) -> None:
    """Stops `process` and removes its work directory; safe to call more than once."""
    if process.poll() is None:
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout=grace_s)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
    shutil.rmtree(workdir, ignore_errors=True)


def _read_port(port_file: str) -> int:
    """The port in `port_file`; 0 while it is not written (or written partially)."""
    try:
        return max(int(pathlib.Path(port_file).read_text().strip()), 0)
    except (OSError, ValueError):
        return 0


def wait_until_serving(address: str, timeout_s: float, security: Security = Security()) -> None:
    """Blocks until the server's grpc.health.v1 service answers SERVING (over TLS when
    `security` says so; the health service needs no token)."""
    deadline = time.monotonic() + timeout_s
    with open_channel(address, security) as channel:
        stub = health_pb2_grpc.HealthStub(channel)
        while True:
            remaining = deadline - time.monotonic()
            try:
                reply = stub.Check(
                    health_pb2.HealthCheckRequest(), timeout=max(remaining, 0.01), wait_for_ready=True
                )
                if reply.status == health_pb2.HealthCheckResponse.SERVING:
                    return
            except grpc.RpcError as error:
                if time.monotonic() >= deadline:
                    raise MLLError(
                        grpc.StatusCode.UNAVAILABLE,
                        f"mll_server at {address} did not answer its health check within "
                        f"{timeout_s} s: {error.code().name} {error.details()}",
                    ) from None
            if time.monotonic() >= deadline:
                raise MLLError(
                    grpc.StatusCode.UNAVAILABLE,
                    f"mll_server at {address} reports {reply.status} instead of SERVING",
                )
            time.sleep(0.01)


class ServerProcess:
    """One `mll_server` child process on a free loopback port, or (unix_socket=True) on a
    Unix-domain socket; `address` is what clients pass as address= ("127.0.0.1:PORT" or
    "unix:PATH")."""

    def __init__(
        self,
        binary: str | None = None,
        *,
        threads: int | None = None,
        max_envs: int | None = None,
        idle_timeout_s: float | None = None,
        extra_args: tuple[str, ...] = (),
        startup_timeout_s: float = 30.0,
        grace_s: float = 5.0,
        unix_socket: bool = False,
        tls_root_cert: str | bytes | None = None,
        tls_server_name: str | None = None,
    ):
        """extra_args: more flags (e.g. --tls_cert/--tls_key, --auth_token_file). With TLS on
        the server, tls_root_cert (and tls_server_name) let the start-up health check reach it."""
        health_security = Security.from_options(tls_root_cert, tls_server_name, token="")
        self.binary = binary or find_server_binary()
        self._workdir = tempfile.mkdtemp(prefix="mll_server_")
        port_file = os.path.join(self._workdir, "port")
        socket_path = os.path.join(self._workdir, "mll.sock")
        if unix_socket and len(os.fsencode(socket_path)) > _MAX_UNIX_PATH_BYTES:
            shutil.rmtree(self._workdir, ignore_errors=True)
            raise MLLError(
                grpc.StatusCode.INVALID_ARGUMENT,
                f"unix_socket=True: the socket path {socket_path!r} is longer than "
                f"{_MAX_UNIX_PATH_BYTES} bytes; set TMPDIR to a shorter directory",
            )
        self._log_path = os.path.join(self._workdir, "server.log")
        address_flags = [f"--address=unix:{socket_path}"] if unix_socket else [
            "--address=127.0.0.1:0", f"--port_file={port_file}"]
        args = [self.binary, *address_flags]
        if threads is not None:
            args.append(f"--threads={threads}")
        if max_envs is not None:
            args.append(f"--max_envs={max_envs}")
        if idle_timeout_s is not None:
            args.append(f"--idle_timeout_s={idle_timeout_s:g}")
        args.extend(extra_args)
        self.args = args
        in_main_thread = threading.current_thread() is threading.main_thread()
        with open(self._log_path, "wb") as log:
            try:
                # No preexec_fn: that would run Python (and grpcio's fork handlers, which restart
                # its threads) in the forked child; the server asks for the parent-death signal
                # itself. Only from the main thread: the signal follows the thread that forked.
                self._process = subprocess.Popen(
                    args + ([f"--parent_pid={os.getpid()}"] if in_main_thread else []),
                    stdin=subprocess.DEVNULL,
                    stdout=log,
                    stderr=subprocess.STDOUT,
                )
            except OSError as error:
                shutil.rmtree(self._workdir, ignore_errors=True)
                raise MLLError(
                    grpc.StatusCode.UNAVAILABLE,
                    f"cannot run {self.binary}: {error}. Set MLL_SERVER_BIN to a built mll_server.",
                ) from None
        self._finalizer = weakref.finalize(self, _terminate, self._process, self._workdir, grace_s)
        try:
            if unix_socket:
                self._wait_for(lambda: os.path.exists(socket_path), socket_path, startup_timeout_s)
                self.address = f"unix:{socket_path}"
            else:
                self._wait_for(lambda: _read_port(port_file), port_file, startup_timeout_s)
                self.address = f"127.0.0.1:{_read_port(port_file)}"
            wait_until_serving(self.address, startup_timeout_s, health_security)
        except BaseException:
            self.stop()
            raise

    @property
    def pid(self) -> int:
        return self._process.pid

    @property
    def running(self) -> bool:
        return self._process.poll() is None

    def log_tail(self, limit: int = 2000) -> str:
        try:
            with open(self._log_path, "rb") as log:
                return log.read()[-limit:].decode(errors="replace")
        except OSError:
            return ""

    def _wait_for(self, ready, path: str, timeout_s: float) -> None:
        """Polls `ready()` (the port file written, or the socket made) until it is true."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self._process.poll() is not None:
                raise MLLError(
                    grpc.StatusCode.UNAVAILABLE,
                    f"{' '.join(self.args)} exited with status {self._process.returncode} before "
                    f"serving; its output: {self.log_tail()!r}",
                )
            if ready():
                return
            time.sleep(0.005)
        raise MLLError(
            grpc.StatusCode.UNAVAILABLE,
            f"{' '.join(self.args)} made no {path} within {timeout_s} s; "
            f"its output: {self.log_tail()!r}",
        )

    def stop(self) -> None:
        """SIGTERM, wait (SIGKILL after the grace period); idempotent."""
        self._finalizer()

    def __enter__(self) -> "ServerProcess":
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


class _SharedServer:
    """The process-wide embedded server and its reference count."""

    def __init__(self):
        self._lock = threading.Lock()
        self._server: ServerProcess | None = None
        self._leases = 0

    def acquire(self) -> "Lease":
        with self._lock:
            if self._server is None or not self._server.running:
                self._server = ServerProcess()
            self._leases += 1
            return Lease(self, self._server.address)

    def release(self) -> None:
        with self._lock:
            self._leases -= 1
            if self._leases == 0 and self._server is not None:
                self._server.stop()
                self._server = None

    @property
    def server(self) -> ServerProcess | None:
        return self._server


class Lease:
    """One user's share of the embedded server; `release()` is idempotent."""

    def __init__(self, owner: _SharedServer, address: str):
        self.address = address
        self._owner = owner
        self._released = False

    def release(self) -> None:
        if not self._released:
            self._released = True
            self._owner.release()


_SHARED = _SharedServer()


def _forget_embedded_after_fork() -> None:
    """In a forked child (e.g. a SuperSuit or multiprocessing worker), the parent's embedded
    server is the parent's: the child must neither use its leases nor stop it at exit. The child
    starts its own on first use; leases it inherited release into the parent's old record."""
    global _SHARED
    inherited = _SHARED.server
    if inherited is not None:
        inherited._finalizer.detach()
    _SHARED = _SharedServer()


os.register_at_fork(after_in_child=_forget_embedded_after_fork)


def acquire_embedded() -> Lease:
    """A lease on this process's embedded server, starting it if needed."""
    return _SHARED.acquire()


def embedded_server() -> ServerProcess | None:
    """The running embedded server, if any (for tests and diagnostics)."""
    return _SHARED.server
