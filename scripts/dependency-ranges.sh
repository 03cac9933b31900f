#!/usr/bin/env bash
# The Python client at both ends of the dependency ranges it declares (pyproject.toml and
# client_py/pyproject.toml): builds the client's wheel once, as pip builds it for a user
# (isolated, with the grpcio-tools the build pins), then installs it into two fresh venvs of
# Debian's Python without the system's site packages:
#   .venv-floor   exactly the declared floors (client_py/constraints-floor.txt), extras
#                 render and test included;
#   .venv-newest  the newest releases of everything;
# and runs the smoke subset (client_py/tests/test_dependency_smoke.py: import, parallel_env,
# vector_env, gym_vector_env, PettingZoo's api_test and parallel_api_test, the render extra) and
# the stub import errors (client_py/tests/test_dependency_stubs.py) in each, against this
# checkout's mll_server on loopback. The floor venv then takes gymnasium 1.0.0, gym_vector_env's
# own floor, and runs its test again. CI runs it after the full suite (.ci/run).
#
# Environment: PYTHON (default /usr/bin/python3), MLL_SERVER_BIN (default build/'s server),
# MLL_NATIVE_LIBRARY (default build/'s libmll_native_stream.so, which vector_env needs).
# pip's downloads come from its cache (~/.cache/pip) after the first run.
set -euo pipefail
cd "$(dirname "$0")/.."
root=$PWD
python=${PYTHON:-/usr/bin/python3}
server=${MLL_SERVER_BIN:-$root/build/server/service/mll_server}
# The pure-Python wheel has no native library, which vector_env needs: the build's.
library=${MLL_NATIVE_LIBRARY:-$root/build/client_cpp/libmll_native_stream.so}
for built in "$server" "$library"; do
  if [ ! -e "$built" ]; then
    echo "dependency-ranges: no $built; build it first (scripts/build.sh)" >&2
    exit 1
  fi
done
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
start=$SECONDS
say() { echo "== dependency-ranges ($((SECONDS - start)) s): $*"; }

fresh_venv() {  # fresh_venv NAME: prints the python of a new .venv-NAME
  rm -rf "$root/.venv-$1"
  "$python" -m venv "$root/.venv-$1"
  echo "$root/.venv-$1/bin/python"
}
pip_install() {  # pip_install PYTHON ARGS...: wheels only, so a release that needs a compiler fails
  local venv_python=$1
  shift
  "$venv_python" -m pip install -q --disable-pip-version-check --only-binary=:all: "$@"
}
versions() {  # versions PYTHON: the client's direct dependencies as installed
  "$1" -m pip freeze | grep -iE '^(grpcio|grpcio-health-checking|protobuf|numpy|gymnasium|pettingzoo)==' | tr '\n' ' '
}
smoke() {  # smoke PYTHON [VAR=VALUE...] [-- PYTEST ARGS...]: the two test files, from an empty folder
  local venv_python=$1
  shift
  local -a vars=() args=()
  while (($#)) && [ "$1" != "--" ]; do vars+=("$1"); shift; done
  (($#)) && shift
  args=("$@")
  (cd "$work" && env MLL_SERVER_BIN="$server" MLL_NATIVE_LIBRARY="$library" MLL_EXPECT_INSTALLED=1 "${vars[@]}" \
    "$venv_python" -m pytest -q -p no:cacheprovider --disable-warnings "${args[@]}" \
    "$root/client_py/tests/test_dependency_smoke.py" "$root/client_py/tests/test_dependency_stubs.py")
}

say "the client's wheel, built with $("$python" --version)"
floor=$(fresh_venv floor)
"$floor" -m pip wheel -q --disable-pip-version-check --no-deps -w "$work/wheel" ./client_py
wheel=$(ls "$work"/wheel/multi_lunar_lander-*.whl)

say "newest: installing"
newest=$(fresh_venv newest)
pip_install "$newest" "$wheel[render,test]"
"$newest" -m pip check
say "newest: $(versions "$newest")"
smoke "$newest"

say "stubs of the newest grpcio-tools (for the floor's import error)"
pip_install "$newest" grpcio-tools
"$newest" client_py/generate_stubs.py proto "$work/newest_stubs"

say "floor: installing"
pip_install "$floor" -c client_py/constraints-floor.txt "$wheel[render,test]"
"$floor" -m pip check
say "floor: $(versions "$floor")"
smoke "$floor" MLL_EXPECT_CONSTRAINTS="$root/client_py/constraints-floor.txt" MLL_NEWEST_STUBS="$work/newest_stubs"

say "floor with gymnasium 1.0.0 (gym_vector_env's floor)"
pip_install "$floor" gymnasium==1.0.0
"$floor" -m pip check
smoke "$floor" -- -k gym_vector

say "done"
