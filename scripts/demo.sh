#!/usr/bin/env bash
# The main job: installs what is missing, builds, and flies landers with the
# heuristic pilot, printing one JSON line per episode and writing frames.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
scripts/build.sh
OUT=${OUT:-out}
mkdir -p "$OUT/frames"
./build/server/core/mll_rollout --n_landers=3 --episodes=3 --seed=0 --policy=heuristic \
  --frames_dir="$OUT/frames" --render_mode=rgb_array
echo "frames written to $OUT/frames"
