# A Debian 12 (bookworm) root file system made with debootstrap, for the tests that need a clean
# Debian system: scripts/docker-test.sh (podman's base image) and scripts/wheel-test.sh (the
# wheel installed where there is no compiler and no -dev package). Sourced, not run; needs root.
#
#   debian_rootfs_tarball TARBALL [PACKAGE...]
#       TARBALL: a minbase bookworm root file system with PACKAGEs (and what they depend on)
#       from the Debian mirror apt uses here, its apt sources as on this host (main, -updates,
#       -security), slim like Debian's official image (no apt lists, caches or .debs). Made
#       unless TARBALL exists already (a cache: delete it to make it anew).
#   debian_mirror
#       The first bookworm (not -security) mirror in apt's sources, deb822 or one-line.

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

debian_rootfs_tarball() {
  local tarball=$1
  shift
  [ -s "$tarball" ] && return 0
  if ! command -v debootstrap >/dev/null; then
    echo "debian_rootfs_tarball: no debootstrap (scripts/setup.sh installs it)" >&2
    return 1
  fi
  local mirror rootfs include=()
  mirror=$(debian_mirror | head -n1)
  if [ -z "$mirror" ]; then
    echo "debian_rootfs_tarball: no bookworm mirror found in apt's sources" >&2
    return 1
  fi
  (($#)) && include=("--include=$(IFS=,; echo "$*")")
  rootfs=$(dirname "$tarball")/rootfs.$$
  rm -rf "$rootfs"
  echo "debootstrap bookworm ${include[*]} from $mirror"
  timeout 1800 debootstrap --variant=minbase "${include[@]}" bookworm "$rootfs" "$mirror" \
    || { rm -rf "$rootfs"; return 1; }
  if [ -f /etc/apt/sources.list.d/debian.sources ]; then
    cp /etc/apt/sources.list.d/debian.sources "$rootfs/etc/apt/sources.list.d/"
    rm -f "$rootfs/etc/apt/sources.list"
  fi
  rm -rf "$rootfs/var/lib/apt/lists/"* "$rootfs/var/cache/apt/"*.bin \
    "$rootfs/var/cache/apt/archives/"*.deb
  tar -C "$rootfs" -cf "$tarball.tmp" .
  mv "$tarball.tmp" "$tarball"
  rm -rf "$rootfs"
}
