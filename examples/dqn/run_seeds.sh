#!/usr/bin/env bash
# The per-seed results of docs/dqn.md in one command: trains the default
# preset on each seed, one run at a time (one torch/BLAS thread, the other
# core for the server), exports each run's greedy network (the last or the
# best-mean one, whichever lands more often on 20 selection episodes),
# evaluates it on 100 episodes, and writes the per-seed table and the plot of
# mean and spread across seeds.
#   examples/dqn/run_seeds.sh [out_dir] [first_seed] [last_seed] [extra train flags...]
# Defaults: runs/seeds, seeds 0 to 9. A seed whose run finished is not rerun;
# an interrupted one resumes from its last checkpoint. Uses the embedded
# server (MLL_SERVER_BIN, else build/server/service/mll_server) unless
# MLL_ADDRESS is set.
set -euo pipefail
cd "$(dirname "$0")"
out=${1:-runs/seeds}
first=${2:-0}
last=${3:-9}
shift $(( $# > 3 ? 3 : $# ))
export OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1
py=../../.venv/bin/python
address=()
[ -n "${MLL_ADDRESS:-}" ] && address=(--address "$MLL_ADDRESS")
mkdir -p "$out"
runs=()
for seed in $(seq "$first" "$last"); do
  run="$out/seed$seed"
  runs+=("$run")
  if [ ! -f "$run/eval.json" ]; then
    $py -m mll_dqn train --preset default --seed "$seed" --out "$run" --resume \
      --no-progress "${address[@]}" "$@" > "$run.log" 2>&1 || { cat "$run.log"; exit 1; }
    $py -m mll_dqn export "$run/checkpoint.pt" "$run/best.pt" --episodes 20 \
      --out "$run/trained.qnet" "${address[@]}" > "$run/export.json"
    $py -m mll_dqn evaluate --policy trained --weights "$run/trained.qnet" \
      --json "$run/eval.json" "${address[@]}" > /dev/null
  fi
  echo "seed $seed: $($py -m mll_dqn summary "$run" | tail -n 1)"
done
$py -m mll_dqn report "${runs[@]}" --out "$out"
