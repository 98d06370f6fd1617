#!/usr/bin/env bash
# A real single-node Kubernetes cluster on this machine, for swarmrec's manifests (k8s/):
#
#   sudo deploy/k8s/cluster-up.sh          idempotent: starts what is not running, changes nothing else
#
# etcd, kube-apiserver, kube-controller-manager, kube-scheduler, a kubelet on its own containerd,
# the CNI bridge, kube-proxy and CoreDNS, all as host processes of this script (there is no systemd
# here to run them). kind, minikube and k3s need images or releases that cannot be downloaded on these
# machines, so the cluster is built from what can: Debian's packages (installed when missing) and the
# Kubernetes binaries built from their Go module (deploy/k8s/build-binaries.sh, once, cached).
# Versions, paths and ports: deploy/k8s/env.sh. Tear down: deploy/k8s/cluster-down.sh.
#
# Prints the time each phase took, writes them to $K8S_STATE/up-times.json, and ends with the
# kubeconfig to use (or use deploy/k8s/kubectl.sh, which sets it).
set -euo pipefail
HERE=$(cd "$(dirname "$0")" && pwd)
# shellcheck source=env.sh
. "$HERE/env.sh"
PATH=$(k8s_path)
export PATH KUBECONFIG=$KUBECONFIG_ADMIN

T0=$(date +%s.%N)
since() { awk -v s="$1" -v n="$(date +%s.%N)" 'BEGIN {printf "%.1f", n - s}'; }
log() { echo "cluster-up [$(since "$T0")s] $*" >&2; }
die() { echo "cluster-up: error: $*" >&2; exit 1; }
[ "$(id -u)" = 0 ] || die "must run as root (it runs a kubelet, containerd and iptables)"

PHASES=()
phase_start=$T0
phase() {  # close the phase that just ended: name it and keep its duration
  local took; took=$(since "$phase_start"); PHASES+=("\"$1_s\": $took"); phase_start=$(date +%s.%N)
  log "$1 done (${took}s)"
}

mkdir -p "$K8S_STATE"/{etc/pki,etc/cni,run/pids,logs,volumes}
RUN=$K8S_STATE/run
PKI=$K8S_STATE/etc/pki

# alive NAME: its pid file names a live process of the same program (pids get reused).
alive() {
  local f=$RUN/pids/$1.pid pid
  [ -f "$f" ] || return 1
  pid=$(cat "$f")
  [ "$(basename "$(readlink "/proc/$pid/exe" 2>/dev/null)")" = "$(cat "$RUN/pids/$1.exe" 2>/dev/null)" ]
}
# start NAME CMD...: a daemon in its own session, its log in $K8S_STATE/logs/NAME.log.
start() {
  local name=$1; shift
  if alive "$name"; then log "$name already running (pid $(cat "$RUN/pids/$name.pid"))"; return; fi
  basename "$(command -v "$1")" > "$RUN/pids/$name.exe"
  setsid "$@" >>"$K8S_STATE/logs/$name.log" 2>&1 </dev/null &
  echo $! > "$RUN/pids/$name.pid"
  log "started $name (pid $!, log $K8S_STATE/logs/$name.log)"
}
# putfile PATH < CONTENT: write only when the content changes. kube-proxy exits ("configuration
# file was updated") when its config file is rewritten under it, even with the same bytes.
putfile() {
  local tmp; tmp=$(mktemp)
  cat > "$tmp"
  if cmp -s "$tmp" "$1"; then rm -f "$tmp"; else chmod 644 "$tmp"; mv "$tmp" "$1"; fi
}
# waitfor WHAT SECONDS CMD...: until CMD succeeds; on time-out, show the log that says why.
waitfor() {
  local what=$1 limit=$2 logname=${WAIT_LOG:-}; shift 2
  local deadline=$(( $(date +%s) + limit ))
  until timeout 10 "$@" >/dev/null 2>&1; do
    if [ "$(date +%s)" -ge "$deadline" ]; then
      [ -n "$logname" ] && tail -n 20 "$K8S_STATE/logs/$logname.log" >&2
      die "$what not ready after ${limit}s"
    fi
    sleep 0.5
  done
}

# ---- 1. Debian packages -----------------------------------------------------------------------------
need=""
for p in etcd-server containerd runc containernetworking-plugins iptables conntrack openssl gcc libc6-dev; do
  dpkg -s "$p" >/dev/null 2>&1 || need="$need $p"
done
if [ -n "$need" ]; then
  log "apt-get install$need"
  # Their maintainer scripts would start Debian's own etcd and containerd services: refuse that (the
  # cluster runs its own instances, with its own ports and sockets) with a policy-rc.d for the install.
  policy=/usr/sbin/policy-rc.d made_policy=0
  if [ ! -e $policy ]; then printf '#!/bin/sh\nexit 101\n' > $policy; chmod +x $policy; made_policy=1; fi
  trap '[ $made_policy = 1 ] && rm -f $policy' EXIT
  DEBIAN_FRONTEND=noninteractive apt-get update -qq
  # shellcheck disable=SC2086
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $need >/dev/null
  [ $made_policy = 1 ] && rm -f $policy
  trap - EXIT
fi
phase packages

# ---- 2. binaries (built once into the cache) --------------------------------------------------------
"$HERE/build-binaries.sh"
phase binaries

# ---- 3. the host: kernel features, sysctls ----------------------------------------------------------
grep -qw overlay /proc/filesystems || modprobe overlay || die "no overlay file system (containerd's snapshotter needs it)"
[ -d /proc/sys/net/bridge ] || modprobe br_netfilter || die "no br_netfilter (Services need bridged traffic to pass iptables)"
# Record, once, every sysctl the cluster may change, so cluster-down.sh puts them back.
if [ ! -f "$K8S_STATE/sysctl.orig" ]; then
  for key in $K8S_SYSCTLS; do sysctl -n "$key" >/dev/null 2>&1 && echo "$key=$(sysctl -n "$key")"; done \
    > "$K8S_STATE/sysctl.orig"
fi
sysctl -qw net.ipv4.ip_forward=1 net.bridge.bridge-nf-call-iptables=1 net.bridge.bridge-nf-call-ip6tables=1
CGROUP=$( [ "$(stat -fc %T /sys/fs/cgroup)" = cgroup2fs ] && echo v2 || echo v1 )
# systemd's cgroup driver only where systemd runs the machine (not here: no systemd as PID 1).
if [ "$CGROUP" = v2 ] && [ "$(ps -p 1 -o comm=)" = systemd ]; then CGDRIVER=systemd; else CGDRIVER=cgroupfs; fi
if [ -z "$(swapon --show 2>/dev/null)" ]; then FAIL_SWAP=true; else FAIL_SWAP=false; fi
# The pods' bridge, made before anything binds its address: the node's address is the bridge's
# gateway (always this machine's own, whatever its other interfaces), and CoreDNS answers there.
ip link show "$K8S_BRIDGE" >/dev/null 2>&1 || ip link add "$K8S_BRIDGE" type bridge
ip -4 addr show dev "$K8S_BRIDGE" | grep -q "inet $POD_GATEWAY/" || ip addr add "$POD_GATEWAY/${POD_CIDR#*/}" dev "$K8S_BRIDGE"
ip link set "$K8S_BRIDGE" up
# Nothing of the cluster's may leave the machine. A Service address kube-proxy has not programmed
# yet (a pod or the host connecting a moment before the Service's rules exist) would follow the
# host's default route out of the machine; this was seen. Stop it instead: once kube-proxy's DNAT
# has rewritten a packet its destination is a pod's, so only unprogrammed Service addresses match.
# The host's own packets: rejected in filter OUTPUT (after the DNAT of nat OUTPUT). Forwarded ones
# (from pods): dropped in mangle FORWARD, which runs before the filter FORWARD rules that the CNI
# firewall plugin and docker put first and that accept pod traffic. (A route would not do: the
# host's own connections are routed before the DNAT.) The pods have no default route either: the
# CNI config below gives them their subnet and the Service range only.
guard() {  # TABLE CHAIN TARGET: the rule, once, first in its chain
  iptables -t "$1" -C "$2" -d "$SERVICE_CIDR" -m comment --comment "$K8S_GUARD" -j "$3" 2>/dev/null \
    || iptables -t "$1" -I "$2" 1 -d "$SERVICE_CIDR" -m comment --comment "$K8S_GUARD" -j "$3"
}
guard filter OUTPUT REJECT
guard mangle FORWARD DROP
NODE_IP=$POD_GATEWAY
log "node $K8S_NODE at $NODE_IP, cgroup $CGROUP ($CGDRIVER driver)"
phase host

# ---- 4. certificates: one cluster CA, a certificate per component (what kubeadm would make) ---------
# ECDSA P-256 keys: every component accepts them, and ten of them take milliseconds (RSA: seconds).
KEY="-newkey ec -pkeyopt ec_paramgen_curve:prime256v1"
if [ ! -f "$PKI/ca.crt" ]; then
  # shellcheck disable=SC2086
  openssl req -x509 $KEY -nodes -keyout "$PKI/ca.key" -out "$PKI/ca.crt" -days 3650 \
    -subj "/CN=swarmrec-k8s-ca" 2>/dev/null
  openssl ecparam -name prime256v1 -genkey -noout -out "$PKI/sa.key"   # signs service-account tokens
  openssl ec -in "$PKI/sa.key" -pubout -out "$PKI/sa.pub" 2>/dev/null
fi
cert() {  # NAME CN [O] [SANS]: a client certificate, a server one too when SANS are given
  [ -f "$PKI/$1.crt" ] && return
  local ext
  ext="basicConstraints=CA:FALSE
keyUsage=critical,digitalSignature,keyEncipherment
extendedKeyUsage=${4:+serverAuth,}clientAuth${4:+
subjectAltName=$4}"
  # shellcheck disable=SC2086
  openssl req $KEY -nodes -keyout "$PKI/$1.key" -out "$PKI/$1.csr" -subj "/CN=$2${3:+/O=$3}" 2>/dev/null
  openssl x509 -req -in "$PKI/$1.csr" -CA "$PKI/ca.crt" -CAkey "$PKI/ca.key" -CAcreateserial \
    -out "$PKI/$1.crt" -days 3650 -extfile <(echo "$ext") 2>/dev/null
  rm -f "$PKI/$1.csr"
}
# Who is who: the CN is the user name, the O the group the apiserver's RBAC and Node authorizer read.
cert apiserver kube-apiserver "" "DNS:kubernetes,DNS:kubernetes.default,DNS:kubernetes.default.svc,DNS:kubernetes.default.svc.cluster.local,DNS:localhost,IP:127.0.0.1,IP:$SERVICE_API_IP,IP:$NODE_IP"
cert apiserver-kubelet-client kube-apiserver-kubelet-client system:masters
cert admin swarmrec-admin system:masters
cert controller-manager system:kube-controller-manager
cert scheduler system:kube-scheduler
cert kube-proxy system:kube-proxy                      # bound to system:node-proxier by default
cert coredns system:coredns                            # bound below, to read Services and EndpointSlices
cert kubelet "system:node:$K8S_NODE" system:nodes      # the Node authorizer's naming
cert kubelet-server "$K8S_NODE" "" "DNS:$K8S_NODE,IP:$NODE_IP,IP:127.0.0.1"
kubeconfig() {  # NAME: $K8S_STATE/etc/NAME.kubeconfig with NAME's certificate, written directly
  local f=$K8S_STATE/etc/$1.kubeconfig   # (four `kubectl config` runs each took seconds in all)
  [ -f "$f" ] && return
  (
    umask 077
    cat > "$f" <<EOF
apiVersion: v1
kind: Config
clusters:
  - name: swarmrec
    cluster:
      server: https://127.0.0.1:$API_PORT
      certificate-authority-data: $(base64 -w0 < "$PKI/ca.crt")
users:
  - name: $1
    user:
      client-certificate-data: $(base64 -w0 < "$PKI/$1.crt")
      client-key-data: $(base64 -w0 < "$PKI/$1.key")
contexts:
  - name: swarmrec
    context: { cluster: swarmrec, user: $1 }
current-context: swarmrec
EOF
  )
}
for c in admin controller-manager scheduler kube-proxy kubelet coredns; do kubeconfig $c; done
phase certificates

# ---- 5. etcd (Debian's), on its own ports and data folder -------------------------------------------
WAIT_LOG=etcd
start etcd etcd --name swarmrec --data-dir "$K8S_STATE/etcd" \
  --listen-client-urls "http://127.0.0.1:$ETCD_CLIENT_PORT" --advertise-client-urls "http://127.0.0.1:$ETCD_CLIENT_PORT" \
  --listen-peer-urls "http://127.0.0.1:$ETCD_PEER_PORT" --initial-advertise-peer-urls "http://127.0.0.1:$ETCD_PEER_PORT" \
  --initial-cluster "swarmrec=http://127.0.0.1:$ETCD_PEER_PORT" --listen-metrics-urls "http://127.0.0.1:$ETCD_METRICS_PORT"
waitfor etcd 60 python3 -c "import urllib.request as u; u.urlopen('http://127.0.0.1:$ETCD_CLIENT_PORT/health', timeout=2)"
phase etcd

# ---- 6. containerd: an instance of our own (socket, root, state, runc root), so it never meets the
#         containerd that runs the docker engine on the same machine --------------------------------
# Without CAP_SYS_RESOURCE in the bounding set (these VMs), runc cannot write the negative
# oom_score_adj the CRI asks for a pod sandbox ("failed to update /proc/self/oom_score_adj:
# Permission denied"); containerd then clamps it to what it may set.
capbnd=$(awk '/^CapBnd/ {print $2}' /proc/self/status)
if (( (0x$capbnd >> 24) & 1 )); then RESTRICT_OOM=false; else RESTRICT_OOM=true; fi
mkdir -p "$(dirname "$CONTAINERD_SOCK")"
putfile "$K8S_STATE/etc/containerd.toml" <<EOF
# Written by deploy/k8s/cluster-up.sh.
version = 2
root = "$K8S_STATE/containerd"
state = "$RUN/containerd/state"
[grpc]
  address = "$CONTAINERD_SOCK"
[ttrpc]
  address = "$RUN/containerd/ttrpc.sock"
[plugins."io.containerd.grpc.v1.cri"]
  sandbox_image = "$PAUSE_IMAGE"
  restrict_oom_score_adj = $RESTRICT_OOM
  [plugins."io.containerd.grpc.v1.cri".containerd]
    snapshotter = "overlayfs"
    default_runtime_name = "runc"
    [plugins."io.containerd.grpc.v1.cri".containerd.runtimes.runc]
      runtime_type = "io.containerd.runc.v2"
      [plugins."io.containerd.grpc.v1.cri".containerd.runtimes.runc.options]
        SystemdCgroup = $( [ $CGDRIVER = systemd ] && echo true || echo false )
        Root = "$RUN/runc"
  [plugins."io.containerd.grpc.v1.cri".cni]
    bin_dir = "/usr/lib/cni"
    conf_dir = "$K8S_STATE/etc/cni"
EOF
# One bridge network for the node's pods. The firewall plugin: the docker engine sets the FORWARD
# policy to DROP, and this plugin's rules let the pods' traffic through anyway. Routes: the pods'
# subnet (on the bridge) and the Service range (through the node, where kube-proxy rewrites it);
# no default route, so no pod can reach beyond this machine.
putfile "$K8S_STATE/etc/cni/10-swarmrec.conflist" <<EOF
{
  "cniVersion": "1.0.0",
  "name": "swarmrec",
  "plugins": [
    { "type": "bridge", "bridge": "$K8S_BRIDGE", "isGateway": true, "ipMasq": true, "hairpinMode": true,
      "ipam": { "type": "host-local", "dataDir": "$K8S_STATE/cni-ipam",
                "ranges": [[{ "subnet": "$POD_CIDR", "gateway": "$POD_GATEWAY" }]],
                "routes": [{ "dst": "$SERVICE_CIDR" }] } },
    { "type": "portmap", "capabilities": { "portMappings": true } },
    { "type": "firewall" }
  ]
}
EOF
WAIT_LOG=containerd
start containerd containerd --config "$K8S_STATE/etc/containerd.toml"
waitfor containerd 60 ctr -a "$CONTAINERD_SOCK" version
CTR="ctr -a $CONTAINERD_SOCK -n k8s.io"
# The sandbox image every pod starts with, made by build-binaries.sh (no registry to pull it from).
$CTR images ls -q | grep -qx "$PAUSE_IMAGE" || $CTR images import "$PAUSE_TAR" >/dev/null
phase containerd

# ---- 7. control plane -------------------------------------------------------------------------------
# --kubelet-preferred-address-types: `kubectl logs/exec` reach the kubelet at the node's own address.
WAIT_LOG=kube-apiserver
start kube-apiserver kube-apiserver --etcd-servers="http://127.0.0.1:$ETCD_CLIENT_PORT" \
  --bind-address=0.0.0.0 --secure-port="$API_PORT" --advertise-address="$NODE_IP" \
  --tls-cert-file="$PKI/apiserver.crt" --tls-private-key-file="$PKI/apiserver.key" --client-ca-file="$PKI/ca.crt" \
  --kubelet-client-certificate="$PKI/apiserver-kubelet-client.crt" --kubelet-client-key="$PKI/apiserver-kubelet-client.key" \
  --kubelet-certificate-authority="$PKI/ca.crt" --kubelet-preferred-address-types=InternalIP,Hostname \
  --service-cluster-ip-range="$SERVICE_CIDR" --service-account-issuer=https://kubernetes.default.svc.cluster.local \
  --service-account-key-file="$PKI/sa.pub" --service-account-signing-key-file="$PKI/sa.key" \
  --authorization-mode=Node,RBAC --enable-admission-plugins=NodeRestriction
waitfor kube-apiserver 180 kubectl get --raw /readyz
# Both run alone on this node: no leader election to wait for.
start kube-controller-manager kube-controller-manager --kubeconfig="$K8S_STATE/etc/controller-manager.kubeconfig" \
  --authentication-kubeconfig="$K8S_STATE/etc/controller-manager.kubeconfig" \
  --authorization-kubeconfig="$K8S_STATE/etc/controller-manager.kubeconfig" \
  --bind-address=127.0.0.1 --leader-elect=false --use-service-account-credentials=true \
  --service-account-private-key-file="$PKI/sa.key" --root-ca-file="$PKI/ca.crt" \
  --cluster-signing-cert-file="$PKI/ca.crt" --cluster-signing-key-file="$PKI/ca.key" \
  --service-cluster-ip-range="$SERVICE_CIDR"
start kube-scheduler kube-scheduler --kubeconfig="$K8S_STATE/etc/scheduler.kubeconfig" \
  --authentication-kubeconfig="$K8S_STATE/etc/scheduler.kubeconfig" \
  --authorization-kubeconfig="$K8S_STATE/etc/scheduler.kubeconfig" --bind-address=127.0.0.1 --leader-elect=false
# CoreDNS's identity may read what it serves, nothing more (the rules of CoreDNS's own manifests).
kubectl apply -f - >/dev/null <<'EOF'
apiVersion: rbac.authorization.k8s.io/v1
kind: ClusterRole
metadata: { name: "system:coredns" }
rules:
  - { apiGroups: [""], resources: [endpoints, services, pods, namespaces], verbs: [list, watch] }
  - { apiGroups: [discovery.k8s.io], resources: [endpointslices], verbs: [list, watch] }
---
apiVersion: rbac.authorization.k8s.io/v1
kind: ClusterRoleBinding
metadata: { name: "system:coredns" }
roleRef: { apiGroup: rbac.authorization.k8s.io, kind: ClusterRole, name: "system:coredns" }
subjects: [ { apiGroup: rbac.authorization.k8s.io, kind: User, name: "system:coredns" } ]
EOF
phase control_plane

# ---- 8. kubelet --------------------------------------------------------------------------------------
# Pods whose dnsPolicy is Default get this resolv.conf instead of the host's: CoreDNS, which answers
# cluster names only, so no pod's DNS query leaves the machine.
putfile "$K8S_STATE/etc/resolv.conf" <<EOF
nameserver $POD_GATEWAY
EOF
putfile "$K8S_STATE/etc/kubelet.yaml" <<EOF
# Written by deploy/k8s/cluster-up.sh.
apiVersion: kubelet.config.k8s.io/v1beta1
kind: KubeletConfiguration
authentication: { anonymous: { enabled: false }, webhook: { enabled: false }, x509: { clientCAFile: "$PKI/ca.crt" } }
authorization: { mode: AlwaysAllow }
tlsCertFile: "$PKI/kubelet-server.crt"
tlsPrivateKeyFile: "$PKI/kubelet-server.key"
cgroupDriver: $CGDRIVER
# v1.34 still runs on cgroup v1 (these machines), when told to.
failCgroupV1: false
containerRuntimeEndpoint: "unix://$CONTAINERD_SOCK"
clusterDNS: [ "$POD_GATEWAY" ]
clusterDomain: cluster.local
resolvConf: "$K8S_STATE/etc/resolv.conf"
failSwapOn: $FAIL_SWAP
podLogsDir: "$K8S_STATE/pod-logs"
readOnlyPort: 0
healthzBindAddress: 127.0.0.1
# The images cannot be pulled again (imagePullPolicy: Never, no registry): never collect them.
imageGCHighThresholdPercent: 100
imageGCLowThresholdPercent: 99
evictionHard: { "memory.available": "100Mi", "nodefs.available": "1%", "imagefs.available": "1%" }
EOF
WAIT_LOG=kubelet
start kubelet kubelet --config="$K8S_STATE/etc/kubelet.yaml" --kubeconfig="$K8S_STATE/etc/kubelet.kubeconfig" \
  --root-dir="$K8S_STATE/kubelet" --hostname-override="$K8S_NODE" --node-ip="$NODE_IP"
waitfor "node $K8S_NODE" 180 kubectl wait --for=condition=Ready "node/$K8S_NODE" --timeout=5s
phase kubelet

# ---- 9. Services: kube-proxy (ClusterIPs, iptables) and CoreDNS (names), on the host ----------------
# conntrack 0s / 0: leave the host's conntrack sysctls as they are; no localhost NodePorts, so
# route_localnet stays unset.
putfile "$K8S_STATE/etc/kube-proxy.yaml" <<EOF
# Written by deploy/k8s/cluster-up.sh.
apiVersion: kubeproxy.config.k8s.io/v1alpha1
kind: KubeProxyConfiguration
clientConnection: { kubeconfig: "$K8S_STATE/etc/kube-proxy.kubeconfig" }
mode: iptables
iptables: { localhostNodePorts: false }
clusterCIDR: "$POD_CIDR"
hostnameOverride: "$K8S_NODE"
bindAddress: 127.0.0.1
healthzBindAddress: 127.0.0.1:10256
metricsBindAddress: 127.0.0.1:10249
conntrack: { maxPerCore: 0, min: 0, tcpEstablishedTimeout: 0s, tcpCloseWaitTimeout: 0s }
EOF
WAIT_LOG=kube-proxy
start kube-proxy kube-proxy --config="$K8S_STATE/etc/kube-proxy.yaml"
waitfor kube-proxy 60 python3 -c "import urllib.request as u; u.urlopen('http://127.0.0.1:10256/healthz', timeout=2)"
# A short cache: StatefulSets scale, and a headless name should follow within seconds.
putfile "$K8S_STATE/etc/Corefile" <<EOF
# Written by deploy/k8s/cluster-up.sh. Cluster names only (no forward plugin is built in).
.:53 {
    bind $POD_GATEWAY
    errors
    health 127.0.0.1:$COREDNS_HEALTH_PORT
    ready 127.0.0.1:$COREDNS_READY_PORT
    kubernetes cluster.local in-addr.arpa ip6.arpa {
        kubeconfig $K8S_STATE/etc/coredns.kubeconfig swarmrec
        pods insecure
    }
    cache 5
}
EOF
WAIT_LOG=coredns
start coredns coredns -conf "$K8S_STATE/etc/Corefile"
# Answers = resolves the apiserver's Service name to its ClusterIP.
waitfor "CoreDNS" 60 python3 "$HERE/tools/dnsquery.py" "$POD_GATEWAY" kubernetes.default.svc.cluster.local "$SERVICE_API_IP"
# Pods of a namespace need its default service account, which the controller-manager makes.
waitfor "default service account" 60 kubectl get serviceaccount default
phase services

printf '{"total_s": %s, %s}\n' "$(since "$T0")" "$(IFS=,; echo "${PHASES[*]}" | sed 's/,/, /g')" > "$K8S_STATE/up-times.json"
kubectl get nodes -o wide >&2
log "cluster up. Use it with:"
echo "export KUBECONFIG=$KUBECONFIG_ADMIN PATH=$K8S_BIN:\$PATH"
