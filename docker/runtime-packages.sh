#!/usr/bin/env bash
# Prints, one per line, the Debian packages that own the shared libraries the
# given executables load. The Dockerfile's runtime stage installs exactly
# these, so the slim image follows the binaries when a layer gains a library
# (e.g. OpenSSL for TLS) instead of a hand-kept list going stale.
# Usage: runtime-packages.sh EXECUTABLE...   (fails if a library has no owner)
set -euo pipefail
(($#)) || { echo "usage: $0 EXECUTABLE..." >&2; exit 2; }

owner_of() {
  local lib=$1 real
  real=$(readlink -f "$lib")
  # usrmerge: dpkg may have recorded /lib/... or /usr/lib/..., and the file or
  # its symlink; match the file name under any directory.
  dpkg-query -S "*/$(basename "$real")" "*/$(basename "$lib")" 2>/dev/null \
    | grep -v '^diversion' | cut -d: -f1 | tr ',' '\n' | sed 's/^ *//' \
    | grep -v -- '-dev$' | sort -u
}

libs=$(for exe in "$@"; do
  [ -x "$exe" ] || { echo "runtime-packages: not an executable: $exe" >&2; exit 1; }
  # ldd marks a missing library "not found"; that is a broken build.
  if ldd "$exe" | grep -q 'not found'; then
    ldd "$exe" >&2; echo "runtime-packages: $exe has unresolved libraries" >&2; exit 1
  fi
  ldd "$exe" | awk '$2 == "=>" && $3 ~ /^\// {print $3}'
done | sort -u)

for lib in $libs; do
  owners=$(owner_of "$lib")
  [ -n "$owners" ] || { echo "runtime-packages: no Debian package owns $lib" >&2; exit 1; }
  echo "$owners"
done | sort -u
