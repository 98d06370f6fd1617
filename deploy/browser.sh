#!/usr/bin/env bash
# Make sure a headless Chromium exists for the live view's browser test, and print its path.
#
# A chromium (or chromium-browser) already on PATH is used as it is. Otherwise, on a Debian
# machine, Debian's chromium package is installed (as root, or with sudo). Nothing is
# downloaded from anywhere but Debian's archive. Prints the browser's path on the last line.
set -euo pipefail

log() { echo "browser: $*" >&2; }
die() { echo "browser: error: $*" >&2; exit 1; }

found() { command -v chromium || command -v chromium-browser || true; }

as_root() {
  if [ "$(id -u)" -eq 0 ]; then "$@"; elif command -v sudo >/dev/null; then sudo "$@"; else
    die "need root to install chromium (no sudo here); install Debian's chromium package yourself"
  fi
}

path=$(found)
if [ -z "$path" ]; then
  command -v apt-get >/dev/null || die "no chromium on PATH and this is not a Debian-like system; install chromium"
  log "installing chromium from Debian"
  as_root env DEBIAN_FRONTEND=noninteractive apt-get update -qq
  as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends chromium >/dev/null
  path=$(found)
  [ -n "$path" ] || die "chromium installed but not on PATH"
fi
echo "$path"
