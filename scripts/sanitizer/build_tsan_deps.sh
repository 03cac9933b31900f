#!/usr/bin/env bash
# Builds Debian 12's own abseil, protobuf and gRPC (their source packages, the
# versions that are installed, Debian's patches applied) with
# -fsanitize=thread into a private library directory, as shared libraries
# with Debian's SONAMEs, for scripts/sanitize.sh tsan, which puts that
# directory first on LD_LIBRARY_PATH. Nothing else changes: the headers,
# gRPC's other libraries (unsecure, plugins, ...) and every other library
# stay Debian's.
#
# Why abseil: Debian's libabsl is not built with ThreadSanitizer, so
# absl::Mutex and absl::CondVar (used by our code, and by gRPC through
# GPR_ABSEIL_SYNC) synchronize through atomics and futexes TSan cannot see,
# and every access guarded by an absl::Mutex looks like a race. Built with
# -fsanitize=thread, Mutex/CondVar carry TSan's mutex annotations
# (ABSL_TSAN_MUTEX_*), for every caller: ours and Debian's gRPC.
#
# Why protobuf: its headers change a class layout under TSan
# (google/protobuf/map_field.h gives MapFieldBase two extra members, seq1_
# and seq2_, when __SANITIZE_THREAD__ is defined), so instrumented code and
# Debian's uninstrumented libprotobuf.so.32 disagree on the offset of every
# member of every map field: reading a google.protobuf.Struct parsed by the
# library crashes (SEGV in Map::find). An instrumented libprotobuf has the
# layout the instrumented headers expect.
#
# Why gRPC: Debian's libgrpc hands call objects, slices and statuses from
# one thread to the next through its completion queue, call combiner and
# transports, synchronization TSan cannot see when the library is not
# instrumented, so every hand-off looks like a race (12 of 129 tests failed
# that way). Built with -fsanitize=thread, gRPC's own accesses are checked
# and its TSan annotations (GRPC_TSAN_ENABLED, e.g. the call combiner's)
# are compiled in.
#
#   scripts/sanitizer/build_tsan_deps.sh [OUT_DIR]   # default build-tsan-deps
#
# Prints the library directory on its last line; does nothing the second
# time. Needs deb-src entries (added if missing), dpkg-dev and autotools
# (installed if missing). Nothing it downloads or builds belongs in git
# (OUT_DIR is ignored through build-*/). Environment: JOBS (default nproc).
set -euo pipefail
cd "$(dirname "$0")/../.."
OUT=$(realpath -m "${1:-build-tsan-deps}")
LIBDIR="$OUT/prefix/lib"
SYSLIB=/usr/lib/x86_64-linux-gnu
JOBS=${JOBS:-$(nproc)}
mkdir -p "$OUT" "$LIBDIR"

# Debian's compiler flags for its packages (dpkg-buildflags: -g -O2,
# hardening) plus ThreadSanitizer.
CXXFLAGS_TSAN="$(dpkg-buildflags --get CXXFLAGS) -fsanitize=thread"
LDFLAGS_TSAN="$(dpkg-buildflags --get LDFLAGS) -fsanitize=thread"

# fetch_source PACKAGE VERSION: unpacks Debian's source package into $OUT
# (patches applied by dpkg-source) and prints its directory.
fetch_source() {
  local package=$1 version=$2 upstream=${2%-*}
  local dir="$OUT/$package-${upstream#*:}"
  if [[ ! -d "$dir" ]]; then
    if ! apt-cache showsrc "$package" 2>/dev/null | grep -qx "Version: $version"; then
      # Debian's source packages come from the same mirrors as its binaries.
      cat >/etc/apt/sources.list.d/mll-debian-src.sources <<'EOF'
Types: deb-src
URIs: http://deb.debian.org/debian
Suites: bookworm bookworm-updates
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg

Types: deb-src
URIs: http://deb.debian.org/debian-security
Suites: bookworm-security
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg
EOF
      apt-get update -qq >&2
    fi
    (cd "$OUT" && apt-get source -qq "$package=$version" >&2)
  fi
  echo "$dir"
}

# check_twins GLOB: every Debian library matching GLOB has its instrumented
# twin, or a caller would silently keep Debian's uninstrumented copy.
check_twins() {
  local lib missing=0
  for lib in $SYSLIB/$1; do
    if [[ ! -e "$LIBDIR/$(basename "$lib")" ]]; then
      echo "missing instrumented $(basename "$lib")" >&2
      missing=1
    fi
  done
  return $missing
}

command -v dpkg-source >/dev/null || apt-get install -y -qq dpkg-dev >&2
command -v autoreconf >/dev/null && command -v libtoolize >/dev/null ||
  apt-get install -y -qq autoconf automake libtool >&2

# abseil: Debian's configure line (debian/rules: CMake, shared, C++17; the
# patched options.h gives inline namespace debian3, no std:: aliases,
# hardened mode, SONAME 20220623).
version=$(dpkg-query -W -f='${Version}' libabsl20220623)
if [[ ! -e "$LIBDIR/.abseil-$version" ]]; then
  src=$(fetch_source abseil "$version")
  cmake -S "$src" -B "$OUT/build" -G Ninja -DCMAKE_BUILD_TYPE=None \
    -DCMAKE_CXX_STANDARD=17 -DBUILD_SHARED_LIBS=ON -DBUILD_TESTING=OFF \
    -DCMAKE_CXX_FLAGS="$CXXFLAGS_TSAN" -DCMAKE_SHARED_LINKER_FLAGS="$LDFLAGS_TSAN" \
    -DCMAKE_INSTALL_PREFIX="$OUT/prefix" -DCMAKE_INSTALL_LIBDIR=lib >&2
  cmake --build "$OUT/build" -j "$JOBS" >&2
  cmake --install "$OUT/build" >/dev/null
  check_twins 'libabsl_*.so.20220623'
  touch "$LIBDIR/.abseil-$version"
fi

# protobuf: Debian's build (debian/rules: autoreconf, then configure); only
# libprotobuf.so.32 is needed (libprotobuf-lite has no TSan-dependent layout,
# protoc runs at build time only).
version=$(dpkg-query -W -f='${Version}' libprotobuf32)
if [[ ! -e "$LIBDIR/.protobuf-$version" ]]; then
  src=$(fetch_source protobuf "$version")
  (
    cd "$src"
    [[ -x configure ]] || autoreconf -f -i >&2
    [[ -e Makefile ]] || ./configure --disable-static --prefix="$OUT/prefix" \
      CXXFLAGS="$CXXFLAGS_TSAN" LDFLAGS="$LDFLAGS_TSAN" >&2
    make -C src -j "$JOBS" libprotobuf.la >&2
  )
  cp -P "$src"/src/.libs/libprotobuf.so.32* "$LIBDIR/"
  check_twins 'libprotobuf.so.32'
  touch "$LIBDIR/.protobuf-$version"
fi
# gRPC: Debian's build (debian/rules: CMake, shared, every dependency from
# its Debian package), only the libraries our programs load (ldd of the
# tests: gpr, grpc, grpc++, grpc++_reflection and what libgrpc links of its
# own, upb and address_sorting). Built against Debian's abseil and protobuf
# headers and libraries (the same headers and SONAMEs as the instrumented
# twins above, which replace them at run time through LD_LIBRARY_PATH).
# CMAKE_SYSTEM_NAME makes CMake treat the build as a cross build, the one
# way gRPC's CMakeLists takes Debian's installed protoc and grpc_cpp_plugin
# (same 1.51.1) for its generated reflection and health code instead of
# building its own plugin, which needs libprotoc's headers (libprotoc-dev).
# The plugin targets are never built; Protobuf_PROTOC_LIBRARY only satisfies
# their declaration.
version=$(dpkg-query -W -f='${source:Version}' libgrpc29)
grpc_libs=(libgpr.so.29 libgrpc.so.29 libgrpc++.so.1.51
  libgrpc++_reflection.so.1.51 libupb.so.29 libaddress_sorting.so.29)
if [[ ! -e "$LIBDIR/.grpc-$version" ]]; then
  src=$(fetch_source grpc "$version")
  cmake -S "$src" -B "$OUT/build-grpc" -G Ninja -DCMAKE_BUILD_TYPE=None \
    -DCMAKE_SYSTEM_NAME=Linux -DBUILD_SHARED_LIBS=ON -DgRPC_BUILD_TESTS=OFF \
    -DgRPC_ABSL_PROVIDER=package -DgRPC_CARES_PROVIDER=package \
    -DgRPC_PROTOBUF_PROVIDER=package -DgRPC_RE2_PROVIDER=package \
    -DgRPC_SSL_PROVIDER=package -DgRPC_ZLIB_PROVIDER=package \
    -DgRPC_BENCHMARK_PROVIDER=none -DgRPC_BACKWARDS_COMPATIBILITY_MODE=OFF \
    -DgRPC_BUILD_GRPC_CPP_PLUGIN=OFF -DgRPC_BUILD_GRPC_CSHARP_PLUGIN=OFF \
    -DgRPC_BUILD_GRPC_NODE_PLUGIN=OFF -DgRPC_BUILD_GRPC_OBJECTIVE_C_PLUGIN=OFF \
    -DgRPC_BUILD_GRPC_PHP_PLUGIN=OFF -DgRPC_BUILD_GRPC_PYTHON_PLUGIN=OFF \
    -DgRPC_BUILD_GRPC_RUBY_PLUGIN=OFF \
    -DProtobuf_PROTOC_LIBRARY="$SYSLIB/libprotoc.so.32" \
    -DCMAKE_C_FLAGS="$(dpkg-buildflags --get CFLAGS) -fsanitize=thread" \
    -DCMAKE_CXX_FLAGS="$CXXFLAGS_TSAN" \
    -DCMAKE_SHARED_LINKER_FLAGS="$LDFLAGS_TSAN" >&2
  # grpc++_reflection depends on all the others.
  cmake --build "$OUT/build-grpc" -j "$JOBS" --target grpc++_reflection >&2
  for lib in "${grpc_libs[@]}"; do
    cp -P "$OUT/build-grpc/${lib%%.so.*}".so.* "$LIBDIR/"
    check_twins "$lib"
  done
  touch "$LIBDIR/.grpc-$version"
fi
echo "$LIBDIR"
