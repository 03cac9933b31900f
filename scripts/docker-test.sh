#!/usr/bin/env bash
# Proves docker/Dockerfile end to end with podman, on a machine with no Docker
# engine and no image registry (run by hand, as root; too slow for CI, and
# scripts/test.sh does not call it):
#   1. installs podman, runc, debootstrap and friends from Debian;
#   2. writes a containers.conf (runc, cgroupfs, ulimits under the host's hard
#      limits, because podman's rootful default nofile=1048576 makes runc fail
#      where the host allows less) and points CONTAINERS_CONF at it;
#   3. makes the base image localhost/debian:bookworm-slim with debootstrap from
#      the Debian mirror apt uses (cached: rootfs tarball and image are kept);
#   4. builds the image (the build stage compiles and runs ctest);
#   5. runs it with a loopback-only port mapping, waits for the server to be
#      healthy (grpc.health.v1 from the host, and the image's HEALTHCHECK);
#   6. creates, resets and steps an environment from the host's Python client;
#   7. sends SIGTERM and checks exit code 0 and a clean stop in the log;
#   8. removes the container (images stay cached; --clean removes them too).
# Every wait is bounded. Exit code 0 only if every check passed.
#
# Environment: MLL_DOCKER_CACHE (default /var/cache/mll-docker-test),
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
# The first bookworm (not -security) mirror that apt uses, deb822 or one-line.
debian_mirror() {
  local file
  for file in /etc/apt/sources.list.d/*.sources; do
    [ -f "$file" ] || continue
    awk '/^URIs:/{uri=$2} /^Suites:/{for(i=2;i<=NF;i++) if($i=="bookworm") found=1}
         /^$/{if(found&&uri){print uri; exit} found=0; uri=""}
         END{if(found&&uri) print uri}' "$file" | head -n1
  done
  awk '$1=="deb" && $3=="bookworm" {print $2}' /etc/apt/sources.list 2>/dev/null || true
}
if podman image exists "$BASE_IMAGE"; then
  echo "cached: $BASE_IMAGE"
else
  tarball=$CACHE/bookworm-minbase.tar
  if [ ! -s "$tarball" ]; then
    mirror=$(debian_mirror | head -n1)
    [ -n "$mirror" ] || fail "no bookworm mirror found in apt's sources"
    echo "debootstrap bookworm from $mirror"
    rm -rf "$CACHE/rootfs"
    timeout 1800 debootstrap --variant=minbase bookworm "$CACHE/rootfs" "$mirror"
    # Slim like the official image: no apt lists or caches in the base layer.
    # apt sources as on this host (main, -updates, -security) like the
    # official image, and slim like it: no apt lists or caches in the layer.
    if [ -f /etc/apt/sources.list.d/debian.sources ]; then
      cp /etc/apt/sources.list.d/debian.sources "$CACHE/rootfs/etc/apt/sources.list.d/"
      rm -f "$CACHE/rootfs/etc/apt/sources.list"
    fi
    rm -rf "$CACHE/rootfs/var/lib/apt/lists/"* "$CACHE/rootfs/var/cache/apt/"*.bin \
      "$CACHE/rootfs/var/cache/apt/archives/"*.deb
    tar -C "$CACHE/rootfs" -cf "$tarball.tmp" .
    mv "$tarball.tmp" "$tarball"
    rm -rf "$CACHE/rootfs"
  fi
  podman import --change 'CMD ["bash"]' "$tarball" "$BASE_IMAGE"
fi
pass "base image $BASE_IMAGE"

step "4. build $IMAGE"
build_args=(--build-arg "BASE_IMAGE=$BASE_IMAGE")
[ "${MLL_DOCKER_NO_TESTS:-0}" = 1 ] && build_args+=(--build-arg RUN_TESTS=0)
# Host networking for the build's apt-get; the server's run below uses the
# default bridge with a loopback-only port mapping.
build_start=$SECONDS
set +e
timeout 3600 podman build --network=host "${build_args[@]}" -f docker/Dockerfile -t "$IMAGE" . 2>&1 \
  | tee "$CACHE/build.log" \
  | grep --line-buffered -E '^(STEP|COMMIT|build packages|runtime packages|WARNING)|tests passed|tests failed|rror'
build_rc=${PIPESTATUS[0]}
set -e
((build_rc == 0)) || { tail -n 40 "$CACHE/build.log"; fail "image build failed (rc $build_rc); see $CACHE/build.log"; }
ctest_line=$(grep -E 'tests passed|tests failed' "$CACHE/build.log" | tail -n1 || true)
size_mb=$(( $(podman image inspect --format '{{.Size}}' "$IMAGE") / 1000000 ))
pass "image built in $((SECONDS - build_start)) s, ${size_mb} MB${ctest_line:+; build-stage ctest: $ctest_line}"

step "5. run with a loopback-only port mapping"
PORT=${MLL_DOCKER_PORT:-$("$PYTHON" -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')}
ADDRESS=127.0.0.1:$PORT
cleanup() {
  podman rm -f --time 5 "$CONTAINER" >/dev/null 2>&1 || true
  if ((CLEAN)); then podman rmi -f "$IMAGE" "$BASE_IMAGE" >/dev/null 2>&1 || true; fi
}
trap cleanup EXIT
podman run -d --name "$CONTAINER" -p "$ADDRESS:50051" "$IMAGE" --max_envs=64 >/dev/null
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
timeout 120 env PYTHONPATH="$ROOT/client_py${PYTHONPATH:+:$PYTHONPATH}" \
  "$PYTHON" - "$ADDRESS" "$ROOT/proto" <<'PY' | tee "$CACHE/client.log"
"""Flies two identical environments in the container and compares their bits;
through multi_lunar_lander.parallel_env when the package has it, otherwise
through stubs generated from proto/ into a temporary directory."""
import sys

import numpy as np

address, proto_dir = sys.argv[1], sys.argv[2]
STEPS, SEED, N = 100, 7, 3

def with_package():
    import multi_lunar_lander as mll
    if not hasattr(mll, "parallel_env"):
        raise ImportError("multi_lunar_lander has no parallel_env yet")
    runs = []
    for _ in range(2):
        env = mll.parallel_env(address=address, n_landers=N)
        obs, _ = env.reset(seed=SEED)
        trace = [np.stack([obs[a] for a in env.possible_agents])]
        for t in range(STEPS):
            if not env.agents:
                break
            obs, rewards, _, _, _ = env.step({a: (t + i) % 4 for i, a in enumerate(env.agents)})
            trace.append(np.array([rewards[a] for a in sorted(rewards)], np.float32))
        env.close()
        runs.append(trace)
    return "multi_lunar_lander.parallel_env", runs

def with_stubs():
    import tempfile
    import grpc
    from grpc_tools import protoc
    out = tempfile.mkdtemp(prefix="mll-stubs-")
    if protoc.main(["protoc", f"-I{proto_dir}", f"--python_out={out}",
                    f"--grpc_python_out={out}", "mll/v1/multi_lunar_lander.proto"]):
        sys.exit("protoc failed")
    sys.path.insert(0, out)
    from mll.v1 import multi_lunar_lander_pb2 as pb, multi_lunar_lander_pb2_grpc as pbg
    runs = []
    with grpc.insecure_channel(address) as channel:
        stub = pbg.MultiLunarLanderStub(channel)
        for _ in range(2):
            env = stub.CreateEnv(pb.CreateEnvRequest(config=pb.EnvConfig(n_landers=N)), timeout=10)
            reset = stub.ResetEnv(pb.ResetEnvRequest(name=env.name, seed=SEED), timeout=10)
            obs = np.frombuffer(reset.data.observations.data, "<f4").reshape(N, 12)
            trace = [obs]
            for t in range(STEPS):
                actions = np.array([(t + i) % 4 for i in range(N)], "<i4")
                data = stub.StepEnv(pb.StepEnvRequest(name=env.name, actions=pb.Array(
                    dtype=pb.DTYPE_INT32, shape=[N], data=actions.tobytes())), timeout=10).data
                trace.append(np.frombuffer(data.rewards.data, "<f4"))
                if data.episode_over:
                    break
            stub.DeleteEnv(pb.DeleteEnvRequest(name=env.name), timeout=10)
            runs.append(trace)
    return "stubs generated from proto/", runs

try:
    how, runs = with_package()
except ImportError as error:
    print(f"client: {error}; using stubs generated from proto/")
    how, runs = with_stubs()
a, b = runs
assert a[0].shape == (N, 12), a[0].shape
assert len(a) == len(b) and all(np.array_equal(x, y) for x, y in zip(a, b)), "runs differ"
print(f"client: {how}: 2 envs x {len(a) - 1} steps, identical bits, "
      f"first observation row {np.round(a[0][0], 3).tolist()}")
PY
pass "$(tail -n1 "$CACHE/client.log")"

step "7. SIGTERM: graceful stop"
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
