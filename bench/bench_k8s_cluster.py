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
  (``swarmrec k8s secrets``: its Namespace and Services, the PKI for 6 robots, the
  Secrets), the overlay (3 robots, 15 pods) applied until every pod is Ready, a shard
  pod deleted until its successor is Ready, and ``kubectl scale`` of the shard
  StatefulSet 3 -> 6 -> 2 -> 3 until the pods are Ready (or gone).
* baseline: the compose swarm's up-to-healthy on the same machine kind
  (bench/results/compose.json, 4 robots = 18 containers).

Leaves no cluster behind (it brings down the one it measured).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from swarmrec.deployments.kubernetes import Kubectl, install_identities

REPO = Path(__file__).resolve().parents[1]
K8S = REPO / "deploy" / "k8s"
NAMESPACE = "swarmrec-bench"
KINDS = ("index-shard", "verifier", "descriptor", "detector")


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


def api_answers() -> bool:
    try:
        kubectl("get", "--raw", "/readyz")
    except (subprocess.CalledProcessError, FileNotFoundError):
        return False
    return True


def bench_swarm() -> dict[str, Any]:
    out: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp:
        local = os.path.relpath(REPO / "k8s/overlays/local", tmp)
        Path(tmp, "kustomization.yaml").write_text(f"namespace: {NAMESPACE}\nresources: [{local}]\n")
        manifest = kubectl("kustomize", tmp)
        t0 = time.perf_counter()
        cluster = Kubectl((f"{ENV['K8S_BIN']}/kubectl",), Path(ENV["KUBECONFIG_ADMIN"]))
        install_identities(cluster, cluster.objects(manifest), Path(tmp) / "pki", max_robots=6)
        out["identities_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    kubectl("apply", "-f", "-", stdin=manifest)
    until(all_ready)
    out[f"apply_to_{PODS}_pods_ready_s"] = time.perf_counter() - t0

    old = pods("index-shard")["index-shard-1"][0]
    t0 = time.perf_counter()
    kubectl("-n", NAMESPACE, "delete", "pod", "index-shard-1", "--wait=false")
    until(lambda: (p := pods("index-shard").get("index-shard-1")) is not None and p[0] != old and p[1])
    out["shard_pod_delete_to_ready_s"] = time.perf_counter() - t0

    sts = json.loads(kubectl("-n", NAMESPACE, "get", "statefulset", "index-shard", "-o", "json"))
    configmap = sts["spec"]["template"]["spec"]["containers"][0]["envFrom"][0]["configMapRef"]["name"]
    for before, after in ((3, 6), (6, 2), (2, 3)):
        patch = json.dumps({"data": {"SWARMREC_N_ROBOTS": str(after)}})
        kubectl("-n", NAMESPACE, "patch", "configmap", configmap, "--type", "merge", "-p", patch)
        t0 = time.perf_counter()
        kubectl("-n", NAMESPACE, "scale", "statefulset/index-shard", f"--replicas={after}")
        want = [f"index-shard-{r}" for r in range(after)]
        until(lambda want=want: sorted(p := pods("index-shard")) == want and all(r for _, r in p.values()))
        out[f"scale_{before}_to_{after}_s"] = time.perf_counter() - t0

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
