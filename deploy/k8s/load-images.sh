#!/usr/bin/env bash
# Put the swarm's images into the cluster's containerd, where pods with imagePullPolicy: Never find them:
#
#   sudo deploy/k8s/load-images.sh [IMAGE ...]    default: swarmrec:<version> and swarmrec-prometheus:<version>
#
# The images come from the docker engine (`make images`, i.e. deploy/build.sh, builds them; this script
# runs it when one is missing). `docker save | ctr import` into the "k8s.io" namespace, the one the
# kubelet's CRI reads. An image whose docker id was imported before, and is still there, is skipped.
set -euo pipefail
HERE=$(cd "$(dirname "$0")" && pwd)
REPO=$(cd "$HERE/../.." && pwd)
# shellcheck source=env.sh
. "$HERE/env.sh"
PATH=$(k8s_path)

T0=$(date +%s.%N)
since() { awk -v s="$1" -v n="$(date +%s.%N)" 'BEGIN {printf "%.1f", n - s}'; }
log() { echo "load-images [$(since "$T0")s] $*" >&2; }
die() { echo "load-images: error: $*" >&2; exit 1; }
[ "$(id -u)" = 0 ] || die "must run as root (the cluster's containerd socket is root's)"
[ -S "$CONTAINERD_SOCK" ] || die "the cluster is not up (no $CONTAINERD_SOCK): run deploy/k8s/cluster-up.sh"
CTR="ctr -a $CONTAINERD_SOCK -n k8s.io"

VERSION=$(sed -n 's/^__version__ = "\(.*\)"/\1/p' "$REPO/swarmrec/__init__.py")
IMAGES=("$@")
[ ${#IMAGES[@]} -gt 0 ] || IMAGES=("swarmrec:$VERSION" "swarmrec-prometheus:$VERSION")

"$REPO/deploy/engine.sh" >/dev/null
for image in "${IMAGES[@]}"; do
  if ! docker image inspect "$image" >/dev/null 2>&1; then
    log "$image is not in the docker engine: building the images (deploy/build.sh)"
    "$REPO/deploy/build.sh"
  fi
done

mkdir -p "$K8S_STATE/images"
for image in "${IMAGES[@]}"; do
  id=$(docker image inspect -f '{{.Id}}' "$image")
  # docker save names an image without a registry docker.io/library/NAME; the CRI normalises a pod's
  # `image: NAME:TAG` to the same reference.
  ref=docker.io/library/$image
  [[ $image == */* ]] && ref=$image
  stamp=$K8S_STATE/images/$(echo "$image" | tr '/:' '__').id
  if [ "$(cat "$stamp" 2>/dev/null)" = "$id" ] && $CTR images ls -q | grep -qx "$ref"; then
    log "$image already loaded ($id)"
    continue
  fi
  s=$(date +%s.%N)
  docker save "$image" | $CTR images import - >/dev/null
  echo "$id" > "$stamp"
  log "loaded $image as $ref in $(since "$s")s"
done
