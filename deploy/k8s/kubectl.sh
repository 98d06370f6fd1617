#!/usr/bin/env bash
# kubectl of the cluster's own version, on the cluster deploy/k8s/cluster-up.sh started:
#
#   deploy/k8s/kubectl.sh get pods -n swarmrec
#   deploy/k8s/kubectl.sh apply -k k8s/overlays/local
#
# (The same as `export KUBECONFIG=... PATH=...` with the lines cluster-up.sh prints.)
set -euo pipefail
HERE=$(cd "$(dirname "$0")" && pwd)
# shellcheck source=env.sh
. "$HERE/env.sh"
[ -x "$K8S_BIN/kubectl" ] || { echo "kubectl.sh: no $K8S_BIN/kubectl: run deploy/k8s/build-binaries.sh" >&2; exit 1; }
KUBECONFIG=$KUBECONFIG_ADMIN exec "$K8S_BIN/kubectl" "$@"
