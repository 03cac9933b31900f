#!/usr/bin/env bash
# The full experiment of docs/dqn.md: trains one preset for 1000 episodes,
# evaluates the greedy policy (last and best network) and the two baselines
# (heuristic pilot, random actions) on 100 episodes each, draws figure 2 and a
# GIF of a greedy episode.
#   examples/dqn/run_experiment.sh [preset] [out_dir] [extra train flags...]
# Uses the embedded server (MLL_SERVER_BIN, else build/server/service/mll_server)
# unless MLL_ADDRESS is set. One torch/BLAS thread throughout.
set -euo pipefail
cd "$(dirname "$0")"
preset=${1:-default}
out=${2:-runs/$preset}
shift $(( $# > 2 ? 2 : $# ))
export OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1
py=../../.venv/bin/python
address=()
[ -n "${MLL_ADDRESS:-}" ] && address=(--address "$MLL_ADDRESS")
mkdir -p "$out"
$py -m mll_dqn train --preset "$preset" --out "$out" "${address[@]}" "$@"
$py -m mll_dqn evaluate --checkpoint "$out/checkpoint.pt" --json "$out/eval.json" "${address[@]}"
# The network of the best 50-episode mean (written once 50 episodes are done).
if [ -f "$out/best.pt" ]; then
  $py -m mll_dqn evaluate --checkpoint "$out/best.pt" --json "$out/eval_best.json" "${address[@]}"
fi
for baseline in heuristic random; do
  $py -m mll_dqn evaluate --policy "$baseline" --json "$out/eval_$baseline.json" "${address[@]}"
done
$py -m mll_dqn plot "$out/episodes.csv" --labels "$preset" --out "$out/scores.png"
$py -m mll_dqn gif --checkpoint "$out/checkpoint.pt" --out "$out/greedy.gif" "${address[@]}"
if [ -f "$out/best.pt" ]; then
  $py -m mll_dqn gif --checkpoint "$out/best.pt" --out "$out/greedy_best.gif" "${address[@]}"
fi
# The training run's figures again, last, so they are the output's last lines.
$py -m mll_dqn summary "$out"
