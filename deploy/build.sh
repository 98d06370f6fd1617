#!/usr/bin/env bash
# Build the swarm's images: the service image and the Prometheus image.
#
#   deploy/build.sh            engine check, base images when needed, wheelhouse, both images
#
# Base images: $SWARMREC_BASE_IMAGE and $SWARMREC_PROMETHEUS_BASE_IMAGE when set (e.g. the public
# python:3.11-slim-bookworm and debian:bookworm-slim, with a registry); else the public ones when
# they are already present locally; else local ones built by deploy/base-image.sh (no registry).
# Writes the build's timings to deploy/.build-times.json (read by bench/bench_compose.py).
set -euo pipefail
cd "$(dirname "$0")/.."

log() { echo "build: $*" >&2; }

deploy/engine.sh >/dev/null

VERSION=$(sed -n 's/^__version__ = "\(.*\)"/\1/p' swarmrec/__init__.py)
IMAGE=${SWARMREC_IMAGE:-swarmrec:$VERSION}
PROM_IMAGE=${SWARMREC_PROMETHEUS_IMAGE:-swarmrec-prometheus:$VERSION}

have_image() { docker image inspect "$1" >/dev/null 2>&1; }
pick_base() {  # $1: override, $2: public image, $3: local stand-in
  if [ -n "$1" ]; then echo "$1"; elif have_image "$2"; then echo "$2"; else echo "$3"; fi
}
BASE=$(pick_base "${SWARMREC_BASE_IMAGE:-}" python:3.11-slim-bookworm swarmrec-base:bookworm)
PROM_BASE=$(pick_base "${SWARMREC_PROMETHEUS_BASE_IMAGE:-}" debian:bookworm-slim swarmrec-prometheus-base:bookworm)

t0=$(date +%s.%N)
if [ "$BASE" = swarmrec-base:bookworm ] || [ "$PROM_BASE" = swarmrec-prometheus-base:bookworm ]; then
  deploy/base-image.sh
fi
t1=$(date +%s.%N)
deploy/wheelhouse.sh
# The compiled data plane (docs/dataplane.md), built on this Debian bookworm host for the
# bookworm images (it links glibc only), onto the image's PATH beside `swarmrec`.
make -s dataplane
rm -rf deploy/.bin
mkdir -p deploy/.bin
cp target/release/swarmrec-dataplane deploy/.bin/
# The shipped ONNX models, laid out as models/ (swarmrec.models finds them via $SWARMREC_MODELS).
rm -rf deploy/.models
mkdir -p deploy/.models
(cd models && find . -name '*.onnx' -exec cp --parents {} ../deploy/.models/ \;)
t2=$(date +%s.%N)
log "building $IMAGE from $BASE"
docker build --quiet --build-arg BASE_IMAGE="$BASE" -t "$IMAGE" -f deploy/Dockerfile deploy 2> >(grep -v -e DEPRECATED -e "legacy builder" -e buildx -e "^ *$" >&2) >/dev/null
t3=$(date +%s.%N)
log "building $PROM_IMAGE from $PROM_BASE"
docker build --quiet --build-arg BASE_IMAGE="$PROM_BASE" -t "$PROM_IMAGE" deploy/prometheus 2> >(grep -v -e DEPRECATED -e "legacy builder" -e buildx -e "^ *$" >&2) >/dev/null
t4=$(date +%s.%N)

size() { docker image inspect -f '{{.Size}}' "$1"; }
cat > deploy/.build-times.json <<JSON
{"base_images_s": $(awk "BEGIN{print $t1 - $t0}"), "wheelhouse_s": $(awk "BEGIN{print $t2 - $t1}"),
 "service_image_s": $(awk "BEGIN{print $t3 - $t2}"), "prometheus_image_s": $(awk "BEGIN{print $t4 - $t3}"),
 "service_image": "$IMAGE", "service_image_bytes": $(size "$IMAGE"),
 "prometheus_image": "$PROM_IMAGE", "prometheus_image_bytes": $(size "$PROM_IMAGE"),
 "base_image": "$BASE", "prometheus_base_image": "$PROM_BASE"}
JSON
log "$IMAGE $(size "$IMAGE" | numfmt --to=iec), $PROM_IMAGE $(size "$PROM_IMAGE" | numfmt --to=iec)"
