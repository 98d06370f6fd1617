#!/usr/bin/env bash
# Make sure a container engine answers, and that a compose command exists.
#
# An engine that already answers `docker info` is left alone. Otherwise, on a
# Debian machine, Debian's docker.io package is installed (when missing) and
# dockerd is started in the background; its log goes to $SWARMREC_DOCKERD_LOG
# (default /var/log/swarmrec-dockerd.log). Compose: `docker compose` (v2) when
# the CLI has the plugin, else `docker-compose` (v1.29), installed from
# Debian when neither exists. Prints the compose command it found on the last
# line of stdout, so scripts can `COMPOSE=$(deploy/engine.sh | tail -1)`.
set -euo pipefail

log() { echo "engine: $*" >&2; }
die() { echo "engine: error: $*" >&2; exit 1; }

as_root() {
  if [ "$(id -u)" -eq 0 ]; then "$@"; elif command -v sudo >/dev/null; then sudo "$@"; else
    die "need root to run: $* (no sudo here); install and start a docker engine yourself"
  fi
}

apt_install() {
  command -v apt-get >/dev/null || die "no engine answers and this is not a Debian-like system; install docker yourself"
  log "installing $* from Debian"
  as_root env DEBIAN_FRONTEND=noninteractive apt-get update -qq
  as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "$@" >/dev/null
}

engine_answers() { docker info >/dev/null 2>&1; }

if engine_answers; then
  log "an engine answers; leaving it alone"
else
  command -v dockerd >/dev/null || apt_install docker.io
  command -v docker >/dev/null || die "docker.io installed but no docker CLI on PATH"
  if pgrep -x dockerd >/dev/null; then
    log "dockerd is running but does not answer yet; waiting for it"
  else
    dockerd_log="${SWARMREC_DOCKERD_LOG:-/var/log/swarmrec-dockerd.log}"
    log "starting dockerd (log: $dockerd_log)"
    as_root sh -c "nohup dockerd >>'$dockerd_log' 2>&1 &"
  fi
  for _ in $(seq 1 120); do
    engine_answers && break
    # A dockerd that died (no iptables, no cgroups, ...) will not answer: say why now.
    pgrep -x dockerd >/dev/null || die "dockerd exited; its log ends: $(tail -n 3 "${SWARMREC_DOCKERD_LOG:-/var/log/swarmrec-dockerd.log}" 2>/dev/null)"
    sleep 0.5
  done
  engine_answers || die "dockerd did not answer within 60 s; see ${SWARMREC_DOCKERD_LOG:-/var/log/swarmrec-dockerd.log}"
  log "engine up: $(docker info --format '{{.ServerVersion}} {{.Driver}}')"
fi

if docker compose version >/dev/null 2>&1; then
  echo "docker compose"
else
  command -v docker-compose >/dev/null || apt_install docker-compose
  echo "docker-compose"
fi
