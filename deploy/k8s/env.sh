# Sourced by every deploy/k8s script: the one place for versions, paths, addresses and ports
# of swarmrec's single-node Kubernetes cluster. Override any of them in the environment.
#
# Two folders, kept apart on purpose:
#   $K8S_CACHE  built binaries and the Go caches (about 6 GB; keyed on versions, survives cluster-down.sh)
#   $K8S_STATE  the running cluster: certificates, etcd, containerd's store, kubelet, logs, pod volumes
#               (removed by cluster-down.sh)
# shellcheck shell=bash

# v1.34: kubelets from v1.35 on refuse cgroup v1 by default, and these machines are cgroup v1.
K8S_VERSION=${SWARMREC_K8S_VERSION:-v1.34.4}
COREDNS_VERSION=${SWARMREC_COREDNS_VERSION:-v1.14.7}
# The k8s.io/* staging modules published alongside k8s.io/kubernetes v1.X.Y are v0.X.Y.
K8S_STAGING_VERSION=v0.${K8S_VERSION#v1.}

K8S_CACHE=${SWARMREC_CACHE:-$HOME/.cache/swarmrec}/k8s
K8S_BIN=$K8S_CACHE/$K8S_VERSION/bin                  # kube-* , kubelet, kubectl, swarmrec-cri-sweep
K8S_SRC=$K8S_CACHE/$K8S_VERSION/src                  # k8s.io/kubernetes source, replaces rewritten
COREDNS_BIN=$K8S_CACHE/coredns-$COREDNS_VERSION/bin  # coredns (only the plugins used here)
K8S_GO=$K8S_CACHE/go                                 # GOMODCACHE and GOCACHE, shared by the versions
PAUSE_TAR=$K8S_CACHE/$K8S_VERSION/images/pause.tar   # the pod sandbox image, built from pause.c
PAUSE_IMAGE=localhost/swarmrec-pause:3.10

K8S_STATE=${SWARMREC_K8S_STATE:-/var/lib/swarmrec-k8s}
KUBECONFIG_ADMIN=$K8S_STATE/etc/admin.kubeconfig
CONTAINERD_SOCK=$K8S_STATE/run/containerd/containerd.sock
# Where the local overlay's hostPath volumes live (k8s/overlays/local names this path too).
K8S_VOLUMES=$K8S_STATE/volumes

K8S_NODE=${SWARMREC_K8S_NODE:-swarmrec-node}
K8S_BRIDGE=swrk8s0   # the pods' CNI bridge (interface names are 15 characters at most)
POD_CIDR=${SWARMREC_K8S_POD_CIDR:-10.244.0.0/24}
POD_GATEWAY=${POD_CIDR%.*/*}.1                       # the bridge's address: CoreDNS answers here
SERVICE_CIDR=${SWARMREC_K8S_SERVICE_CIDR:-10.96.0.0/16}
SERVICE_API_IP=${SERVICE_CIDR%.*/*}.1                # the `kubernetes` Service's ClusterIP
# The comment on cluster-up.sh's rules rejecting Service addresses kube-proxy has not programmed.
K8S_GUARD="swarmrec-k8s: unprogrammed Service addresses stay on this machine"
API_PORT=${SWARMREC_K8S_API_PORT:-6443}
ETCD_CLIENT_PORT=${SWARMREC_K8S_ETCD_PORT:-12379}   # not etcd's 2379: a user's own etcd keeps it
ETCD_PEER_PORT=$((ETCD_CLIENT_PORT + 1))
ETCD_METRICS_PORT=$((ETCD_CLIENT_PORT + 2))
COREDNS_HEALTH_PORT=$((ETCD_CLIENT_PORT + 3))  # CoreDNS's own health and readiness pages, on loopback
COREDNS_READY_PORT=$((ETCD_CLIENT_PORT + 4))

# Processes the scripts start, in start order (cluster-down.sh stops them in reverse).
K8S_DAEMONS="etcd containerd kube-apiserver kube-controller-manager kube-scheduler kubelet kube-proxy coredns"
# The host sysctls the kubelet and kube-proxy change; cluster-up.sh records them, cluster-down.sh restores them.
K8S_SYSCTLS="vm.overcommit_memory vm.panic_on_oom kernel.panic kernel.panic_on_oops net.ipv4.ip_forward
net.bridge.bridge-nf-call-iptables net.bridge.bridge-nf-call-ip6tables net.netfilter.nf_conntrack_max
net.netfilter.nf_conntrack_tcp_timeout_established net.netfilter.nf_conntrack_tcp_timeout_close_wait
kernel.keys.root_maxkeys kernel.keys.root_maxbytes net.ipv4.conf.all.route_localnet"

k8s_path() {  # the cluster's own binaries first, then the system's (sbin for iptables, ip, sysctl)
  echo "$K8S_BIN:$COREDNS_BIN:/usr/local/go/bin:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin"
}
