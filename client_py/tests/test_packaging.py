"""The two ways users install the package from source, each into a fresh venv from a fresh clone
of this repository's committed HEAD (so run it on committed work); the binary wheel, the third,
is installed and run on a clean Debian by scripts/wheel-test.sh:

- `pip install .` at the top builds the C++ server and CLI and installs them with the client:
  `mll_server` and `mll_cli` land in the venv's bin/, the native stream library beside the
  package, and an embedded environment (address=None) steps from any directory without
  $MLL_SERVER_BIN or the venv on PATH, a vector env over the native library;
- `pip install ./client_py` installs the pure-Python client: stubs generated at build time,
  py.typed, license metadata, and no server or native library.
"""

from __future__ import annotations

import os
import pathlib
import shutil
import subprocess

import pytest

REPO = pathlib.Path(__file__).resolve().parents[2]

# Installs take minutes (the server's C++ build); their output goes to the failure message.
INSTALL_TIMEOUT_S = 1500

_STEP_AN_EMBEDDED_ENV = """
import os, shutil, sys
import multi_lunar_lander as mll
assert "MLL_SERVER_BIN" not in os.environ and shutil.which("mll_server") is None
env = mll.parallel_env(n_landers=2)
observations, infos = env.reset(seed=0)
for _ in range(20):
    observations, rewards, terminations, truncations, infos = env.step(
        {agent: mll.heuristic(observations[agent]) for agent in env.agents})
print("binary", mll.embedded_server().binary)
env.close()
vector = mll.vector_env(2, n_landers=1, transport="native")
vector.reset(seed=0)
vector.step([[0], [1]])
print("native", mll._native._load()[0]._name)
vector.close()
"""


def _run(command, cwd, env=None):
    result = subprocess.run(
        command, cwd=cwd, env=env, capture_output=True, text=True, timeout=INSTALL_TIMEOUT_S
    )
    assert result.returncode == 0, (
        f"{' '.join(map(str, command))} exited {result.returncode}\n"
        f"stdout:\n{result.stdout[-4000:]}\nstderr:\n{result.stderr[-4000:]}"
    )
    return result.stdout


@pytest.fixture(scope="module")
def fresh_clone(tmp_path_factory):
    if shutil.which("git") is None or not (REPO / ".git").exists():
        pytest.skip("needs a git checkout of the repository")
    clone = tmp_path_factory.mktemp("clone") / "multi_lunar_lander"
    _run(["git", "clone", "--quiet", "--depth", "1", f"file://{REPO}", str(clone)], cwd=REPO)
    return clone


def _fresh_venv(path: pathlib.Path) -> pathlib.Path:
    # Debian's interpreter with its site packages, as the README's setup makes the project venv.
    _run(["/usr/bin/python3", "-m", "venv", "--system-site-packages", str(path)], cwd=path.parent)
    return path / "bin" / "python"


# What would make the fresh venv find this checkout's package, server or native library.
_NOT_PASSED = ("MLL_SERVER_BIN", "MLL_NATIVE_LIBRARY", "VIRTUAL_ENV", "PYTHONPATH")


def _isolated_env() -> dict:
    env = {key: value for key, value in os.environ.items() if key not in _NOT_PASSED}
    env["PATH"] = "/usr/bin:/bin"
    return env


def test_pip_install_dot_brings_the_server_and_the_cli(fresh_clone, tmp_path):
    python = _fresh_venv(tmp_path / "venv")
    _run([python, "-m", "pip", "install", "--quiet", str(fresh_clone)], cwd=tmp_path, env=_isolated_env())
    bin_dir = python.parent
    for program in ("mll_server", "mll_cli"):
        assert os.access(bin_dir / program, os.X_OK), f"{program} is not in {bin_dir}"
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    out = _run([python, "-c", _STEP_AN_EMBEDDED_ENV], cwd=elsewhere, env=_isolated_env())
    assert f"binary {bin_dir / 'mll_server'}" in out
    package = pathlib.Path(_run([python, "-c", "import multi_lunar_lander as m; print(m.__file__)"],
                                cwd=elsewhere, env=_isolated_env()).strip()).parent
    assert f"native {package / 'libmll_native_stream.so'}" in out
    # The stubs of the grpcio-tools the build pins for Python 3.11 (client_py/tests/test_dependency_ranges.py).
    assert "# Protobuf Python Version: 4.25.1" in (package / "_proto" / "multi_lunar_lander_pb2.py").read_text()


def test_pip_install_client_py_is_the_pure_python_client(fresh_clone, tmp_path):
    python = _fresh_venv(tmp_path / "venv")
    _run(
        [python, "-m", "pip", "install", "--quiet", str(fresh_clone / "client_py")],
        cwd=tmp_path,
        env=_isolated_env(),
    )
    assert not (python.parent / "mll_server").exists()
    probe = (
        "import importlib.metadata as m, pathlib, multi_lunar_lander as mll\n"
        "from multi_lunar_lander._stubs import pb\n"
        "package = pathlib.Path(mll.__file__).parent\n"
        "print('typed', (package / 'py.typed').exists())\n"
        "print('stubs', (package / '_proto' / 'multi_lunar_lander_pb2.py').exists())\n"
        "print('license', m.metadata('multi_lunar_lander')['License-Expression'])\n"
        "print('location', package)\n"
        "print('native', mll._native.available())\n"
        "try:\n"
        "    mll.vector_env(1, address='127.0.0.1:1')\n"
        "except mll.MLLError as error:\n"
        "    print('vector_env', error.code.name, 'binary wheel' in error.message)\n"
        "stubs = (package / '_proto' / 'multi_lunar_lander_pb2.py').read_text()\n"
        "print('gencode', stubs.split('Protobuf Python Version: ')[1].split()[0])\n"
    )
    out = _run([python, "-c", probe], cwd=tmp_path, env=_isolated_env())
    assert "typed True" in out and "stubs True" in out and "license MIT" in out
    # Generated by the grpcio-tools the build pins for Debian 12's Python 3.11 (1.62.3), not the
    # newest: they run on protobuf >= 4.25.1 (client_py/tests/test_dependency_ranges.py).
    assert "gencode 4.25.1" in out, out
    assert "native False" in out  # No library: env and parallel_env only; vector_env says how to get it.
    assert "vector_env FAILED_PRECONDITION True" in out
    assert str(fresh_clone) not in out  # Installed, not imported from the clone.
