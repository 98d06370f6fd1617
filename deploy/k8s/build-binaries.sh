#!/usr/bin/env bash
# Build the cluster's binaries from Go modules, once, into the project's cache (deploy/k8s/env.sh):
#
#   deploy/k8s/build-binaries.sh           kube-apiserver, kube-controller-manager, kube-scheduler, kubelet,
#                                          kube-proxy, kubectl (k8s.io/kubernetes), coredns, swarmrec-cri-sweep,
#                                          and the pause image; skips whatever the cache already holds
#   deploy/k8s/build-binaries.sh kubectl   only these commands of k8s.io/kubernetes (the manifest tests
#                                          need kubectl and the release's OpenAPI documents, not a cluster)
#
# No release binary or image can be downloaded on these machines, but the Go module proxy answers,
# and k8s.io/kubernetes is a Go module. Writes the build's timings to $K8S_CACHE/$K8S_VERSION/build-times.json
# (read by bench/bench_k8s_cluster.py). About 8 minutes on 2 cores from nothing; about 6 GB of Go caches.
set -euo pipefail
HERE=$(cd "$(dirname "$0")" && pwd)
# shellcheck source=env.sh
. "$HERE/env.sh"
PATH=$(k8s_path)
export PATH GOMODCACHE=$K8S_GO/mod GOCACHE=$K8S_GO/build GOTOOLCHAIN=local GOWORK=off CGO_ENABLED=0 \
  GOFLAGS="-buildvcs=false -mod=mod"

T0=$(date +%s.%N)
since() { awk -v s="$1" -v n="$(date +%s.%N)" 'BEGIN {printf "%.1f", n - s}'; }
log() { echo "build [$(since "$T0")s] $*" >&2; }
die() { echo "build: error: $*" >&2; exit 1; }
command -v go >/dev/null || die "needs Go >= 1.24 (the k8s $K8S_VERSION go.mod asks for it) on PATH or in /usr/local/go"
command -v gcc >/dev/null || die "needs gcc (the pause binary is C)"
mkdir -p "$K8S_BIN" "$COREDNS_BIN" "$(dirname "$PAUSE_TAR")" "$K8S_GO"
TIMES=$K8S_CACHE/$K8S_VERSION/build-times.json
declare -A took=()

# --- Kubernetes itself --------------------------------------------------------------------------------
KUBE_CMDS=${*:-kube-apiserver kube-controller-manager kube-scheduler kubelet kube-proxy kubectl}
ONLY=$#   # some commands named: build those, nothing else, and record no timings
missing=""
for b in $KUBE_CMDS; do [ -x "$K8S_BIN/$b" ] || missing="$missing $b"; done
if [ ! -f "$K8S_SRC/go.mod" ]; then
  s=$(date +%s.%N)
  log "go mod download k8s.io/kubernetes@$K8S_VERSION"
  dir=$(go mod download -json "k8s.io/kubernetes@$K8S_VERSION" | python3 -c 'import json, sys; print(json.load(sys.stdin)["Dir"])')
  [ -d "$dir" ] || die "go mod download gave no source directory for k8s.io/kubernetes@$K8S_VERSION"
  rm -rf "$K8S_SRC.tmp"; cp -r "$dir" "$K8S_SRC.tmp"; chmod -R u+w "$K8S_SRC.tmp"
  # The module zip holds neither staging/ (the nested k8s.io/* modules its replaces point at) nor a
  # usable vendor/: require the published k8s.io/* modules of the same release instead.
  (
    cd "$K8S_SRC.tmp"
    rm -rf vendor go.work go.work.sum
    edits=$(sed -n '/^replace (/,/^)/p' go.mod | awk -v v="$K8S_STAGING_VERSION" \
      '$2 == "=>" && $3 ~ /^\.\/staging\// {printf "-dropreplace=%s -require=%s@%s ", $1, $1, v}')
    # shellcheck disable=SC2086 # one word per edit
    go mod edit $edits
  )
  mv "$K8S_SRC.tmp" "$K8S_SRC"
  took[source_s]=$(since "$s")
fi
if [ -n "$missing" ]; then
  minor=$(echo "$K8S_VERSION" | cut -d. -f2)
  # Versions stamped in, so `kubectl version` and the kubelet agree with the apiserver (a build
  # without them says v0.0.0 and the kubelet's version checks complain).
  ldflags="-s -w -X k8s.io/component-base/version.gitVersion=$K8S_VERSION
    -X k8s.io/component-base/version.gitMajor=1 -X k8s.io/component-base/version.gitMinor=$minor
    -X k8s.io/component-base/version.gitTreeState=clean -X k8s.io/client-go/pkg/version.gitVersion=$K8S_VERSION
    -X k8s.io/component-base/version.buildDate=1970-01-01T00:00:00Z"
  s=$(date +%s.%N)
  log "go build$missing (the first time also downloads their dependencies)"
  # One `go build` for all of them: the packages they share are compiled once.
  pkgs=""; for b in $missing; do pkgs="$pkgs ./cmd/$b"; done
  # shellcheck disable=SC2086
  (cd "$K8S_SRC" && go build -trimpath -ldflags "$(echo $ldflags)" -o "$K8S_BIN/" $pkgs)
  took[kubernetes_s]=$(since "$s")
  log "built$missing"
fi

[ "$ONLY" = 0 ] || exit 0

# --- CoreDNS with only the plugins the Corefile uses (its stock main links every cloud SDK) -------------
if [ ! -x "$COREDNS_BIN/coredns" ]; then
  s=$(date +%s.%N)
  work=$K8S_CACHE/coredns-$COREDNS_VERSION/src
  mkdir -p "$work"; cp "$HERE/tools/coredns/main.go" "$work/main.go"
  (
    cd "$work"
    [ -f go.mod ] || go mod init swarmrec.local/coredns >/dev/null 2>&1
    go get "github.com/coredns/coredns@$COREDNS_VERSION" >/dev/null 2>&1
    go mod tidy >/dev/null 2>&1
    go build -trimpath -ldflags "-s -w" -o "$COREDNS_BIN/coredns" .
  )
  took[coredns_s]=$(since "$s")
  log "built coredns $COREDNS_VERSION"
fi

# --- swarmrec-cri-sweep: removes every pod sandbox through CRI (crictl is not obtainable here) ----------
if [ ! -x "$K8S_BIN/swarmrec-cri-sweep" ]; then
  s=$(date +%s.%N)
  work=$K8S_CACHE/$K8S_VERSION/cri-sweep
  mkdir -p "$work"; cp "$HERE/tools/cri-sweep/main.go" "$work/main.go"
  (
    cd "$work"
    [ -f go.mod ] || go mod init swarmrec.local/cri-sweep >/dev/null 2>&1
    go get "k8s.io/cri-api@$K8S_STAGING_VERSION" google.golang.org/grpc >/dev/null 2>&1
    go mod tidy >/dev/null 2>&1
    go build -trimpath -ldflags "-s -w" -o "$K8S_BIN/swarmrec-cri-sweep" .
  )
  took[cri_sweep_s]=$(since "$s")
  log "built swarmrec-cri-sweep"
fi

# --- the pause image: every pod's sandbox runs it; kubeadm would pull registry.k8s.io/pause -------------
if [ ! -f "$PAUSE_TAR" ]; then
  s=$(date +%s.%N)
  rootfs=$(mktemp -d)
  gcc -Os -static -DVERSION=3.10-swarmrec -o "$rootfs/pause" "$K8S_SRC/build/pause/linux/pause.c"
  python3 "$HERE/tools/mkimage.py" "$rootfs" "$PAUSE_IMAGE" "$PAUSE_TAR.tmp" --entrypoint '["/pause"]' >/dev/null
  mv "$PAUSE_TAR.tmp" "$PAUSE_TAR"; rm -rf "$rootfs"
  took[pause_image_s]=$(since "$s")
  log "built $PAUSE_IMAGE"
fi

if [ ${#took[@]} -gt 0 ]; then
  {
    printf '{"k8s_version": "%s", "coredns_version": "%s", "cpus": %s, "go": "%s",\n' \
      "$K8S_VERSION" "$COREDNS_VERSION" "$(nproc)" "$(go env GOVERSION)"
    for k in "${!took[@]}"; do printf ' "%s": %.1f,\n' "$k" "${took[$k]}"; done
    printf ' "total_s": %.1f, "bin_mb": %s, "go_cache_mb": %s}\n' "$(since "$T0")" \
      "$(du -sm "$K8S_BIN" "$COREDNS_BIN" | awk '{s+=$1} END {print s}')" "$(du -sm "$K8S_GO" | cut -f1)"
  } > "$TIMES.tmp"
  # A partial run (only coredns missing, say) must not overwrite the cold build's figures.
  if [ ! -f "$TIMES" ] || [ -n "$missing" ]; then mv "$TIMES.tmp" "$TIMES"; else rm -f "$TIMES.tmp"; fi
  log "binaries in $K8S_BIN and $COREDNS_BIN"
fi
