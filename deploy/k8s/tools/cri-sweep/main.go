// swarmrec-cri-sweep lists (ls) or stops and removes (rm) every pod sandbox of a CRI runtime.
//
//	swarmrec-cri-sweep SOCKET ls|rm
//
// deploy/k8s/cluster-down.sh runs it after stopping the kubelet. Removing a sandbox through
// the CRI, rather than killing its processes, makes containerd run the CNI DEL of each pod:
// its address, veth, network namespace and iptables rules are released. It stands in for
// `crictl rmp -af`: cri-tools cannot be fetched on these machines.
package main

import (
	"context"
	"fmt"
	"os"
	"path/filepath"
	"time"

	"google.golang.org/grpc"
	"google.golang.org/grpc/credentials/insecure"
	cri "k8s.io/cri-api/pkg/apis/runtime/v1"
)

func main() {
	if len(os.Args) != 3 || (os.Args[2] != "ls" && os.Args[2] != "rm") {
		fmt.Fprintln(os.Stderr, "usage: swarmrec-cri-sweep SOCKET ls|rm")
		os.Exit(2)
	}
	sock, err := filepath.Abs(os.Args[1])
	if err != nil {
		fail(err)
	}
	conn, err := grpc.NewClient("unix://"+sock, grpc.WithTransportCredentials(insecure.NewCredentials()))
	if err != nil {
		fail(err)
	}
	defer conn.Close()
	runtime := cri.NewRuntimeServiceClient(conn)
	ctx, cancel := context.WithTimeout(context.Background(), 120*time.Second)
	defer cancel()
	pods, err := runtime.ListPodSandbox(ctx, &cri.ListPodSandboxRequest{})
	if err != nil {
		fail(err)
	}
	failed := false
	for _, p := range pods.Items {
		fmt.Printf("%s %s/%s %s\n", p.Id[:13], p.Metadata.Namespace, p.Metadata.Name, p.State)
		if os.Args[2] != "rm" {
			continue
		}
		if _, err := runtime.StopPodSandbox(ctx, &cri.StopPodSandboxRequest{PodSandboxId: p.Id}); err != nil {
			fmt.Fprintln(os.Stderr, "  stop:", err)
			failed = true
		}
		if _, err := runtime.RemovePodSandbox(ctx, &cri.RemovePodSandboxRequest{PodSandboxId: p.Id}); err != nil {
			fmt.Fprintln(os.Stderr, "  remove:", err)
			failed = true
		}
	}
	if failed {
		os.Exit(1)
	}
}

func fail(err error) {
	fmt.Fprintln(os.Stderr, "swarmrec-cri-sweep:", err)
	os.Exit(1)
}
