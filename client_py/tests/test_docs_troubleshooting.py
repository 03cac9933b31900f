"""docs/troubleshooting.md shows the messages the code gives: every ```text block marked
`<!-- message: KEY -->` is compared with the message that the failure KEY produces here, made to
happen against a real mll_server (or, for the client's own checks, by the real client code). In
a shown message "..." stands for any text, and 127.0.0.1:50051 for the address of the server
the test started. Every marked block has a failure below, and every failure below a block."""

from __future__ import annotations

import os
import pathlib
import re
import signal
import subprocess
import sys
import sysconfig
import time

import grpc
import pytest

import multi_lunar_lander as mll
from multi_lunar_lander import _server, _server_info
from multi_lunar_lander._stubs import pb, pb_grpc

from mll_test_helpers import wait_draining

_DOC = pathlib.Path(__file__).resolve().parents[2] / "docs" / "troubleshooting.md"
_SHOWN_ADDRESS = "127.0.0.1:50051"
_BLOCK = re.compile(r"^<!--\s*message:\s*([\w-]+)\s*-->\n```text\n(.*?)\n```", re.MULTILINE | re.DOTALL)
_SERVER_NAME = "mll-server.test"
_TOKEN = "token-troubleshooting-1"


def _shown() -> dict[str, str]:
    text = _DOC.read_text(encoding="utf-8")
    found = {}
    for key, message in _BLOCK.findall(text):
        assert key not in found, f"docs/troubleshooting.md marks two messages '{key}'"
        found[key] = message
    return found


def _message(call, *args, **kwargs) -> str:
    try:
        call(*args, **kwargs)
    except mll.MLLError as error:
        return str(error)
    raise AssertionError(f"{call} raised no MLLError")


def _raw(address: str, method: str, request) -> str:
    """The `CODE: message` of a call made with a plain stub (no client code in between)."""
    with grpc.insecure_channel(address) as channel:
        try:
            getattr(pb_grpc.MultiLunarLanderStub(channel), method)(request, timeout=30)
        except grpc.RpcError as error:
            return f"{error.code().name}: {error.details()}"
    raise AssertionError(f"{method} succeeded")


def _certificate(directory: pathlib.Path):
    if subprocess.run(["which", "openssl"], capture_output=True).returncode != 0:
        pytest.skip("openssl is not installed")
    cert, key = directory / "server.crt", directory / "server.key"
    subprocess.run(
        ["openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
         "-days", "1", "-subj", f"/CN={_SERVER_NAME}", "-addext", f"subjectAltName=DNS:{_SERVER_NAME}",
         "-keyout", str(key), "-out", str(cert)],
        check=True, capture_output=True, timeout=60,
    )
    return cert, key


# --- The failures: each returns (message, address of the server it used or None). ---


def refused(tmp_path):
    with mll.ServerProcess(threads=1) as process:
        address = process.address
    # The server has stopped: nothing listens at its address now.
    return _message(mll.parallel_env, address=address), address


def plaintext_to_tls(tmp_path):
    cert, key = _certificate(tmp_path)
    with mll.ServerProcess(threads=1, extra_args=(f"--tls_cert={cert}", f"--tls_key={key}"),
                           tls_root_cert=str(cert), tls_server_name=_SERVER_NAME) as process:
        return _message(mll.parallel_env, address=process.address), process.address


def tls_name(tmp_path):
    cert, key = _certificate(tmp_path)
    with mll.ServerProcess(threads=1, extra_args=(f"--tls_cert={cert}", f"--tls_key={key}"),
                           tls_root_cert=str(cert), tls_server_name=_SERVER_NAME) as process:
        return _message(mll.parallel_env, address=process.address, tls_root_cert=str(cert)), process.address


def tls_to_plaintext(tmp_path):
    cert, _ = _certificate(tmp_path)
    with mll.ServerProcess(threads=1) as process:
        message = _message(mll.parallel_env, address=process.address, tls_root_cert=str(cert),
                           tls_server_name=_SERVER_NAME)
        return message, process.address


def _token_server(tmp_path, *flags):
    tokens = tmp_path / "tokens.txt"
    tokens.write_text(f"{_TOKEN}\n")
    return mll.ServerProcess(threads=1, extra_args=(f"--auth_token_file={tokens}", *flags))


def no_token(tmp_path):
    with _token_server(tmp_path) as process:
        return _message(mll.parallel_env, address=process.address, token=""), process.address


def wrong_token(tmp_path):
    with _token_server(tmp_path) as process:
        return _message(mll.parallel_env, address=process.address, token="not-the-token"), process.address


def quota(tmp_path):
    with _token_server(tmp_path, "--max_envs_per_token=1") as process:
        env = mll.parallel_env(address=process.address, token=_TOKEN)
        try:
            return _message(mll.parallel_env, address=process.address, token=_TOKEN), process.address
        finally:
            env.close()


def draining(tmp_path):
    with mll.ServerProcess(threads=1, extra_args=("--drain_s=30",)) as process:
        env = mll.parallel_env(address=process.address, failover=False)
        env.reset(seed=0)  # An environment keeps the drain going.
        os.kill(process.pid, signal.SIGTERM)
        wait_draining(process.address)
        message = _message(mll.parallel_env, address=process.address)
        env.close()
        return message, process.address


def protocol(tmp_path):
    info = mll.ServerInfo("9.0.0", (mll.PROTOCOL[0] + 1, 0), frozenset(), mll.ServerLimits())
    return _message(_server_info.check_compatible, info, _SHOWN_ADDRESS), None


def no_server_binary(tmp_path, monkeypatch):
    monkeypatch.delenv(_server.SERVER_BIN_ENV, raising=False)
    monkeypatch.setenv("PATH", str(tmp_path))
    monkeypatch.setattr(sysconfig, "get_path", lambda name, *args, **kwargs: str(tmp_path))
    monkeypatch.setattr(_server, "_CHECKOUT_BUILD_BIN", tmp_path / "build" / "mll_server")
    monkeypatch.setattr(_server, "_WHEEL_BIN", tmp_path / "wheel" / "mll_server", raising=False)
    return _message(mll.find_server_binary), None


def bad_server_binary(tmp_path, monkeypatch):
    monkeypatch.setenv(_server.SERVER_BIN_ENV, "/nonexistent/mll_server")
    return _message(mll.find_server_binary), None


def port_in_use(tmp_path):
    with mll.ServerProcess(threads=1) as process:
        second = subprocess.run(
            [mll.find_server_binary(), f"--address={process.address}"], capture_output=True, text=True, timeout=30
        )
        assert second.returncode == 1, second
        return second.stderr.strip().split("\n")[-1], process.address


def option_range(tmp_path, address):
    return _message(mll.parallel_env, address=address, n_landers=40), address


def max_envs(tmp_path):
    with mll.ServerProcess(threads=1, max_envs=1) as process:
        env = mll.parallel_env(address=process.address)
        try:
            return _message(mll.parallel_env, address=process.address), process.address
        finally:
            env.close()


def shared_memory_off(tmp_path):
    with mll.ServerProcess(threads=1, extra_args=("--shared_memory_sessions=0",)) as process:
        return _message(mll.vector_env, 2, address=process.address, transport="shared_memory"), process.address


def no_native_library(tmp_path):
    code = (
        "import multi_lunar_lander as mll, sys\n"
        "try:\n"
        "    mll.vector_env(1, address=sys.argv[1])\n"
        "except mll.MLLError as error:\n"
        "    print(str(error))\n"
    )
    with mll.ServerProcess(threads=1) as process:
        # A library path that does not exist, and no build tree nor package copy to fall back to.
        env = dict(os.environ, MLL_NATIVE_LIBRARY=str(tmp_path / "libmll_native_stream.so"))
        result = subprocess.run([sys.executable, "-c", code, process.address], capture_output=True, text=True,
                                timeout=60, env=env)
        return result.stdout.strip(), process.address


def step_before_reset(tmp_path, address):
    env = mll.parallel_env(address=address, n_landers=2)
    try:
        return _message(env.step, {"lander_0": 0, "lander_1": 0}), address
    finally:
        env.close()


def episode_over(tmp_path, address):
    with grpc.insecure_channel(address) as channel:
        stub = pb_grpc.MultiLunarLanderStub(channel)
        config = pb.EnvConfig(n_landers=1)
        env = stub.CreateEnv(pb.CreateEnvRequest(config=config))
        stub.ResetEnv(pb.ResetEnvRequest(name=env.name, seed=0))
        request = pb.StepEnvRequest(name=env.name)
        request.actions.dtype = pb.DTYPE_INT32
        request.actions.shape.append(1)
        request.actions.data = (0).to_bytes(4, "little")
        for _ in range(2000):  # A lander doing nothing falls and crashes long before.
            response = stub.StepEnv(request)
            if response.data.episode_over:
                break
        assert response.data.episode_over
    return _raw(address, "StepEnv", request), address


def _step_message(address, actions):
    """The message of a parallel env's step with `actions` right after its reset."""
    env = mll.parallel_env(address=address, n_landers=2)
    env.reset(seed=0)
    try:
        return _message(env.step, actions), address
    finally:
        env.close()


def action_range(tmp_path, address):
    return _step_message(address, {"lander_0": 7, "lander_1": 0})


def action_type(tmp_path, address):
    return _step_message(address, {"lander_0": 0.5, "lander_1": 0})


def reclaimed(tmp_path):
    with mll.ServerProcess(threads=1, idle_timeout_s=0.5) as process:
        with grpc.insecure_channel(process.address) as channel:
            stub = pb_grpc.MultiLunarLanderStub(channel)
            name = stub.CreateEnv(pb.CreateEnvRequest()).name
            deadline = time.monotonic() + 30
            # ListEnvs does not touch the environments it lists: wait until it no longer lists it.
            while stub.ListEnvs(pb.ListEnvsRequest()).envs and time.monotonic() < deadline:
                time.sleep(0.05)
        return _raw(process.address, "GetEnv", pb.GetEnvRequest(name=name)), process.address


def not_found(tmp_path, address):
    with grpc.insecure_channel(address) as channel:
        stub = pb_grpc.MultiLunarLanderStub(channel)
        name = stub.CreateEnv(pb.CreateEnvRequest()).name
        stub.DeleteEnv(pb.DeleteEnvRequest(name=name))
    return _raw(address, "GetEnv", pb.GetEnvRequest(name=name)), address


def message_size(tmp_path):
    with mll.ServerProcess(threads=1, extra_args=("--max_message_mb=1",)) as process:
        request = pb.KeepAliveRequest(names=["envs/" + "0" * 300] * 5000)  # About 1.5 MB.
        return _raw(process.address, "KeepAlive", request), process.address


def not_recreatable(tmp_path, address):
    vector = mll.vector_env(1, address=address)  # Never reset.
    snapshot = vector.env_snapshot
    try:
        return _message(snapshot, 0), address
    finally:
        vector.close()


_FAILURES = {
    "refused": refused, "plaintext-to-tls": plaintext_to_tls, "tls-name": tls_name,
    "tls-to-plaintext": tls_to_plaintext, "no-token": no_token, "wrong-token": wrong_token, "quota": quota,
    "draining": draining, "protocol": protocol, "no-server-binary": no_server_binary,
    "bad-server-binary": bad_server_binary, "port-in-use": port_in_use, "option-range": option_range,
    "max-envs": max_envs, "shared-memory-off": shared_memory_off, "no-native-library": no_native_library,
    "step-before-reset": step_before_reset, "episode-over": episode_over, "action-range": action_range,
    "action-type": action_type, "reclaimed": reclaimed, "not-found": not_found, "message-size": message_size,
    "not-recreatable": not_recreatable,
}


def test_every_shown_message_has_a_failure_and_every_failure_a_message():
    shown = _shown()
    assert set(shown) == set(_FAILURES), (
        f"shown without a failure here: {sorted(set(shown) - set(_FAILURES))}; "
        f"failures not shown: {sorted(set(_FAILURES) - set(shown))}"
    )


def _matches(shown: str, actual: str, address: str | None) -> bool:
    if address:
        actual = actual.replace(address, _SHOWN_ADDRESS)
    pattern = ".*".join(re.escape(part) for part in shown.split("..."))
    return re.fullmatch(pattern, actual, re.DOTALL) is not None


def test_matching():
    assert _matches("A: x ... y", "A: x 1 2 y", None)
    assert not _matches("A: x ... y", "A: x 1 2 z", None)
    assert _matches("at 127.0.0.1:50051...", "at 127.0.0.1:4242 now", "127.0.0.1:4242")


@pytest.mark.parametrize("key", sorted(_FAILURES))
def test_the_message_is_the_codes(key, tmp_path, monkeypatch, request):
    failure = _FAILURES[key]
    names = failure.__code__.co_varnames[: failure.__code__.co_argcount]
    kwargs = {"monkeypatch": monkeypatch} if "monkeypatch" in names else {}
    if "address" in names:
        kwargs["address"] = request.getfixturevalue("address")
    monkeypatch.delenv(mll.TOKEN_ENV, raising=False)
    actual, address = failure(tmp_path, **kwargs)
    shown = _shown()[key]
    assert _matches(shown, actual, address), f"docs/troubleshooting.md shows\n  {shown}\nthe code gives\n  {actual}"
