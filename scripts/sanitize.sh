#!/usr/bin/env bash
# Builds the whole C++ tree (tests included, benchmarks off) with sanitizers
# into its own build directory and runs every ctest suite under them.
#
#   scripts/sanitize.sh asan   # AddressSanitizer + UndefinedBehaviorSanitizer -> build-asan/
#   scripts/sanitize.sh tsan   # ThreadSanitizer -> build-tsan/
#   scripts/sanitize.sh asan --build-only   # builds, runs nothing
#
# Any report fails the run: the sanitizers halt on the first error, and leaks
# are reported at exit. Suppressions live in scripts/sanitizer/*.supp,
# each entry with the reason it is there. Environment: JOBS (default nproc),
# CTEST_ARGS (extra ctest arguments, e.g. "-R reliability"), TSAN_DEPS_DIR
# (default build-tsan-deps).
#
# tsan first builds Debian's abseil, protobuf and gRPC with -fsanitize=thread
# (scripts/sanitizer/build_tsan_deps.sh, once) and runs the tests with those
# libraries first on LD_LIBRARY_PATH: without them TSan cannot see absl::Mutex
# (ours and gRPC's), protobuf's map fields change layout under TSan, and
# gRPC hands its call objects between threads through synchronization TSan
# cannot see.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
kind=${1:-asan}
case "$kind" in
  asan) sanitize="address,undefined"; BUILD_DIR=${BUILD_DIR:-build-asan} ;;
  tsan) sanitize="thread"; BUILD_DIR=${BUILD_DIR:-build-tsan} ;;
  *) echo "usage: $0 [asan|tsan] [--build-only]" >&2; exit 2 ;;
esac
case "${2:-}" in
  "") build_only=0 ;;
  "--build-only") build_only=1 ;;
  *) echo "usage: $0 [asan|tsan] [--build-only]" >&2; exit 2 ;;
esac
SUPP="$ROOT/scripts/sanitizer"

start=$(date +%s)
if [[ "$kind" == tsan ]]; then
  deps_lib=$(scripts/sanitizer/build_tsan_deps.sh "${TSAN_DEPS_DIR:-build-tsan-deps}" | tail -n 1)
fi
deps_built=$(date +%s)
# -O1 -g1 (line tables only): sanitizer reports keep file:line stacks, and the
# build takes about 40% less time than RelWithDebInfo's -O2 -g.
cmake -S . -B "$BUILD_DIR" -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo \
  -DCMAKE_CXX_FLAGS_RELWITHDEBINFO="-O1 -g1 -DNDEBUG" \
  -DMLL_SANITIZE="$sanitize" -DMLL_BUILD_TESTS=ON -DMLL_BUILD_BENCHMARKS=OFF >/dev/null
cmake --build "$BUILD_DIR" -j "${JOBS:-$(nproc)}"
built=$(date +%s)
if ((build_only)); then
  echo "sanitize.sh $kind: dependencies $((deps_built - start)) s, build $((built - deps_built)) s"
  exit 0
fi

# halt_on_error / abort_on_error: the first report ends the process with a
# failure that ctest sees. Stack-use-after-return and init-order checks catch
# more than the defaults at a small cost.
export ASAN_OPTIONS="halt_on_error=1:abort_on_error=1:detect_leaks=1:detect_stack_use_after_return=1:check_initialization_order=1:strict_init_order=1:suppressions=$SUPP/asan.supp"
export LSAN_OPTIONS="suppressions=$SUPP/lsan.supp:print_suppressions=0"
export UBSAN_OPTIONS="halt_on_error=1:print_stacktrace=1:suppressions=$SUPP/ubsan.supp"
# ignore_noninstrumented_modules: interceptors (memcpy, ...) called from
# uninstrumented Debian libraries (Cairo, c-ares, OpenSSL) record no
# accesses; see
# scripts/sanitizer/tsan.supp for why that is the narrow choice.
export TSAN_OPTIONS="halt_on_error=1:second_deadlock_stack=1:history_size=4:ignore_noninstrumented_modules=1:suppressions=$SUPP/tsan.supp"
if [[ "$kind" == tsan ]]; then
  export LD_LIBRARY_PATH="$deps_lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
  # The run means nothing if a test still loads Debian's uninstrumented copy.
  probe="$BUILD_DIR/tests/service/service_service_test"
  # ldd's output is taken whole first: with pipefail, grep -q quitting at
  # its first match can fail the pipe through ldd's SIGPIPE.
  loaded=$(ldd "$probe")
  for lib in libabsl_synchronization.so libprotobuf.so.32 libgpr.so.29 \
      libgrpc.so.29 libgrpc++.so.1.51; do
    if ! grep -q "$lib.* => $deps_lib/" <<<"$loaded"; then
      echo "sanitize.sh: $probe does not load $lib from $deps_lib" >&2
      exit 1
    fi
  done
fi
# Sanitized code runs several times slower: give timing-bound waits room.
export MLL_SANITIZER="$kind"

status=0
# client_cpp.consumer_package builds a project outside the tree against the
# installed library with plain flags: linking sanitized objects without the
# sanitizer runtime cannot work, so it only runs in the normal build.
# shellcheck disable=SC2086
ctest --test-dir "$BUILD_DIR" --output-on-failure -j "${JOBS:-$(nproc)}" \
  --timeout 1200 -E '^client_cpp\.consumer_package$' ${CTEST_ARGS:-} || status=$?
end=$(date +%s)
echo "sanitize.sh $kind: dependencies $((deps_built - start)) s," \
  "build $((built - deps_built)) s, tests $((end - built)) s," \
  "total $((end - start)) s, ctest exit $status"
exit $status
