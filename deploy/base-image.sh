#!/usr/bin/env bash
# Build the base images locally, for machines that cannot reach an image registry.
#
#   deploy/base-image.sh [--force]
#
# Makes two images from a Debian bookworm root file system made by debootstrap:
#   swarmrec-base:bookworm             python3 (3.11), python3-venv, ca-certificates: the services' base,
#                                      standing in for python:3.11-slim-bookworm
#   swarmrec-prometheus-base:bookworm  the same plus Debian's prometheus package: the Prometheus image's base,
#                                      standing in for debian:bookworm-slim
# With a registry, skip this script: deploy/build.sh uses the public images unless told otherwise.
# The Debian mirror is the one this machine's apt uses (or $SWARMREC_DEBIAN_MIRROR); nothing is
# downloaded from anywhere else. An image that already exists is kept unless --force.
set -euo pipefail

BASE=swarmrec-base:bookworm
PROM_BASE=swarmrec-prometheus-base:bookworm
SUITE=bookworm

log() { echo "base-image: $*" >&2; }
die() { echo "base-image: error: $*" >&2; exit 1; }

force=0
[ "${1:-}" = "--force" ] && force=1

have_image() { docker image inspect "$1" >/dev/null 2>&1; }
if [ $force = 0 ] && have_image "$BASE" && have_image "$PROM_BASE"; then
  log "$BASE and $PROM_BASE exist (--force rebuilds)"
  exit 0
fi

[ "$(id -u)" -eq 0 ] || die "debootstrap needs root"

mirror() {
  if [ -n "${SWARMREC_DEBIAN_MIRROR:-}" ]; then echo "$SWARMREC_DEBIAN_MIRROR"; return; fi
  # deb822 sources (URIs: ...) first, then one-line sources (deb URI suite ...); the main archive, not security.
  local uri
  uri=$(grep -hs '^URIs:' /etc/apt/sources.list.d/*.sources /etc/apt/sources.list.d/*.list 2>/dev/null \
        | awk '{print $2}' | grep -v security | head -n 1 || true)
  [ -n "$uri" ] || uri=$(grep -hs '^deb ' /etc/apt/sources.list /etc/apt/sources.list.d/*.list 2>/dev/null \
        | awk '{print $2}' | grep -v security | head -n 1 || true)
  [ -n "$uri" ] || die "no Debian mirror in this machine's apt sources; set SWARMREC_DEBIAN_MIRROR"
  echo "$uri"
}

command -v debootstrap >/dev/null || {
  log "installing debootstrap from Debian"
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq debootstrap >/dev/null
}

MIRROR=$(mirror)
ROOT=$(mktemp -d /tmp/swarmrec-rootfs.XXXXXX)
trap 'rm -rf "$ROOT" "$ROOT.log"' EXIT

start=$(date +%s)
log "debootstrap $SUITE from $MIRROR (about a minute)"
debootstrap --variant=minbase --include=python3,python3-venv,ca-certificates "$SUITE" "$ROOT" "$MIRROR" \
  > "$ROOT.log" 2>&1 || { tail -n 20 "$ROOT.log" >&2; die "debootstrap failed (log above)"; }
rm -f "$ROOT.log"

# An image does not need the package lists or the downloaded packages.
clean_rootfs() { rm -rf "$ROOT"/var/cache/apt/archives/*.deb "$ROOT"/var/lib/apt/lists/* "$ROOT"/tmp/*; }

clean_rootfs
log "importing $BASE"
tar -C "$ROOT" -c . | docker import -c 'CMD ["/bin/bash"]' - "$BASE" >/dev/null

log "installing prometheus into the root file system"
# No service may start inside a chroot.
printf '#!/bin/sh\nexit 101\n' > "$ROOT/usr/sbin/policy-rc.d"
chmod +x "$ROOT/usr/sbin/policy-rc.d"
# apt's warnings about running as root in a chroot are expected; its log is shown only on failure.
{ chroot "$ROOT" /usr/bin/env DEBIAN_FRONTEND=noninteractive apt-get update -qq \
  && chroot "$ROOT" /usr/bin/env DEBIAN_FRONTEND=noninteractive \
       apt-get install -y -qq --no-install-recommends prometheus; } > "$ROOT.log" 2>&1 \
  || { tail -n 20 "$ROOT.log" >&2; die "installing prometheus failed (log above)"; }
rm -f "$ROOT.log"
rm -f "$ROOT/usr/sbin/policy-rc.d"
clean_rootfs
log "importing $PROM_BASE"
tar -C "$ROOT" -c . | docker import -c 'CMD ["/bin/bash"]' - "$PROM_BASE" >/dev/null

log "done in $(( $(date +%s) - start )) s: $(docker image inspect -f '{{.Size}}' "$BASE" | numfmt --to=iec) and $(docker image inspect -f '{{.Size}}' "$PROM_BASE" | numfmt --to=iec)"
