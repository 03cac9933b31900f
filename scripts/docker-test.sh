#!/usr/bin/env bash
# Proves docker/Dockerfile end to end with podman, on a machine with no Docker
# engine and no image registry (run by hand, as root; too slow for CI, and
# scripts/test.sh does not call it):
#   1. installs podman, runc, debootstrap and friends from Debian;
#   2. writes a containers.conf (runc, cgroupfs, ulimits under the host's hard
#      limits, because podman's rootful default nofile=1048576 makes runc fail
#      where the host allows less) and points CONTAINERS_CONF at it;
#   3. makes the base image localhost/debian:bookworm-slim with debootstrap from
#      the Debian mirror apt uses (scripts/debian-rootfs.sh; cached: rootfs
#      tarball and image are kept);
#   4. builds the image (the build stage compiles and runs ctest);
#   5. runs it with a loopback-only port mapping, waits for the server to be
#      healthy (grpc.health.v1 from the host, and the image's HEALTHCHECK);
#   6. creates, resets and steps an environment from the host's Python client;
#   7. leaves 1000 reset environments on it and measures the server's RSS per
#      environment against the 256 KiB that deploy/k8s is sized with;
#   8. sends SIGTERM and checks exit code 0 and a clean stop in the log;
#   9. removes the container (images stay cached; --clean removes them too).
# Every wait is bounded. Exit code 0 only if every check passed.
#
# Environment: MLL_DOCKER_CACHE (default /var/cache/mll-docker-test),
# MLL_DOCKER_CONTEXT (head: build what is committed, the default; worktree:
# build the work tree with its uncommitted edits),
# MLL_DOCKER_PORT (default: a free loopback port), MLL_DOCKER_IMAGE
# (default localhost/mll-server:test), MLL_DOCKER_NO_TESTS=1 skips ctest in the
# build stage.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD

CACHE=${MLL_DOCKER_CACHE:-/var/cache/mll-docker-test}
BASE_IMAGE=localhost/debian:bookworm-slim
IMAGE=${MLL_DOCKER_IMAGE:-localhost/mll-server:test}
CONTAINER=mll-docker-test-$$
PYTHON=${PYTHON:-$ROOT/.venv/bin/python}
CLEAN=0
for arg in "$@"; do
  case "$arg" in
    --clean) CLEAN=1 ;;
    *) echo "usage: $0 [--clean]" >&2; exit 2 ;;
  esac
done

step() { printf '\n== %s\n' "$*"; }
fail() { echo "docker-test: FAIL: $*" >&2; exit 1; }
declare -a SUMMARY=()
pass() { echo "docker-test: ok: $*"; SUMMARY+=("ok: $*"); }
note() { echo "docker-test: note: $*"; SUMMARY+=("note: $*"); }

[ "$(id -u)" -eq 0 ] || fail "run as root (rootful podman; debootstrap needs root)"

step "1. packages"
PACKAGES=(podman runc debootstrap slirp4netns fuse-overlayfs uidmap catatonit
          netavark aardvark-dns iptables)
missing=()
for package in "${PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$package" 2>/dev/null | grep -q "install ok installed" \
    || missing+=("$package")
done
if ((${#missing[@]})); then
  echo "installing: ${missing[*]}"
  apt-get update -q
  DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends "${missing[@]}"
fi
podman --version

step "2. containers.conf"
mkdir -p "$CACHE"
# Container limits must stay under the host's hard limits or runc's setrlimit
# fails; the server needs a few descriptors per connection, not per env.
nofile=$(ulimit -Hn)
[ "$nofile" = unlimited ] && nofile=65536
((nofile > 65536)) && nofile=65536
nproc=$(ulimit -Hu)
{ [ "$nproc" = unlimited ] || ((nproc > 32768)); } && nproc=32768
cat > "$CACHE/containers.conf" <<EOF
# Written by scripts/docker-test.sh.
[containers]
default_ulimits = ["nofile=${nofile}:${nofile}", "nproc=${nproc}:${nproc}"]
log_driver = "k8s-file"

[engine]
runtime = "runc"
cgroup_manager = "cgroupfs"
events_logger = "file"
EOF
export CONTAINERS_CONF=$CACHE/containers.conf
cat "$CONTAINERS_CONF"

step "3. base image $BASE_IMAGE"
source scripts/debian-rootfs.sh
if podman image exists "$BASE_IMAGE"; then
  echo "cached: $BASE_IMAGE"
else
  tarball=$CACHE/bookworm-minbase.tar
  debian_rootfs_tarball "$tarball" || fail "debootstrap of bookworm failed"
  podman import --change 'CMD ["bash"]' "$tarball" "$BASE_IMAGE"
fi
pass "base image $BASE_IMAGE"

step "4. build $IMAGE"
# The build context is what is committed (HEAD, exported like CI's clean
# clone), so others' half-done edits in the work tree do not decide the
# result; MLL_DOCKER_CONTEXT=worktree builds the work tree as it is.
if [ "${MLL_DOCKER_CONTEXT:-head}" = worktree ]; then
  context=$ROOT commit=""
  echo "context: the work tree $ROOT"
else
  context=$CACHE/context
  rm -rf "$context" && mkdir -p "$context"
  commit=$(git rev-parse --short HEAD)
  git archive "$commit" | tar -x -C "$context"
  echo "context: HEAD $commit exported to $context"
fi
build_args=(--build-arg "BASE_IMAGE=$BASE_IMAGE")
[ "${MLL_DOCKER_NO_TESTS:-0}" = 1 ] && build_args+=(--build-arg RUN_TESTS=0)
# Docker's image format: podman's default (OCI) drops SHELL and HEALTHCHECK.
# Host networking for the build's apt-get; the server's run below uses the
# default bridge with a loopback-only port mapping.
build_start=$SECONDS
set +e
timeout 3600 podman build --format docker --network=host "${build_args[@]}" -f "$context/docker/Dockerfile" -t "$IMAGE" "$context" 2>&1 \
  | tee "$CACHE/build.log" \
  | grep --line-buffered -E '^(STEP|COMMIT|build packages|runtime packages|WARNING)|tests passed|tests failed|^Error|error:'
build_rc=${PIPESTATUS[0]}
set -e
((build_rc == 0)) || { tail -n 40 "$CACHE/build.log"; fail "image build failed (rc $build_rc); see $CACHE/build.log"; }
ctest_line=$(grep -E 'tests passed|tests failed' "$CACHE/build.log" | tail -n1 || true)
size_mb=$(( $(podman image inspect --format '{{.Size}}' "$IMAGE") / 1000000 ))
pass "image of ${commit:-the work tree} built in $((SECONDS - build_start)) s, ${size_mb} MB${ctest_line:+; build-stage ctest: $ctest_line}"

step "5. run with a loopback-only port mapping"
PORT=${MLL_DOCKER_PORT:-$("$PYTHON" -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')}
ADDRESS=127.0.0.1:$PORT
cleanup() {
  podman rm -f --time 5 "$CONTAINER" >/dev/null 2>&1 || true
  if ((CLEAN)); then podman rmi -f "$IMAGE" "$BASE_IMAGE" >/dev/null 2>&1 || true; fi
}
trap cleanup EXIT
MEMORY_ENVS=1000
podman run -d --name "$CONTAINER" -p "$ADDRESS:50051" "$IMAGE" --max_envs=$((MEMORY_ENVS + 16)) >/dev/null
podman port "$CONTAINER"
podman port "$CONTAINER" | grep -qx "50051/tcp -> $ADDRESS" \
  || fail "port mapping is not loopback-only: $(podman port "$CONTAINER")"
pass "container $CONTAINER publishes 50051 on $ADDRESS only"
[ "$(podman exec "$CONTAINER" cat /proc/1/comm)" = mll_server ] \
  || fail "PID 1 is $(podman exec "$CONTAINER" cat /proc/1/comm), not mll_server"
uid=$(podman exec "$CONTAINER" id -u)
[ "$uid" != 0 ] || fail "the server runs as root"
pass "PID 1 is mll_server, uid $uid"

# grpc.health.v1.Health/Check from the host, without generated stubs: the
# request is an empty HealthCheckRequest, SERVING is the response 08 01.
health_from_host() {
  "$PYTHON" - "$ADDRESS" <<'PY'
import sys, grpc
with grpc.insecure_channel(sys.argv[1]) as channel:
    check = channel.unary_unary("/grpc.health.v1.Health/Check")
    try:
        reply = check(b"", timeout=2)
    except grpc.RpcError as error:
        sys.exit(f"health: {error.code().name}")
sys.exit(0 if reply == b"\x08\x01" else f"health: not SERVING ({reply.hex()})")
PY
}
deadline=$((SECONDS + 60))
until health_from_host 2>/dev/null; do
  [ "$(podman inspect --format '{{.State.Running}}' "$CONTAINER")" = true ] \
    || { podman logs "$CONTAINER" >&2; fail "container exited before serving"; }
  ((SECONDS < deadline)) || { podman logs "$CONTAINER" >&2; fail "not SERVING within 60 s"; }
  sleep 1
done
pass "grpc.health.v1 SERVING on $ADDRESS after $((60 - deadline + SECONDS)) s"
if podman exec "$CONTAINER" test -x /usr/local/bin/mll_cli; then
  deadline=$((SECONDS + 60))
  until timeout 20 podman healthcheck run "$CONTAINER"; do
    ((SECONDS < deadline)) || fail "the image's HEALTHCHECK (mll_cli health) did not pass within 60 s"
    sleep 2
  done
  pass "the image's HEALTHCHECK (mll_cli health) passes: $(podman inspect --format '{{.State.Health.Status}}' "$CONTAINER")"
else
  note "mll_cli is not in the image (not built by this tree yet): HEALTHCHECK not exercised"
fi

step "6. create, reset and step environments from the host's Python client"
timeout 180 "$PYTHON" docker/smoke_client.py --address="$ADDRESS" --proto_dir="$ROOT/proto" \
  | tee "$CACHE/client.log"
pass "$(tail -n1 "$CACHE/client.log")"

step "7. memory per environment (the Kubernetes sizing assumes 256 KiB)"
rss_kib() { podman exec "$CONTAINER" awk '/^VmRSS:/{print $2}' /proc/1/status; }
before=$(rss_kib)
timeout 300 "$PYTHON" docker/smoke_client.py --address="$ADDRESS" --proto_dir="$ROOT/proto" \
  --leave_envs="$MEMORY_ENVS"
after=$(rss_kib)
per_env=$(( (after - before) / MEMORY_ENVS ))
echo "VmRSS $before KiB -> $after KiB with $MEMORY_ENVS more envs of 3 landers"
((per_env <= 256)) || fail "$per_env KiB per environment: more than the 256 KiB deploy/k8s and docs/deployment.md budget"
pass "memory: $per_env KiB per reset 3-lander environment (RSS $((before / 1024)) -> $((after / 1024)) MiB for $MEMORY_ENVS envs; budget 256 KiB)"

step "8. SIGTERM with $MEMORY_ENVS live environments: graceful stop"
stop_start=$SECONDS
timeout 60 podman stop --time 30 "$CONTAINER" >/dev/null
code=$(podman inspect --format '{{.State.ExitCode}}' "$CONTAINER")
podman logs "$CONTAINER" > "$CACHE/server.log" 2>&1
echo "--- server log (last lines)"; tail -n 8 "$CACHE/server.log"
[ "$code" = 0 ] || fail "exit code $code after SIGTERM (137 means it ignored SIGTERM and was killed)"
grep -qiE 'stop|shut' "$CACHE/server.log" || fail "the log shows no stop; see $CACHE/server.log"
pass "SIGTERM -> exit 0 in $((SECONDS - stop_start)) s; log: $(grep -iE 'stop|shut' "$CACHE/server.log" | tail -n1)"

step "summary"
printf '%s\n' "${SUMMARY[@]}"
echo "docker-test: PASS"
