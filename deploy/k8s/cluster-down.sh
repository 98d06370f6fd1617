#!/usr/bin/env bash
# Stop the cluster deploy/k8s/cluster-up.sh started and undo what it changed on the host:
#
#   sudo deploy/k8s/cluster-down.sh           stop every process, remove the pods' network, iptables
#                                             rules, mounts and cgroups, restore the sysctls, remove
#                                             the cluster's state ($K8S_STATE: etcd, images, volumes)
#   sudo deploy/k8s/cluster-down.sh --purge   the same, and the built binaries and Go caches too
#
# The binary cache ($K8S_CACHE, deploy/k8s/env.sh) stays, so the next cluster-up.sh takes seconds.
# Only what the cluster made is touched: processes from its pid files, shims of its own containerd
# socket, processes in the kubelet's kubepods cgroups, its bridge, and the iptables chains of the
# kubelet, kube-proxy and the CNI plugins. The docker engine and its containerd are left alone.
set -uo pipefail
HERE=$(cd "$(dirname "$0")" && pwd)
# shellcheck source=env.sh
. "$HERE/env.sh"
PATH=$(k8s_path)
export PATH

T0=$(date +%s.%N)
since() { awk -v s="$1" -v n="$(date +%s.%N)" 'BEGIN {printf "%.1f", n - s}'; }
log() { echo "cluster-down [$(since "$T0")s] $*" >&2; }
[ "$(id -u)" = 0 ] || { echo "cluster-down: error: must run as root" >&2; exit 1; }
# It ends with rm -rf of the state folder: an absolute path, not /, no "..".
[[ $K8S_STATE == /?* && $K8S_STATE != *..* ]] \
  || { echo "cluster-down: error: refusing state folder '$K8S_STATE'" >&2; exit 1; }
PURGE=0
[ "${1:-}" = --purge ] && PURGE=1
RUN=$K8S_STATE/run

# stop NAME: SIGTERM, up to 20 s to exit, then SIGKILL; only a live process of the recorded program.
stop() {
  local f=$RUN/pids/$1.pid pid
  [ -f "$f" ] || return 0
  pid=$(cat "$f")
  if [ "$(basename "$(readlink "/proc/$pid/exe" 2>/dev/null)")" = "$(cat "$RUN/pids/$1.exe" 2>/dev/null)" ]; then
    kill "$pid" 2>/dev/null
    for _ in $(seq 40); do kill -0 "$pid" 2>/dev/null || break; sleep 0.5; done
    if kill -0 "$pid" 2>/dev/null; then log "$1 did not exit in 20 s: SIGKILL"; kill -9 "$pid"; fi
    log "stopped $1 (pid $pid)"
  fi
  rm -f "$f" "$RUN/pids/$1.exe"
}

# 1. The kubelet first, so it recreates nothing; then every pod through the CRI, so containerd runs
#    each pod's CNI DEL (its address, veth, network namespace and portmap rules go away).
stop kube-proxy; stop coredns; stop kubelet
if [ -S "$CONTAINERD_SOCK" ] && [ -x "$K8S_BIN/swarmrec-cri-sweep" ]; then
  timeout 120 swarmrec-cri-sweep "$CONTAINERD_SOCK" rm | sed 's/^/cluster-down: removed pod /' >&2
fi
stop kube-scheduler; stop kube-controller-manager; stop kube-apiserver
stop containerd; stop etcd

# 2. Leftovers: shims of our containerd (they name its socket on their command line), processes
#    still in the kubelet's pod cgroups.
for d in /proc/[0-9]*; do
  if tr '\0' ' ' 2>/dev/null < "$d/cmdline" | grep -q -- "-address $CONTAINERD_SOCK"; then
    log "killing leftover shim ${d#/proc/}"; kill -9 "${d#/proc/}" 2>/dev/null
  fi
done
for f in $(find /sys/fs/cgroup/pids/kubepods /sys/fs/cgroup/kubepods.slice /sys/fs/cgroup/kubepods \
             -name cgroup.procs 2>/dev/null); do
  for p in $(cat "$f" 2>/dev/null); do log "killing leftover pod process $p"; kill -9 "$p" 2>/dev/null; done
done

# 3. Mounts under the state folder (pod volumes, sandbox shm, overlay root file systems), deepest first.
grep " $K8S_STATE/" /proc/mounts | awk '{print $2}' | sort -r | while read -r m; do umount -l "$m" 2>/dev/null; done
# libcni's result cache lives in /var/lib/cni whatever the config says: only our network's entries.
for c in /var/lib/cni/results/swarmrec-*; do
  [ -f "$c" ] || continue
  id=${c#/var/lib/cni/results/swarmrec-}; id=${id%-eth0}
  rm -f "$c" "/var/lib/cni/results/cni-loopback-$id-lo"
done

# 4. Networking: kube-proxy's rules (it removes its own), the bridge, the kubelet's and CNI's chains.
[ -x "$K8S_BIN/kube-proxy" ] && kube-proxy --cleanup >/dev/null 2>&1 && log "kube-proxy rules removed"
ip link show "$K8S_BRIDGE" >/dev/null 2>&1 && ip link del "$K8S_BRIDGE" && log "bridge $K8S_BRIDGE removed"
# cluster-up.sh's guard against unprogrammed Service addresses leaving the machine.
while iptables -D OUTPUT -d "$SERVICE_CIDR" -m comment --comment "$K8S_GUARD" -j REJECT 2>/dev/null; do :; done
while iptables -t mangle -D FORWARD -d "$SERVICE_CIDR" -m comment --comment "$K8S_GUARD" -j DROP 2>/dev/null; do :; done
OURS='KUBE-FIREWALL|KUBE-KUBELET-CANARY|CNI-FORWARD|CNI-ADMIN'
for ipt in iptables ip6tables; do
  command -v $ipt >/dev/null || continue
  for table in filter nat mangle; do
    $ipt -t $table -S 2>/dev/null | grep -E -- "^-A (INPUT|OUTPUT|FORWARD|PREROUTING|POSTROUTING) .*-j ($OURS)( |$)" \
      | sed 's/^-A/-D/' | while read -r rule; do eval "$ipt -t $table $rule"; done
    for chain in ${OURS//|/ }; do $ipt -t $table -F "$chain" 2>/dev/null; $ipt -t $table -X "$chain" 2>/dev/null; done
  done
done
# The bridge plugin's masquerade rules for the pod network (chains CNI-<hash>, jumped to from POSTROUTING).
# Only chains that name our pod network: another CNI user's chains (podman's) look the same.
iptables -t nat -S POSTROUTING 2>/dev/null | grep -F -- "-s ${POD_CIDR%.*}." | sed 's/^-A/-D/' \
  | while read -r rule; do eval "iptables -t nat $rule"; done
iptables -t nat -S 2>/dev/null | grep -F -- "-d $POD_CIDR " | sed -n 's/^-A \(CNI-[0-9a-f]\{24\}\) .*/\1/p' \
  | sort -u | while read -r chain; do iptables -t nat -F "$chain"; iptables -t nat -X "$chain" 2>/dev/null; done

# 5. Host settings. The kubelet sets vm.overcommit_memory=1, kernel.panic=10, kernel.panic_on_oops=1 and
#    kernel.keys.*; cluster-up.sh set ip_forward and bridge-nf-call-*. Back to what they were, except the
#    forwarding ones while a docker engine runs: it needs them and set them itself.
if [ -f "$K8S_STATE/sysctl.orig" ]; then
  while IFS='=' read -r key value; do
    case $key in
      net.ipv4.ip_forward|net.bridge.*) pgrep -x dockerd >/dev/null && continue ;;
    esac
    [ "$(sysctl -n "$key" 2>/dev/null)" = "$value" ] || sysctl -qw "$key=$value"
  done < "$K8S_STATE/sysctl.orig"
  log "sysctls restored"
fi
# The kubelet's cgroups (cgroupfs driver), deepest first.
for c in /sys/fs/cgroup/*/kubepods /sys/fs/cgroup/kubepods; do
  [ -d "$c" ] && find "$c" -depth -type d -exec rmdir {} \; 2>/dev/null
done
# Paths the kubelet uses whatever its --root-dir: the log links, and an empty device-plugins folder.
find /var/log/containers -maxdepth 1 -lname "$K8S_STATE/*" -delete 2>/dev/null
[ "$(ls /var/lib/kubelet 2>/dev/null)" = device-plugins ] && rm -rf /var/lib/kubelet

# 6. State; with --purge the cache as well.
rm -rf "$K8S_STATE"
log "state $K8S_STATE removed"
if [ $PURGE = 1 ]; then
  chmod -R u+w "$K8S_GO" 2>/dev/null   # the Go module cache is read-only
  rm -rf "$K8S_CACHE"
  log "cache $K8S_CACHE removed"
fi
log "done"
