#!/usr/bin/env bash
# Builds the libFuzzer targets with clang, ASan and UBSan into $BUILD_DIR and
# runs each for a bounded time on one core.
#
#   fuzz/run.sh [seconds per target, default 600] [targets..., default: core service]
#
# The targets run one after the other, or all at once with PARALLEL=1 (one
# process each: on a 2-core machine two targets finish in one target's time).
#
# The committed seeds (fuzz/corpus/<target>/) are read; new inputs go to
# $BUILD_DIR/corpus/<target>/ and crashes to $BUILD_DIR/artifacts/<target>/
# (BUILD_DIR defaults to build-fuzz).
# A crash input belongs in fuzz/regressions/<target>/, where
# tests/reliability/fuzz_regression_test.cc replays it in every test run.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
seconds=${1:-600}
shift || true
targets=("$@")
((${#targets[@]})) || targets=(core service)
BUILD_DIR=${BUILD_DIR:-build-fuzz}

CXX=${CXX:-clang++-14} CC=${CC:-clang-14} cmake -S . -B "$BUILD_DIR" -G Ninja \
  -DCMAKE_BUILD_TYPE=RelWithDebInfo -DMLL_BUILD_FUZZERS=ON \
  -DMLL_SANITIZE=address,undefined -DMLL_BUILD_TESTS=OFF \
  -DMLL_BUILD_BENCHMARKS=OFF >/dev/null
cmake --build "$BUILD_DIR" -j "${JOBS:-2}" --target "${targets[@]/%/_fuzzer}"

# Leaks are checked at exit by the regression test under scripts/sanitize.sh;
# here a leak report would only stop the run without an input to blame.
export ASAN_OPTIONS="detect_leaks=0:abort_on_error=1"
export UBSAN_OPTIONS="halt_on_error=1:print_stacktrace=1"
fuzz_one() {
  local target=$1
  local corpus="$BUILD_DIR/corpus/$target"
  local artifacts="$BUILD_DIR/artifacts/$target"
  mkdir -p "$corpus" "$artifacts"
  echo "== $target: $seconds s"
  # One process per target (libFuzzer's default, like -jobs=1 without the log
  # indirection): the machine's cores are shared.
  "$BUILD_DIR/fuzz/${target}_fuzzer" -max_total_time="$seconds" -max_len=4096 -timeout=30 -rss_limit_mb=4096 -print_final_stats=1 \
    -artifact_prefix="$artifacts/" "$corpus" "$ROOT/fuzz/corpus/$target" \
    >"$BUILD_DIR/$target.log" 2>&1 || true
  grep -E "^Done|stat::|==ERROR|SUMMARY|harness:" "$BUILD_DIR/$target.log" | sed "s/^/$target: /" || true
  if ls "$artifacts"/crash-* "$artifacts"/timeout-* "$artifacts"/oom-* >/dev/null 2>&1; then
    echo "== $target: findings in $artifacts"; return 1
  fi
}

status=0
if [ "${PARALLEL:-0}" = 1 ]; then
  pids=()
  for target in "${targets[@]}"; do fuzz_one "$target" & pids+=($!); done
  for pid in "${pids[@]}"; do wait "$pid" || status=1; done
else
  for target in "${targets[@]}"; do fuzz_one "$target" || status=1; done
fi
exit $status
