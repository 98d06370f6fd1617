// CoreDNS for swarmrec's single-node cluster, with only the plugins its Corefile uses
// (deploy/k8s/cluster-up.sh). CoreDNS's stock main links every plugin, and with them every
// cloud provider's SDK: twice the build time for nothing used here.
//
// There is deliberately no `forward` plugin: the cluster answers cluster.local names and
// nothing else, so no pod's DNS query ever leaves this machine.
package main

import (
	"github.com/coredns/coredns/core/dnsserver"
	"github.com/coredns/coredns/coremain"

	_ "github.com/coredns/coredns/plugin/bind"
	_ "github.com/coredns/coredns/plugin/cache"
	_ "github.com/coredns/coredns/plugin/errors"
	_ "github.com/coredns/coredns/plugin/health"
	_ "github.com/coredns/coredns/plugin/kubernetes"
	_ "github.com/coredns/coredns/plugin/log"
	_ "github.com/coredns/coredns/plugin/ready"
)

func init() {
	// The order plugins run in, as in CoreDNS's plugin.cfg (a plugin missing here is ignored
	// in a Corefile, so this list must name every one linked above).
	dnsserver.Directives = []string{"bind", "ready", "health", "errors", "log", "cache", "kubernetes"}
}

func main() { coremain.Run() }
