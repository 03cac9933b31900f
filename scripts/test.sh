#!/usr/bin/env bash
# Runs every test: installs what is missing, lints, builds, then the C++
# suites (ctest), the Python suites (pytest), and the binary wheel built from
# that build and installed on a clean Debian 12 (scripts/wheel.sh and
# scripts/wheel-test.sh, as root or through sudo). Exit code non-zero on any
# failure. CI passes CMAKE_ARGS=-DMLL_WERROR=ON so that a warning fails too.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO=sudo
# The wheel test's Debian root file system is made meanwhile (debootstrap downloads and unpacks;
# it hardly competes with the compiler), unless its cache has it already.
rootfs_log=$(mktemp)
$SUDO scripts/wheel-test.sh --rootfs-only >"$rootfs_log" 2>&1 &
rootfs_pid=$!
echo "== lint: ruff (Python), clang-format (every tracked C and C++ file, .clang-format)"
.venv/bin/ruff check client_py examples bench
git ls-files -z '*.h' '*.cc' '*.c' | xargs -0 clang-format --dry-run --Werror
scripts/build.sh
echo "== C++ tests (ctest)"
ctest --test-dir "${BUILD_DIR:-build}" --output-on-failure -j "$(nproc)" --timeout 600
if ls client_py/tests/*.py examples/dqn/tests/*.py examples/tests/*.py >/dev/null 2>&1; then
  # On PYTEST_WORKERS processes (default 2; pytest-xdist): most tests wait on servers, and
  # `pip install .`'s test compiles for minutes beside the others.
  echo "== Python tests (pytest)"
  export MLL_SERVER_BIN="$PWD/${BUILD_DIR:-build}/server/service/mll_server"
  .venv/bin/python -m pytest -q -n "${PYTEST_WORKERS:-2}" --durations=15 $(ls -d client_py/tests examples/dqn/tests examples/tests 2>/dev/null)
fi
echo "== the binary wheel (scripts/wheel.sh), installed and run on a clean Debian 12 (scripts/wheel-test.sh)"
scripts/wheel.sh
wait "$rootfs_pid" || { cat "$rootfs_log"; echo "the wheel test's root file system could not be made (above)" >&2; exit 1; }
cat "$rootfs_log"
$SUDO scripts/wheel-test.sh
