"""The embedded default (address=None): one shared, reference-counted server per process that
stops with its last user, at interpreter exit, and with a killed parent."""

import gc
import os
import signal
import subprocess
import sys
import time

import grpc
import pytest

import multi_lunar_lander as mll
from multi_lunar_lander import _server


def _gone(pid, timeout_s=10.0):
    """True once `pid` no longer exists: exited AND reaped (a zombie still answers kill(0), so
    a child we forgot to wait for fails this; an orphan is reaped by init)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        time.sleep(0.02)
    return False


def test_shared_server_starts_with_the_first_env_and_stops_with_the_last():
    gc.collect()  # Envs other tests dropped without close() release their lease here.
    assert mll.embedded_server() is None
    first = mll.env(n_landers=1)
    server = mll.embedded_server()
    assert server is not None and server.running
    second = mll.parallel_env(continuous=True)
    assert mll.embedded_server() is server and second.address == first.address == server.address
    second.reset(seed=1)
    first.close()
    assert server.running  # Still leased by `second`.
    second.close()
    assert not server.running and mll.embedded_server() is None
    assert _gone(server.pid)


def test_garbage_collected_env_releases_the_server():
    env = mll.parallel_env()
    server = mll.embedded_server()
    del env
    gc.collect()
    assert not server.running and mll.embedded_server() is None


_CHILD = """
import multi_lunar_lander as mll, os, sys, time
env = mll.parallel_env()
env.reset(seed=0)
print(mll.embedded_server().pid, flush=True)
if sys.argv[1] == "hang":
    time.sleep(60)
"""


def test_no_server_left_after_interpreter_exit_without_close():
    child = subprocess.run(
        [sys.executable, "-c", _CHILD, "exit"], capture_output=True, text=True, timeout=60, check=True
    )
    assert _gone(int(child.stdout.split()[0]))


def test_no_server_left_after_the_parent_is_killed():
    child = subprocess.Popen([sys.executable, "-c", _CHILD, "hang"], stdout=subprocess.PIPE, text=True)
    try:
        server_pid = int(child.stdout.readline())
        os.kill(server_pid, 0)  # Running.
        child.send_signal(signal.SIGKILL)
        child.wait(timeout=10)
        assert _gone(server_pid)
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()


def _no_server_anywhere(monkeypatch, tmp_path):
    """Hides every mll_server find_server_binary could use; returns the empty scripts dir."""
    scripts = tmp_path / "venv_bin"
    scripts.mkdir()
    monkeypatch.delenv("MLL_SERVER_BIN", raising=False)
    monkeypatch.setenv("PATH", str(tmp_path))
    monkeypatch.setattr(_server.sysconfig, "get_path", lambda name, *a, **k: str(scripts))
    monkeypatch.setattr(_server, "_CHECKOUT_BUILD_BIN", tmp_path / "build" / "mll_server")
    return scripts


def test_a_bad_server_bin_variable_is_named(monkeypatch, tmp_path):
    monkeypatch.setenv("MLL_SERVER_BIN", str(tmp_path / "no_such_server"))
    with pytest.raises(mll.MLLError) as caught:
        mll.env()
    assert caught.value.code == grpc.StatusCode.UNAVAILABLE
    assert f"$MLL_SERVER_BIN={tmp_path / 'no_such_server'} is not an executable file" in caught.value.message
    assert mll.embedded_server() is None


def test_missing_binary_says_how_to_install_it(monkeypatch, tmp_path):
    scripts = _no_server_anywhere(monkeypatch, tmp_path)
    with pytest.raises(mll.MLLError) as caught:
        mll.env()
    message = caught.value.message
    assert caught.value.code == grpc.StatusCode.UNAVAILABLE
    assert str(scripts) in message and "PATH" in message and "MLL_SERVER_BIN" in message
    assert "pip install ." in message and "address=" in message
    assert "build" not in message  # No path inside a repository the user may not have.
    assert mll.embedded_server() is None


def test_the_server_installed_beside_python_is_found_off_path(monkeypatch, tmp_path):
    scripts = _no_server_anywhere(monkeypatch, tmp_path)
    installed = scripts / "mll_server"
    installed.write_text("#!/bin/sh\nexit 0\n")
    installed.chmod(0o755)
    assert mll.find_server_binary() == str(installed)
