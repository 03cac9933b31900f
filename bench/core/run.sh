#!/usr/bin/env bash
# Builds and runs the core benchmarks and prints their rows of the table in
# docs/benchmarks.md (run A), in the table's format, with the machine's load.
#   bench/core/run.sh                 # BUILD_DIR=build, 5 repetitions
#   BUILD_DIR=build-x REPETITIONS=3 bench/core/run.sh
set -euo pipefail
cd "$(dirname "$0")/../.."
BUILD_DIR=${BUILD_DIR:-build}
REPETITIONS=${REPETITIONS:-5}
cmake -S . -B "$BUILD_DIR" -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo >/dev/null
cmake --build "$BUILD_DIR" --target core_bench -j "${JOBS:-$(nproc)}"
OUT="$BUILD_DIR/bench/core/core_bench.json"
# Repetitions are interleaved at random so that a load spike from elsewhere
# hits the Env and its floor alike; the table uses medians of CPU time.
"$BUILD_DIR/bench/core/core_bench" \
  --benchmark_repetitions="$REPETITIONS" \
  --benchmark_enable_random_interleaving=true \
  --benchmark_report_aggregates_only=true \
  --benchmark_out="$OUT" --benchmark_out_format=json >/dev/null
python3 bench/core/report.py "$OUT"
