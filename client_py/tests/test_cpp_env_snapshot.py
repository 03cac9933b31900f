"""Env snapshots cross between the clients: a snapshot written by Python's vector_env restores in the
C++ VectorEnv and vice versa, and after the same steps both clients write the same bytes
(tests/client_cpp/env_snapshot_tool.cc drives the C++ side)."""

import os
import pathlib
import subprocess

import numpy as np
import pytest

import multi_lunar_lander as mll
from multi_lunar_lander._server import checkout_build_path

TOOL = pathlib.Path(
    os.environ.get("MLL_ENV_SNAPSHOT_TOOL_BIN") or checkout_build_path("tests", "client_cpp", "env_snapshot_tool")
)
pytestmark = pytest.mark.skipif(not TOOL.is_file(), reason=f"env_snapshot_tool is not built ({TOOL})")
N_LANDERS, MAX_CYCLES, SEED = 2, 30, 11
FIRST, MORE = 40, 25  # Steps before the snapshot is taken, and after it (auto-resets in both).


def _actions(t):
    """Step t's actions, as env_snapshot_tool gives them: lander a acts (t + a) % 4."""
    return np.array([[(t + a) % 4 for a in range(N_LANDERS)]], np.int32)


def _python_env(address):
    return mll.vector_env(1, address=address, n_landers=N_LANDERS, max_cycles=MAX_CYCLES)


def _fly(vector, first, steps):
    for t in range(first, first + steps):
        vector.step(_actions(t))


def _cpp(address, tmp_path, name, *start, first, steps):
    out = tmp_path / name
    done = subprocess.run(
        [
            str(TOOL), f"--address={address}", f"--n_landers={N_LANDERS}", f"--max_cycles={MAX_CYCLES}",
            *start, f"--first_step={first}", f"--steps={steps}", f"--out={out}",
        ],
        capture_output=True, text=True, timeout=120,
    )
    assert done.returncode == 0, done.stderr
    return out.read_bytes()


def test_snapshots_cross_between_python_and_cpp_to_the_same_bytes(address, tmp_path):
    with _python_env(address) as vector:
        vector.reset(seed=SEED)
        _fly(vector, 0, FIRST)
        python_first = vector.env_snapshot(0)
        _fly(vector, FIRST, MORE)
        python_last = vector.env_snapshot(0)
    # C++ from the seed writes Python's bytes.
    cpp_first = _cpp(address, tmp_path, "cpp_first", f"--seed={SEED}", first=0, steps=FIRST)
    assert cpp_first == python_first
    # Python's snapshot restored in C++, stepped on: Python's bytes again.
    (tmp_path / "python_first").write_bytes(python_first)
    restored_in_cpp = _cpp(
        address, tmp_path, "restored_in_cpp", f"--restore={tmp_path / 'python_first'}", first=FIRST, steps=MORE
    )
    assert restored_in_cpp == python_last
    # C++'s snapshot restored in Python, stepped on: the same.
    with _python_env(address) as vector:
        vector.reset(seed=SEED + 1)
        vector.restore_env(0, cpp_first)
        _fly(vector, FIRST, MORE)
        assert vector.env_snapshot(0) == python_last


def test_a_damaged_snapshot_from_python_is_refused_by_cpp(address, tmp_path):
    with _python_env(address) as vector:
        vector.reset(seed=SEED)
        _fly(vector, 0, 5)
        snapshot = bytearray(vector.env_snapshot(0))
    snapshot[len(snapshot) // 2] ^= 0x10
    (tmp_path / "damaged").write_bytes(bytes(snapshot))
    done = subprocess.run(
        [
            str(TOOL), f"--address={address}", f"--n_landers={N_LANDERS}", f"--max_cycles={MAX_CYCLES}",
            f"--restore={tmp_path / 'damaged'}", "--first_step=5", "--steps=1", f"--out={tmp_path / 'out'}",
        ],
        capture_output=True, text=True, timeout=120,
    )
    assert done.returncode == 1
    assert "INVALID_ARGUMENT: snapshot is damaged: its CRC-32" in done.stderr
