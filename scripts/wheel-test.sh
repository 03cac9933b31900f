#!/usr/bin/env bash
# The binary wheel (dist/, from scripts/wheel.sh) on a clean Debian 12, as a trainer installs it
# on another machine: run as root (debootstrap, chroot, namespaces); scripts/test.sh runs it.
#   1. the wheel holds what a trainer needs and nothing else: no tests, no debug symbols; its
#      stubs are the ones that run on every Python it installs on;
#   2. a bookworm root file system from debootstrap (minbase) with python3 and python3-venv
#      from Debian (scripts/debian-rootfs.sh; cached as a tarball in $MLL_WHEEL_TEST_CACHE,
#      default /var/cache/mll-wheel-test), unpacked afresh into a temporary directory: no
#      compiler, no -dev package, no X11;
#   3. in a chroot there: a fresh venv (no system site packages), `pip install` of the wheel,
#      its dependencies from PyPI (pip's cache kept in the cache directory);
#   4. offline, in a network namespace whose loopback also has 192.0.2.1 (a host that is not
#      127.0.0.0/8): scripts/wheel_smoke.py from /, with no MLL_* variable (the embedded server,
#      shared memory, a separate server at 192.0.2.1 over the native library, --version).
# `scripts/wheel-test.sh --rootfs-only` makes (or finds) stage 2's cached root file system and
# exits: scripts/test.sh runs it in the background while the tree builds, since debootstrap
# spends its time downloading and unpacking, not computing.
# Each stage is timed. Exit code 0 only if every check passed.
set -euo pipefail
cd "$(dirname "$0")/.."
CACHE=${MLL_WHEEL_TEST_CACHE:-/var/cache/mll-wheel-test}
REMOTE_HOST=192.0.2.1  # TEST-NET-1 (RFC 5737), only ever on the namespace's loopback
start=$SECONDS
stage=$SECONDS
say() { echo "== wheel-test ($((SECONDS - start)) s): $*"; }
took() { echo "wheel-test: $1: $((SECONDS - stage)) s"; stage=$SECONDS; }
fail() { echo "wheel-test: FAIL: $*" >&2; exit 1; }

[ "$(id -u)" -eq 0 ] || fail "run as root (debootstrap, chroot, namespaces)"
source scripts/debian-rootfs.sh
packages=(python3 python3-venv)
tarball=$CACHE/bookworm-minbase+$(IFS=+; echo "${packages[*]}").tar
if [ "${1:-}" = --rootfs-only ]; then
  mkdir -p "$CACHE"
  debian_rootfs_tarball "$tarball" "${packages[@]}"
  took "root file system (debootstrap, or its cached tarball)"
  exit 0
fi
wheels=(dist/multi_lunar_lander-*.whl)
((${#wheels[@]} == 1)) && [ -f "${wheels[0]}" ] || fail "want one wheel in dist/ (scripts/wheel.sh); found: ${wheels[*]}"
wheel=${wheels[0]}
say "$wheel: $(stat -c %s "$wheel") bytes"

say "1. contents"
contents=$(python3 -m zipfile -l "$wheel" | awk 'NR > 1 {print $1}')
! grep -E '(^|/)(tests?|__pycache__)/|\.(pyc|a|o|debug)$' <<<"$contents" || fail "the wheel holds files a trainer does not need (above)"
for file in multi_lunar_lander/libmll_native_stream.so multi_lunar_lander.scripts/mll_server \
  multi_lunar_lander.scripts/mll_cli multi_lunar_lander/_proto/multi_lunar_lander_pb2.py; do
  grep -qx "$file" <<<"$contents" || fail "$file is not in the wheel"
done
unpacked=$(mktemp -d)
python3 -m zipfile -e "$wheel" "$unpacked"
# One wheel for every Python: its stubs must be those of the grpcio-tools pinned for Python 3.11
# (1.62.3), which run on protobuf 4.25.1 and later (client_py/tests/test_dependency_ranges.py).
grep -q "Protobuf Python Version: 4.25.1$" "$unpacked/multi_lunar_lander/_proto/multi_lunar_lander_pb2.py" \
  || fail "the wheel's stubs are not protobuf 4.25.1's: $(grep -h 'Protobuf Python Version' \
    "$unpacked/multi_lunar_lander/_proto/multi_lunar_lander_pb2.py")"
debug=$(find "$unpacked" -name '*.so*' -o -path '*.scripts/*' | while read -r elf; do
  readelf -S --wide "$elf" | grep -qE '\] \.(debug_|symtab)' && echo "$elf"; done || true)
rm -rf "$unpacked"
[ -z "$debug" ] || fail "not stripped: $debug"
echo "$(grep -c . <<<"$contents") files; the stubs run on protobuf 4.25.1 and later; every ELF file stripped"
took contents

say "2. Debian 12 root file system"
mkdir -p "$CACHE/pip"
debian_rootfs_tarball "$tarball" "${packages[@]}"
took "root file system (debootstrap, or its cached tarball)"
root=$(mktemp -d /var/tmp/mll-wheel-test.XXXXXX)
trap 'rm -rf --one-file-system "$root"' EXIT
tar -C "$root" -xf "$tarball"
# The host's network settings, as a container gets them: DNS, and the CA bundle that its TLS
# (a proxy's own CA, where there is one) verifies against; pip.conf where the host has one.
cp /etc/resolv.conf "$root/etc/resolv.conf"
mkdir -p "$root/etc/ssl/certs"
cp /etc/ssl/certs/ca-certificates.crt "$root/etc/ssl/certs/ca-certificates.crt"
[ -f /etc/pip.conf ] && cp /etc/pip.conf "$root/etc/pip.conf"
mkdir -p "$root/wheel" "$root/root/.cache/pip"
cp "$wheel" scripts/wheel_smoke.py "$root/wheel/"
took "unpacked into $root"

# in_chroot [--net] COMMAND...: COMMAND in the chroot, in a mount namespace of its own (its
# /proc, /dev and pip cache mounts vanish with it), with an empty environment but for the host's
# proxy and package index settings; --net: also in a network namespace of its own (offline) with
# loopback up and $REMOTE_HOST on it.
in_chroot() {
  local -a namespaces=(--mount)
  local remote=""
  if [ "$1" = --net ]; then namespaces+=(--net); remote=$REMOTE_HOST; shift; fi
  unshare "${namespaces[@]}" --fork -- bash -euc '
    root=$1 remote=$2; shift 2
    if [ -n "$remote" ]; then ip link set lo up; ip addr add "$remote/32" dev lo; fi
    mount -t proc proc "$root/proc"
    mount --rbind /dev "$root/dev"
    mount --bind "$CACHE/pip" "$root/root/.cache/pip"
    passed=()
    for name in http_proxy https_proxy no_proxy HTTP_PROXY HTTPS_PROXY NO_PROXY \
      PIP_INDEX_URL PIP_EXTRA_INDEX_URL PIP_TRUSTED_HOST; do
      [ -n "${!name:-}" ] && passed+=("$name=${!name}")
    done
    exec chroot "$root" /usr/bin/env -i HOME=/root LANG=C.UTF-8 PATH=/usr/bin:/bin "${passed[@]}" "$@"
  ' in_chroot "$root" "$remote" "$@"
}
export CACHE

say "3. no compiler, no -dev package, no desktop libraries; a fresh venv, pip install of the wheel"
in_chroot sh -c '
  set -e
  for tool in cc c++ gcc g++ clang ld; do
    if command -v $tool; then echo "$tool is installed"; exit 1; fi
  done
  dev=$(dpkg-query -W -f="\${Package}\n" | grep -E -- "-dev$" || true)
  if [ -n "$dev" ]; then echo "-dev packages: $dev"; exit 1; fi
  # Nor the libraries of a desktop, which the manylinux policies would let the wheel expect.
  libraries=$(/sbin/ldconfig -p)
  if echo "$libraries" | grep -E "lib(X11|Xext|Xrender|GL|glib-2\.0)\.so"; then exit 1; fi
  . /etc/os-release
  echo "$PRETTY_NAME, $(python3 --version), no compiler, no -dev package, no X11, GL or GLib"
' || fail "the chroot is not a clean headless Debian 12"
in_chroot python3 -m venv /opt/venv
took "chroot checks and venv"
in_chroot /opt/venv/bin/python -m pip install -q --disable-pip-version-check --only-binary=:all: \
  "/wheel/$(basename "$wheel")" || fail "pip install of the wheel"
in_chroot /opt/venv/bin/python -m pip check
took "pip install (the wheel and its dependencies from PyPI)"

say "4. the installed package, offline, from /"
in_chroot --net sh -c "cd / && PATH=/opt/venv/bin:\$PATH exec python /wheel/wheel_smoke.py --remote_host=$REMOTE_HOST" \
  || fail "wheel_smoke.py"
took "smoke test"
say "PASS"
