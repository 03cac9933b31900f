#!/usr/bin/env bash
# Starts the real mll_server on a free loopback port and runs a load tool
# against it, then stops the server with SIGTERM and checks it exits 0.
#
#   bench/load/run.sh load [mll_load flags]   # 64 clients, 64,000 operations
#   bench/load/run.sh soak [mll_soak flags]   # 1,000,000 create/step/delete cycles
#
# BUILD_DIR (default build-rel) must hold mll_server and the tools; build with
#   cmake --build build-rel --target mll_server mll_load mll_soak
# SERVER_FLAGS adds mll_server flags (e.g. "--threads=2").
set -euo pipefail
cd "$(dirname "$0")/../.."
BUILD_DIR=${BUILD_DIR:-build-rel}
tool=${1:?usage: run.sh load|soak [flags]}
shift
dir=$(mktemp -d)
trap 'rm -rf "$dir"' EXIT
# shellcheck disable=SC2086
"$BUILD_DIR/server/service/mll_server" --address=127.0.0.1:0 \
  --port_file="$dir/port" ${SERVER_FLAGS:-} 2>"$dir/server.log" &
server=$!
for _ in $(seq 300); do [ -s "$dir/port" ] && break; sleep 0.1; done
port=$(cat "$dir/port")
status=0
"$BUILD_DIR/bench/load/mll_$tool" --address="127.0.0.1:$port" \
  --server_pid="$server" "$@" || status=$?
kill -TERM "$server"
server_status=0
wait "$server" || server_status=$?
echo "mll_server exit status after SIGTERM: $server_status"
[ "$server_status" -eq 0 ] || { cat "$dir/server.log"; status=1; }
exit $status
