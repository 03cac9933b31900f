"""docs/remote.md runs as written across two hosts: the server's host and the trainer's host are
two network namespaces made here, joined by a veth pair that carries the page's own addresses
(192.0.2.10 and 192.0.2.20, a documentation range; they exist only inside the namespaces, and
nothing leaves them: the namespaces have no other link). The host's network is not touched.

Every sh and python block of the page is marked `<!-- test: skip on the server's host: ... -->`
or `... on the trainer's host: ...` (so test_readme.py, which runs the other documents' blocks
on this machine's loopback, passes them over) and runs here, in document order, in its host's
namespace and working directory: an sh block that starts `mll_server` serves until the next
one replaces it (SIGTERM, as Ctrl-C would), the others run to their end; a ```text block right
after a block is what it prints ("..." stands for any text, as in test_readme.py). The files
the page says to copy to the trainer's host are copied after each block of the server's host.

Also checked: each row of the page's table of connection failures is the failure it names (made
to happen between the namespaces), the Little's-law table's arithmetic, and every flag and
option the page names exists. The namespace tests need root (`ip netns add`, iproute2) and skip
without it, saying why; CI runs as root.
"""

from __future__ import annotations

import ast
import contextlib
import dataclasses
import inspect
import os
import pathlib
import re
import secrets
import select
import shutil
import signal
import subprocess
import sys
import sysconfig
import time

import pytest

import multi_lunar_lander as mll
from multi_lunar_lander import _native
from multi_lunar_lander._server import checkout_build_path
from multi_lunar_lander.vector import VectorEnv

from test_readme import Block, _environment, _expect_output, blocks
from test_security import self_signed

_REPO = pathlib.Path(__file__).resolve().parents[2]
_DOC = "docs/remote.md"
SERVER_IP, TRAINER_IP, PREFIX = "192.0.2.10", "192.0.2.20", 24
ADDRESS = f"{SERVER_IP}:50051"
NO_HOST_IP = "192.0.2.30"  # In the link's subnet, held by no one: nothing answers its ARP.
DROPPED_IP = "192.0.2.40"  # Sent to the server's namespace, which does not hold it and drops it.
_HOSTS = {"on the server's host": "server", "on the trainer's host": "trainer"}
_RUN_TIMEOUT_S = 120  # A block (or a failure) that takes longer fails.
_SERVER_START_S = 30  # Until a server block has printed its output.
_SERVER_STOP_S = 30


# --- The page's blocks. ---


@dataclasses.dataclass(frozen=True)
class Step:
    host: str  # "server" or "trainer".
    block: Block
    output: Block | None  # The ```text block right after it: what it prints.

    @property
    def serves(self) -> bool:
        """An sh block that starts a server that runs until stopped."""
        return self.block.language == "sh" and self.block.code.lstrip().startswith("mll_server")


def _steps() -> list[Step]:
    found = blocks(_DOC)
    steps = []
    for index, block in enumerate(found):
        if block.language == "text":
            continue
        host = next((name for prefix, name in _HOSTS.items() if block.reason.startswith(prefix)), None)
        assert block.marker == "skip" and host, (
            f"{block.id}: every {block.language} block of {_DOC} runs on a host of the walkthrough: mark it "
            "<!-- test: skip on the server's host: ... --> or <!-- test: skip on the trainer's host: ... -->"
        )
        following = found[index + 1] if index + 1 < len(found) else None
        output = following if following is not None and following.language == "text" else None
        steps.append(Step(host, block, output))
    return steps


def _text() -> str:
    return (_REPO / _DOC).read_text(encoding="utf-8")


def _copied() -> list[str]:
    """The files the page says to copy to the trainer's host."""
    match = re.search(r"Copy ((?:`[^`]+`(?:, | and )?)+) to the trainer", _text())
    assert match, f"{_DOC} no longer says which files to copy to the trainer's host"
    return re.findall(r"`([^`]+)`", match.group(1))


def test_every_block_runs_on_a_host_and_text_blocks_are_outputs():
    steps = _steps()
    assert {step.host for step in steps} == {"server", "trainer"}
    assert sum(step.serves for step in steps) >= 2, "the page starts a plaintext and a TLS server"
    outputs = {step.output.line for step in steps if step.output}
    stray = [block.id for block in blocks(_DOC) if block.language == "text" and block.line not in outputs]
    assert not stray, f"text blocks that follow no block of the walkthrough: {stray}"
    assert "key.pem" not in _copied()


# --- Flags and options the page names. ---


def _cli_binary() -> pathlib.Path | None:
    candidates = [
        os.environ.get("MLL_CLI_BIN"),
        os.path.join(sysconfig.get_path("scripts") or "", "mll_cli"),
        shutil.which("mll_cli"),
        checkout_build_path("client_cpp", "mll_cli"),
    ]
    for candidate in candidates:
        if candidate and os.path.isfile(candidate) and os.access(candidate, os.X_OK):
            return pathlib.Path(candidate)
    return None


def _help(binary) -> str:
    printed = subprocess.run([str(binary), "--help"], capture_output=True, text=True, timeout=30)
    return printed.stdout + printed.stderr


def test_every_flag_the_page_gives_exists():
    cli = _cli_binary()
    if cli is None:
        pytest.skip("mll_cli is not built (scripts/build.sh) nor installed")
    helps = {"mll_server": _help(mll.find_server_binary()), "mll_cli": _help(cli)}
    checked, unknown = 0, []
    for step in _steps():
        if step.block.language != "sh":
            continue
        for line in step.block.code.replace("\\\n", " ").split("\n"):
            program = line.split()[0] if line.split() else ""
            for flag in re.findall(r"(?<!\S)--(\w+)", line) if program in helps else ():
                checked += 1
                if f"--{flag}=" not in helps[program]:
                    unknown.append(f"{step.block.id}: {program} --{flag}")
    assert checked and not unknown, f"flags that --help does not list: {unknown}"


def _parameters(function) -> set[str]:
    return {name for name, p in inspect.signature(function).parameters.items() if p.kind != p.VAR_KEYWORD}


# The keyword options of the functions the page calls; vector_env's are VectorEnv's and the
# environment's options.
_OPTIONS = {
    "vector_env": _parameters(VectorEnv.__init__) | set(mll.CONFIG_OPTIONS),
    "server_info": _parameters(mll.server_info),
}


def test_every_option_the_page_names_exists():
    text = _text()
    known = set().union(*_OPTIONS.values())
    unknown, checked = [], 0
    for step in _steps():
        if step.block.language != "python":
            continue
        for node in ast.walk(ast.parse(step.block.code)):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr in _OPTIONS:
                for keyword in node.keywords:
                    checked += 1
                    if keyword.arg not in _OPTIONS[node.func.attr]:
                        unknown.append(f"{step.block.id}: {node.func.attr}({keyword.arg}=)")
    prose = re.sub(r"^```.*?^```", "", text, flags=re.MULTILINE | re.DOTALL)
    for span in re.findall(r"(?<!`)`([^`\n]+)`(?!`)", prose):
        for option in re.findall(r"^(\w+)=", span):
            checked += 1
            if option not in known:
                unknown.append(f"`{span}`")
        for attribute in re.findall(r"^vec\.(\w+)$", span):
            checked += 1
            if not hasattr(VectorEnv, attribute):
                unknown.append(f"`{span}`")
    assert checked and not unknown, f"{_DOC} names options that do not exist: {unknown}"


# --- The table of envs in flight. ---


def test_the_envs_in_flight_table_is_littles_law():
    """Each cell is N / RTT: N envs in flight, each away for one round trip."""
    text = _text()
    header = re.search(r"^\| RTT \|(.*)\|$", text, re.MULTILINE)
    assert header, f"{_DOC} has no table of envs in flight by RTT"
    counts = [int(cell.strip().split()[0].replace(",", "")) for cell in header.group(1).split("|")]
    rows = re.findall(r"^\| ([\d.]+) ms \|(.*)\|$", text[header.end():], re.MULTILINE)
    assert len(rows) >= 4
    for rtt_ms, cells in rows:
        shown = [int(cell.strip().replace(",", "")) for cell in cells.split("|")]
        expected = [round(count / (float(rtt_ms) / 1000)) for count in counts]
        assert shown == expected, f"RTT {rtt_ms} ms: the table shows {shown}, N / RTT is {expected}"


# --- Two hosts in two network namespaces. ---


def _run_checked(*argv: str) -> subprocess.CompletedProcess:
    return subprocess.run(argv, capture_output=True, text=True, timeout=30)


@dataclasses.dataclass
class Host:
    namespace: str
    workdir: pathlib.Path
    environment: dict

    def start(self, argv, **kwargs) -> subprocess.Popen:
        """`argv` in this host's namespace and working directory, in a process group of its own."""
        return subprocess.Popen(
            ["ip", "netns", "exec", self.namespace, *argv],
            cwd=self.workdir,
            env=self.environment,
            stdin=subprocess.DEVNULL,
            start_new_session=True,
            **kwargs,
        )

    def run(self, argv) -> subprocess.CompletedProcess:
        process = self.start(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            stdout, stderr = process.communicate(timeout=_RUN_TIMEOUT_S)
        finally:
            _end(process)
        return subprocess.CompletedProcess(argv, process.returncode, stdout, stderr)

    def leftover_pids(self) -> list[int]:
        listed = _run_checked("ip", "netns", "pids", self.namespace)
        return [int(pid) for pid in listed.stdout.split()]


def _end(process: subprocess.Popen) -> None:
    """Kills what is left of a process group this file started."""
    if process.poll() is None:
        try:
            os.killpg(process.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        process.wait(timeout=_SERVER_STOP_S)


@pytest.fixture(scope="module")
def hosts(tmp_path_factory):
    if os.geteuid() != 0:
        pytest.skip("needs root to make network namespaces (ip netns add); CI runs as root")
    if shutil.which("ip") is None:
        pytest.skip("needs iproute2's `ip` to make network namespaces")
    cli = _cli_binary()
    if cli is None:
        pytest.skip("mll_cli is not built (scripts/build.sh) nor installed")
    # The page's commands name the programs as `pip install .` installs them: on PATH.
    bin_dir = tmp_path_factory.mktemp("bin")
    (bin_dir / "mll_server").symlink_to(mll.find_server_binary())
    (bin_dir / "mll_cli").symlink_to(cli)
    environment = _environment()
    environment["PATH"] = f"{bin_dir}{os.pathsep}{environment.get('PATH', '')}"
    tag = secrets.token_hex(3)
    made: list[Host] = []
    try:
        for role in ("server", "trainer"):
            namespace = f"mll-test-{tag}-{role[0]}"
            added = _run_checked("ip", "netns", "add", namespace)
            if added.returncode != 0:
                pytest.skip(f"cannot make a network namespace here: ip netns add: {added.stderr.strip()}")
            made.append(Host(namespace, tmp_path_factory.mktemp(role), environment))
        server, trainer = made
        # The veth pair is made inside the server's namespace with its peer in the trainer's: it
        # never exists in the host's namespace.
        commands = [
            ("-n", server.namespace, "link", "add", "mll-s", "type", "veth", "peer", "name", "mll-t",
             "netns", trainer.namespace),
            ("-n", server.namespace, "address", "add", f"{SERVER_IP}/{PREFIX}", "dev", "mll-s"),
            ("-n", trainer.namespace, "address", "add", f"{TRAINER_IP}/{PREFIX}", "dev", "mll-t"),
        ]
        for host, device in ((server, "mll-s"), (trainer, "mll-t")):
            commands += [("-n", host.namespace, "link", "set", "lo", "up"),
                         ("-n", host.namespace, "link", "set", device, "up")]
        for command in commands:
            done = _run_checked("ip", *command)
            if done.returncode != 0:
                pytest.skip(f"cannot link two network namespaces here: ip {' '.join(command)}: {done.stderr.strip()}")
        yield {"server": server, "trainer": trainer}
    finally:
        for host in made:
            for pid in host.leftover_pids():  # Processes of this file's blocks, left running.
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
            _run_checked("ip", "netns", "delete", host.namespace)


def _read_lines(process: subprocess.Popen, count: int, timeout_s: float) -> list[str]:
    """Up to `count` lines of the process's stdout, waiting at most `timeout_s` in all."""
    lines, pending = [], b""
    deadline = time.monotonic() + timeout_s
    descriptor = process.stdout.fileno()
    while len(lines) < count:
        remaining = deadline - time.monotonic()
        if remaining <= 0 or not select.select([descriptor], [], [], remaining)[0]:
            break
        chunk = os.read(descriptor, 65536)
        if not chunk:
            break
        *complete, pending = (pending + chunk).split(b"\n")
        lines += [line.decode(errors="replace") + "\n" for line in complete]
    return lines


class _Server:
    """A server block's mll_server, serving in its host's namespace until stopped."""

    def __init__(self, host: Host, step: Step):
        self.step = step
        self.process = host.start(
            ["bash", "-c", "exec " + step.block.code.strip()], stdout=subprocess.PIPE, stderr=subprocess.STDOUT
        )
        want = step.output.code.rstrip("\n").split("\n") if step.output else []
        try:
            printed = _read_lines(self.process, len(want), _SERVER_START_S)
            if step.output:
                _expect_output(step.block, step.output, "".join(printed))
        except BaseException:
            _end(self.process)
            raise

    def stop(self) -> None:
        """SIGTERM, as a supervisor or Ctrl-C would: it must exit 0."""
        self.process.send_signal(signal.SIGTERM)
        try:
            rest, _ = self.process.communicate(timeout=_SERVER_STOP_S)
        finally:
            _end(self.process)
        assert self.process.returncode == 0, (
            f"{self.step.block.id}: exited with {self.process.returncode} on SIGTERM:\n{rest.decode()[-3000:]}"
        )


def _run_block(host: Host, block: Block) -> str:
    if block.language == "python":
        argv = [sys.executable, "-c", block.code]
    else:
        argv = ["bash", "-e", "-o", "pipefail", "-c", block.code]
    result = host.run(argv)
    assert result.returncode == 0, (
        f"{block.id}: the {block.language} block exited with {result.returncode} on the {host.namespace} host\n"
        f"--- stdout\n{result.stdout[-3000:]}\n--- stderr\n{result.stderr[-3000:]}"
    )
    return result.stdout


def test_the_walkthrough_runs_across_two_hosts(hosts):
    if shutil.which("openssl") is None:
        pytest.skip("the page makes its certificate with openssl, which is not installed")
    if not _native.available():
        pytest.skip("the page shows the native transport, and libmll_native_stream.so is not built here")
    server = None
    try:
        for step in _steps():
            host = hosts[step.host]
            if step.serves:
                if server is not None:
                    server.stop()
                    server = None
                server = _Server(host, step)
                continue
            printed = _run_block(host, step.block)
            if step.output is not None:
                _expect_output(step.block, step.output, printed)
            if step.host == "server":
                for name in _copied():
                    if (host.workdir / name).exists():
                        shutil.copyfile(host.workdir / name, hosts["trainer"].workdir / name)
        assert server is not None
        server.stop()
        server = None
    finally:
        if server is not None:
            _end(server.process)


# --- The table of connection failures. ---


def _failure_rows() -> dict[str, str]:
    """The first column's ending -> its row, of the page's table."""
    rows = {}
    for line in _text().split("\n"):
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if len(cells) == 3 and (cells[1] == "at once" or cells[1].startswith("about ")):
            ending = re.match(r"`([^`]+)`", cells[0])
            rows[ending.group(1) if ending else cells[0].split(",")[0]] = line
    return rows


_TRY_TO_CONNECT = """
import sys
import multi_lunar_lander as mll

try:
    mll.vector_env(1, address=sys.argv[1])
except mll.MLLError as error:
    print(error)
else:
    raise SystemExit("connected")
"""


def _connect_failure(trainer: Host, address: str) -> str:
    result = trainer.run([sys.executable, "-c", _TRY_TO_CONNECT, address])
    assert result.returncode == 0, result.stdout + result.stderr
    return result.stdout.strip()


@contextlib.contextmanager
def _serving(host: Host, *flags: str):
    """mll_server with `flags` in `host`'s namespace, once it has said where it listens."""
    server = host.start(["mll_server", *flags], stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        printed = _read_lines(server, 1, _SERVER_START_S)
        assert printed and "listening on" in printed[0], f"mll_server {' '.join(flags)} printed {printed}"
        yield printed[0]
    finally:
        server.send_signal(signal.SIGTERM)
        try:
            server.communicate(timeout=_SERVER_STOP_S)
        finally:
            _end(server)


def _refused(hosts) -> str:
    """A server started without --address: it listens on its own host's loopback only."""
    with _serving(hosts["server"]) as listening:
        assert "listening on 127.0.0.1:50051 " in listening
        return _connect_failure(hosts["trainer"], ADDRESS)


def _no_host(hosts) -> str:
    return _connect_failure(hosts["trainer"], f"{NO_HOST_IP}:50051")


def _plaintext_to_tls(hosts) -> str:
    cert, key = self_signed(hosts["server"].workdir, "mll-server.test")
    with _serving(hosts["server"], f"--address={ADDRESS}", f"--tls_cert={cert}", f"--tls_key={key}"):
        return _connect_failure(hosts["trainer"], ADDRESS)


def _dropped(hosts) -> str:
    """Packets to DROPPED_IP reach the server's namespace (a static neighbour entry gives them
    its veth's MAC address), which does not hold that address and does not forward: dropped
    without an answer, as a firewall that drops would. (A new namespace takes its IPv4
    forwarding from the host's, which a container engine turns on; forwarding, the namespace
    would answer "host unreachable" once nothing answers its ARP for the address.)"""
    off = _run_checked("ip", "netns", "exec", hosts["server"].namespace, "sh", "-c",
                       "echo 0 > /proc/sys/net/ipv4/conf/all/forwarding")
    assert off.returncode == 0, off.stderr
    link = _run_checked("ip", "-n", hosts["server"].namespace, "-o", "link", "show", "mll-s")
    mac = re.search(r"link/ether ([0-9a-f:]{17})", link.stdout).group(1)
    added = _run_checked("ip", "-n", hosts["trainer"].namespace, "neigh", "replace", DROPPED_IP,
                         "lladdr", mac, "dev", "mll-t", "nud", "permanent")
    assert added.returncode == 0, added.stderr
    return _connect_failure(hosts["trainer"], f"{DROPPED_IP}:50051")


_FAILURES = {
    "Connection refused": _refused,
    "No route to host": _no_host,
    "Socket closed": _plaintext_to_tls,
    "(step timeout): Deadline Exceeded": _dropped,
}


def test_the_failure_table_has_a_case_for_each_row():
    assert set(_failure_rows()) == set(_FAILURES)


@pytest.mark.parametrize("ending", sorted(_FAILURES))
def test_each_connection_failure_ends_as_the_table_says(hosts, ending):
    message = _FAILURES[ending](hosts)
    code = "DEADLINE_EXCEEDED: " if "Deadline Exceeded" in ending else "UNAVAILABLE: mll_server at "
    assert message.startswith(code), message
    assert message.endswith(ending), f"the row `{ending}` got: {message}"
