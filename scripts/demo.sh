#!/usr/bin/env bash
# The main job: installs what is missing, builds, starts an mll_server on a free
# loopback port, flies landers through it (the C++ CLI and the Python PettingZoo
# client, with Gymnasium's heuristic pilot and the trained DQN pilot of
# docs/dqn.md), and shows the result: one JSON line per episode, a rendered
# frame and an animated GIF under out/.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
scripts/build.sh
OUT=${OUT:-out}
mkdir -p "$OUT"
BIN=build/server/service/mll_server
CLI=build/client_cpp/mll_cli

port_file=$(mktemp)
"$BIN" --address=127.0.0.1:0 --port_file="$port_file" --threads=2 &
server_pid=$!
trap 'kill -TERM "$server_pid" 2>/dev/null; wait "$server_pid" 2>/dev/null || true; rm -f "$port_file"' EXIT
for _ in $(seq 100); do [ -s "$port_file" ] && break; sleep 0.1; done
[ -s "$port_file" ] || { echo "demo: mll_server did not start" >&2; exit 1; }
address="127.0.0.1:$(cat "$port_file")"
"$CLI" health --address="$address"

echo "== 1 lander (Gymnasium's LunarLander-v3), 5 episodes, heuristic pilot, through the server"
"$CLI" play --address="$address" --n_landers=1 --episodes=5 --seed=0 --policy=heuristic

# Gymnasium's pilot steers every lander to the pad's centre and knows nothing of the others,
# so with several landers they often collide: that is what the agents have to learn.
echo "== 3 landers, 5 episodes, the same pilot, damage ends only the damaged lander's episode"
"$CLI" play --address="$address" --n_landers=3 --episodes=5 --seed=5 --policy=heuristic \
  --terminate_on_damage=false

# The trained pilot (examples/dqn/trained.qnet, docs/dqn.md) learnt to land beside the others
# in the environment it was trained in: damage removes only the damaged lander, 2,000 steps.
echo "== 3 landers, 5 episodes, the trained DQN pilot"
"$CLI" play --address="$address" --n_landers=3 --episodes=5 --seed=10 --policy=trained \
  --terminate_on_damage=false --remove_on_damage=true --max_cycles=2000

echo "== 3 landers, the trained pilot through the Python PettingZoo client, rendered to $OUT/landers.gif"
.venv/bin/python examples/play.py --address="$address" --policy trained --n_landers=3 --episodes=1 \
  --seed=10 --frame_skip=4 --gif "$OUT/landers.gif"
"$CLI" create --address="$address" --n_landers=3 --render_mode=rgb_array > "$OUT/env.txt"
name=$(grep -o 'envs/[0-9a-f]*' "$OUT/env.txt" | head -n 1)
"$CLI" reset "$name" --address="$address" --seed=0 > /dev/null
"$CLI" render "$name" --address="$address" --out="$OUT/frame.png"
"$CLI" delete "$name" --address="$address"
echo "demo: results in $OUT/ (landers.gif, frame.png)"
