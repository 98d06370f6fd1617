"""Kubernetes benchmark: the cluster's build, its start and stop, and the swarm's pods on it.

    sudo .venv/bin/python bench/bench_k8s_cluster.py --out bench/results/k8s_cluster.json

Figures (2-core machine, single node, deploy/k8s/):

* cold build: the binaries from nothing (Go module downloads, compile), as
  ``deploy/k8s/build-binaries.sh`` recorded it when it built the cache
  (``build-times.json`` beside the binaries). Rebuilding costs about 8 minutes
  and 6 GB, so this script reads that record; ``--cold`` empties the cache
  first and measures it again.
* warm up: ``cluster-up.sh`` with the binaries cached and no cluster running,
  by phase; down: ``cluster-down.sh``, with the swarm's namespace removed first.
* the swarm: the images loaded (``load-images.sh``), the local overlay's identities
  (``swarmrec k8s secrets``: its Namespace and Services, the PKI for its
  ``SWARMREC_MAX_SHARDS`` = 6 robots, the Secrets), the overlay (3 robots, 15 pods)
  applied until every pod is Ready, 100 lock-step steps replayed (300 frames stored,
  so the elastic index has something to hand over), then: a shard pod deleted until
  its successor is Ready and the index has settled again; two of the three deleted
  at once (a node's worth on this single node), likewise; and ``kubectl scale`` of the
  shard StatefulSet 3 -> 6 -> 2 -> 3: until the pods are Ready (or gone), until the
  index has settled on the live shards (every one following one settled placement
  whose members they are, nothing pending), and the descriptors the handoffs copied
  (``swarmrec_shard_handoff_records_total`` of the live shards, read from each pod).
* baseline: the compose swarm's up-to-healthy on the same machine kind
  (bench/results/compose.json, 4 robots = 18 containers).

Leaves no cluster behind (it brings down the one it measured).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import socket
import subprocess
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from swarmrec.client import ZenohClient
from swarmrec.core.placement import Placement
from swarmrec.deployments.identities import client_tls
from swarmrec.deployments.kubernetes import Kubectl, install_identities
from swarmrec.deployments.metrics import read_metrics
from swarmrec.runtime.tls import tls_endpoint

REPO = Path(__file__).resolve().parents[1]
K8S = REPO / "deploy" / "k8s"
NAMESPACE = "swarmrec-bench"
KINDS = ("index-shard", "verifier", "descriptor", "detector")
#: Lock-step steps replayed before the shards are moved (3 robots: 300 frames to hand over).
STEPS = 100


def env_sh() -> dict[str, str]:
    names = ["K8S_VERSION", "K8S_CACHE", "K8S_BIN", "K8S_STATE", "KUBECONFIG_ADMIN", "K8S_VOLUMES"]
    script = f". {K8S / 'env.sh'}; " + "; ".join(f'echo "${n}"' for n in names)
    out = subprocess.run(["bash", "-c", script], capture_output=True, text=True, check=True).stdout
    return dict(zip(names, out.splitlines(), strict=True))


ENV = env_sh()


def timed(cmd: list[str], stdin: str | None = None) -> float:
    t0 = time.perf_counter()
    subprocess.run(cmd, input=stdin, text=True, check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


def kubectl(*args: str, stdin: str | None = None) -> str:
    cmd = [f"{ENV['K8S_BIN']}/kubectl", "--kubeconfig", ENV["KUBECONFIG_ADMIN"], *args]
    return subprocess.run(cmd, input=stdin, capture_output=True, text=True, check=True).stdout


def until(cond: Callable[[], bool], timeout_s: float = 300.0) -> float:
    t0 = time.perf_counter()
    while not cond():
        if time.perf_counter() - t0 > timeout_s:
            raise TimeoutError(f"not after {timeout_s} s")
        time.sleep(0.2)
    return time.perf_counter() - t0


def pods(component: str) -> dict[str, tuple[str, bool]]:
    items = json.loads(
        kubectl(
            "-n", NAMESPACE, "get", "pods", "-l", f"app.kubernetes.io/component={component}", "-o", "json"
        )
    )["items"]
    out = {}
    for p in items:
        ready = any(c["type"] == "Ready" and c["status"] == "True" for c in p["status"].get("conditions", []))
        out[p["metadata"]["name"]] = (
            p["metadata"]["uid"],
            ready and "deletionTimestamp" not in p["metadata"],
        )
    return out


PODS = 3 * len(KINDS) + 3  # the robots' services, router, gateway, Prometheus


def all_ready() -> bool:
    items = json.loads(kubectl("-n", NAMESPACE, "get", "pods", "-o", "json"))["items"]
    return len(items) == PODS and all(
        any(c["type"] == "Ready" and c["status"] == "True" for c in p["status"].get("conditions", []))
        for p in items
    )


def port_open(host: str, port: int) -> bool:
    try:
        with socket.create_connection((host, port), timeout=2.0):
            return True
    except OSError:
        return False


def api_answers() -> bool:
    try:
        kubectl("get", "--raw", "/readyz")
    except (subprocess.CalledProcessError, FileNotFoundError):
        return False
    return True


def shard_counter(name: str) -> dict[tuple[str, str], float]:
    """``name``'s value in each Ready shard pod, read from the pod's own metrics page (the node
    reaches pod addresses), by (pod name, uid): a recreated pod counts from 0 again."""
    items = json.loads(
        kubectl("-n", NAMESPACE, "get", "pods", "-l", "app.kubernetes.io/component=index-shard", "-o", "json")
    )["items"]
    out = {}
    for p in items:
        ip = p["status"].get("podIP")
        if ip and "deletionTimestamp" not in p["metadata"]:
            samples = read_metrics(f"http://{ip}:9464/metrics")
            value = sum(v for (n, _), v in samples.items() if n == name)
            out[(p["metadata"]["name"], p["metadata"]["uid"])] = value
    return out


def settled_on(client: ZenohClient, live: set[int], timeout_s: float = 300.0) -> Placement:
    """The placement once every live shard follows it, settled, with ``live`` its members."""
    deadline = time.perf_counter() + timeout_s
    while True:
        state = client.wait_index_settled(timeout_s=max(deadline - time.perf_counter(), 1.0))
        p = state.placement
        if state.settled and p is not None and set(p.members) == live and set(state.versions) == live:
            return p
        if time.perf_counter() > deadline:
            raise TimeoutError(f"the index did not settle on {sorted(live)}: {state}")
        time.sleep(0.2)


def recreated(old: dict[str, str]) -> bool:
    now = pods("index-shard")
    return all(n in now and now[n][0] != uid and now[n][1] for n, uid in old.items())


def bench_swarm() -> dict[str, Any]:
    out: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp:
        local = os.path.relpath(REPO / "k8s/overlays/local", tmp)
        Path(tmp, "kustomization.yaml").write_text(f"namespace: {NAMESPACE}\nresources: [{local}]\n")
        manifest = kubectl("kustomize", tmp)
        t0 = time.perf_counter()
        cluster = Kubectl((f"{ENV['K8S_BIN']}/kubectl",), Path(ENV["KUBECONFIG_ADMIN"]))
        # Identities for as many shards as the overlay's SWARMREC_MAX_SHARDS (6).
        ids = install_identities(cluster, cluster.objects(manifest), Path(tmp) / "pki")
        out["identities_s"] = time.perf_counter() - t0
        out["max_shards"] = ids.robots
        t0 = time.perf_counter()
        kubectl("apply", "-f", "-", stdin=manifest)
        until(all_ready)
        out[f"apply_to_{PODS}_pods_ready_s"] = time.perf_counter() - t0

        router = tls_endpoint(ids.cluster_ips["router"], 7447)
        until(lambda: port_open(ids.cluster_ips["router"], 7447))
        with ZenohClient([router], ids.swarm, timeout_s=10.0, tls=client_tls(ids.pki, ids.swarm)) as client:
            client.wait_for({(k, r) for k in KINDS for r in range(3)}, timeout_s=120)
            # Something to hand over: the first STEPS lock-step steps of the overlay's synthetic world.
            t0 = time.perf_counter()
            for t in range(STEPS):
                client.step(t, 30.0)
            first = settled_on(client, {0, 1, 2})
            out[f"replay_{STEPS}_steps_and_settle_s"] = time.perf_counter() - t0
            out["stored_slices_per_shard"] = {
                m.robot: m.stored_items for m in client.members() if m.kind == "index-shard"
            }
            out["placement_version_after_replay"] = first.version

            old = {"index-shard-1": pods("index-shard")["index-shard-1"][0]}
            t0 = time.perf_counter()
            kubectl("-n", NAMESPACE, "delete", "pod", "index-shard-1", "--wait=false")
            until(lambda: recreated(old))
            out["shard_pod_delete_to_ready_s"] = time.perf_counter() - t0
            settled_on(client, {0, 1, 2})
            out["shard_pod_delete_to_settled_s"] = time.perf_counter() - t0

            # A node's worth at once on this single node: two of the three shards.
            now = pods("index-shard")
            old = {n: now[n][0] for n in ("index-shard-1", "index-shard-2")}
            t0 = time.perf_counter()
            kubectl("-n", NAMESPACE, "delete", "pod", *old, "--wait=false")
            until(lambda: recreated(old))
            out["two_shard_pods_delete_to_ready_s"] = time.perf_counter() - t0
            first = settled_on(client, {0, 1, 2})
            out["two_shard_pods_delete_to_settled_s"] = time.perf_counter() - t0
            out["placement_version_before_scaling"] = first.version

            # kubectl scale alone: the elastic index moves the label groups.
            for before, after in ((3, 6), (6, 2), (2, 3)):
                copied = shard_counter("swarmrec_shard_handoff_records_total")
                t0 = time.perf_counter()
                kubectl("-n", NAMESPACE, "scale", "statefulset/index-shard", f"--replicas={after}")
                want = [f"index-shard-{r}" for r in range(after)]
                until(
                    lambda want=want: (
                        sorted(p := pods("index-shard")) == want and all(r for _, r in p.values())
                    )
                )
                out[f"scale_{before}_to_{after}_s"] = time.perf_counter() - t0
                placement = settled_on(client, set(range(after)))
                out[f"scale_{before}_to_{after}_settled_s"] = time.perf_counter() - t0
                handed = shard_counter("swarmrec_shard_handoff_records_total")
                # Copied records new to the learner: a shard that held the group before finds
                # its slices in its own record log (its volume) and copies none of them again.
                out[f"scale_{before}_to_{after}_handoff_records"] = sum(
                    v - copied.get(pod, 0.0) for pod, v in handed.items()
                )
                out[f"scale_{before}_to_{after}_placement_versions"] = [first.version, placement.version]
                out[f"scale_{before}_to_{after}_owners"] = [list(o) for o in placement.owners]
                first = placement

    t0 = time.perf_counter()
    kubectl("delete", "namespace", NAMESPACE, "--wait=true", "--timeout=180s")
    out["delete_namespace_s"] = time.perf_counter() - t0
    subprocess.run(["rm", "-rf", f"{ENV['K8S_VOLUMES']}/{NAMESPACE}"], check=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=REPO / "bench/results/k8s_cluster.json")
    ap.add_argument("--cold", action="store_true", help="empty the binary cache and build it again (8 min)")
    args = ap.parse_args()
    if os.geteuid() != 0:
        raise SystemExit("run as root: the cluster runs a kubelet and containerd")

    result: dict[str, Any] = {
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform()},
        "date": time.strftime("%Y-%m-%d"),
        "kubernetes": ENV["K8S_VERSION"],
    }
    if api_answers():
        subprocess.run([str(K8S / "cluster-down.sh")], check=True, stderr=subprocess.DEVNULL)
    if args.cold:
        subprocess.run([str(K8S / "cluster-down.sh"), "--purge"], check=True, stderr=subprocess.DEVNULL)
        result["cold_build_measured_now_s"] = timed([str(K8S / "build-binaries.sh")])
    build = Path(ENV["K8S_CACHE"], ENV["K8S_VERSION"], "build-times.json")
    result["cold_build"] = json.loads(build.read_text()) if build.is_file() else None

    result["warm_up_s"] = timed([str(K8S / "cluster-up.sh")])
    result["warm_up_phases"] = json.loads(Path(ENV["K8S_STATE"], "up-times.json").read_text())
    result["up_when_already_up_s"] = timed([str(K8S / "cluster-up.sh")])
    subprocess.run([str(REPO / "deploy/build.sh")], check=True, stdout=subprocess.DEVNULL)
    result["load_images_s"] = timed([str(K8S / "load-images.sh")])
    result["load_images_again_s"] = timed([str(K8S / "load-images.sh")])
    result["swarm_3_robots"] = bench_swarm()
    result["down_s"] = timed([str(K8S / "cluster-down.sh")])

    compose = json.loads((REPO / "bench/results/compose.json").read_text())
    result["baseline_compose_4_robots_up_to_healthy_s"] = compose["cold_start_4_robots"][
        "compose_up_to_healthy_s"
    ]
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
