#!/usr/bin/env bash
# Installs what the project needs on Debian 12: the C++ toolchain and libraries
# from Debian's packages, and the project's Python venv (.venv) from PyPI.
# Idempotent: installs only what is missing. `scripts/setup.sh --debian-only`: the Debian
# packages alone.
set -euo pipefail
cd "$(dirname "$0")/.."

DEBIAN_PACKAGES=(
  build-essential cmake ninja-build pkg-config git ca-certificates
  libbox2d-dev libgrpc++-dev protobuf-compiler-grpc libprotobuf-dev protobuf-compiler
  libabsl-dev libgtest-dev libgmock-dev libbenchmark-dev libcairo2-dev libpng-dev
  libcpp-httplib-dev openssl chromium clang-format
  python3 python3-venv python3-dev python3-torch libopenblas0-pthread
  debootstrap iproute2  # scripts/wheel-test.sh: a clean Debian chroot, its network namespace
)

missing=()
for package in "${DEBIAN_PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$package" 2>/dev/null | grep -q "install ok installed" || missing+=("$package")
done
if ((${#missing[@]})); then
  echo "setup: installing Debian packages: ${missing[*]}"
  SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO=sudo
  $SUDO apt-get update -q
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -q --no-install-recommends "${missing[@]}"
fi

[ "${1:-}" = --debian-only ] && exit 0

# The venv is rebuilt when requirements.txt changes.
VENV=.venv
stamp="$VENV/.requirements.sha256"
want=$({ cat requirements.txt requirements-nodeps.txt; cat client_py/pyproject.toml 2>/dev/null || true; } | sha256sum | cut -d' ' -f1)
if [ ! -x "$VENV/bin/python" ] || [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  echo "setup: creating the Python venv in $VENV"
  /usr/bin/python3 -m venv --system-site-packages "$VENV"
  "$VENV/bin/pip" install -q --upgrade pip
  "$VENV/bin/pip" install -q -r requirements.txt
  "$VENV/bin/pip" install -q --no-deps -r requirements-nodeps.txt
  echo "$want" > "$stamp"
fi

# The Python client, editable, with its stubs generated from proto/.
if [ -f client_py/pyproject.toml ]; then
  "$VENV/bin/pip" install -q --no-build-isolation -e client_py
fi
