"""The swarm on a real Kubernetes cluster: deploy/k8s/cluster-up.sh's single node, the swarm's
images loaded into its containerd, the local overlay (k8s/overlays/local) applied with 3 robots
in a namespace of this run's own.

Real pods, real kubelet, kube-proxy and CoreDNS: nothing is simulated. A cluster that is already
up is reused (and left up); one this module started is brought down at the end unless
``SWARMREC_K8S_KEEP=1``. The namespace, and its pods' folders on the node, are removed either way.
The tests run in file order: the replay fills the shards, the pod deletion and the scaling then
check that their records stay.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from swarmrec.services.common import label_bounds_of
from swarmrec.services.config import ServiceSettings
from swarmrec.swarm.attached import main_attached

from swarmrec.client import SwarmClient
from tests.conftest import REPO
from tests.unit.test_k8s_manifests import ROBOT_KINDS, cluster_env

ROBOTS, FRAMES = 3, 300
KEEP = os.environ.get("SWARMREC_K8S_KEEP") == "1"
WORKLOADS = [("deployment", "router"), ("deployment", "prometheus")] + [
    ("statefulset", k) for k in ROBOT_KINDS
]


def _run(cmd: list[str], timeout_s: float, stdin: str | None = None) -> subprocess.CompletedProcess[str]:
    try:
        done = subprocess.run(
            cmd, input=stdin, capture_output=True, text=True, timeout=timeout_s, check=False
        )
    except subprocess.TimeoutExpired:
        pytest.fail(f"{' '.join(cmd)} did not finish in {timeout_s:g} s")
    if done.returncode != 0:
        pytest.fail(f"{' '.join(cmd)} failed ({done.returncode}):\n{done.stderr[-4000:]}")
    return done


@dataclass
class Cluster:
    """The running cluster, driven with its own kubectl."""

    started_here: bool
    timings: dict[str, float] = field(default_factory=dict)

    def kubectl(self, *args: str, stdin: str | None = None, timeout_s: float = 120.0) -> str:
        env = cluster_env()
        cmd = [str(Path(env["K8S_BIN"]) / "kubectl"), "--kubeconfig", env["KUBECONFIG_ADMIN"], *args]
        return _run(cmd, timeout_s, stdin).stdout

    def json(self, *args: str) -> Any:
        return json.loads(self.kubectl(*args, "-o", "json"))


def _api_answers() -> bool:
    env = cluster_env()
    kubectl = Path(env["K8S_BIN"]) / "kubectl"
    if not kubectl.is_file() or not Path(env["KUBECONFIG_ADMIN"]).is_file():
        return False
    probe = [str(kubectl), "--kubeconfig", env["KUBECONFIG_ADMIN"], "get", "--raw", "/readyz"]
    return subprocess.run(probe, capture_output=True, timeout=20, check=False).returncode == 0


@pytest.fixture(scope="module")
def cluster() -> Iterator[Cluster]:
    if os.geteuid() != 0:
        pytest.fail("the Kubernetes tests run a kubelet and containerd: run them as root")
    was_up = _api_answers()
    c = Cluster(started_here=not was_up)
    t0 = time.monotonic()
    _run([str(REPO / "deploy/k8s/cluster-up.sh")], timeout_s=1800)
    c.timings["cluster_up_s"] = time.monotonic() - t0
    try:
        yield c
    finally:
        if c.started_here and not KEEP:
            _run([str(REPO / "deploy/k8s/cluster-down.sh")], timeout_s=300)


@pytest.fixture(scope="module")
def loaded(cluster: Cluster, images: None) -> Cluster:
    """The images deploy/build.sh made (tests/e2e/conftest.py), in the cluster's containerd."""
    t0 = time.monotonic()
    _run([str(REPO / "deploy/k8s/load-images.sh")], timeout_s=900)
    cluster.timings["load_images_s"] = time.monotonic() - t0
    return cluster


@dataclass
class Swarm:
    cluster: Cluster
    namespace: str
    swarm: str
    manifest: str
    dry_run: str
    timings: dict[str, float]

    def k(self, *args: str, timeout_s: float = 120.0) -> str:
        return self.cluster.kubectl("-n", self.namespace, *args, timeout_s=timeout_s)

    def pods(self, component: str) -> dict[str, dict[str, Any]]:
        """Pod name -> {uid, ready, ip} of one component."""
        items = self.cluster.json(
            "-n", self.namespace, "get", "pods", "-l", f"app.kubernetes.io/component={component}"
        )
        out = {}
        for p in items["items"]:
            conditions = {c["type"]: c["status"] for c in p["status"].get("conditions", [])}
            out[p["metadata"]["name"]] = {
                "uid": p["metadata"]["uid"],
                "ready": conditions.get("Ready") == "True" and "deletionTimestamp" not in p["metadata"],
            }
        return out

    def cluster_ip(self, service: str) -> str:
        ip: str = self.cluster.json("-n", self.namespace, "get", "service", service)["spec"]["clusterIP"]
        return ip

    def router(self) -> str:
        return f"tcp/{self.cluster_ip('router')}:7447"

    def client(self) -> SwarmClient:
        return SwarmClient([self.router()], self.swarm, timeout_s=5.0)

    def swarm_configmap(self) -> str:
        sts = self.cluster.json("-n", self.namespace, "get", "statefulset", "index-shard")
        name: str = sts["spec"]["template"]["spec"]["containers"][0]["envFrom"][0]["configMapRef"]["name"]
        return name

    def rollout(self, kind: str, name: str, timeout_s: int = 300) -> None:
        self.k("rollout", "status", f"{kind}/{name}", f"--timeout={timeout_s}s", timeout_s=timeout_s + 30)


def _wait_tcp(host: str, port: int, timeout_s: float) -> None:
    """Until a TCP connection to the Service opens (kube-proxy lags the pod's readiness a little)."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with socket.create_connection((host, port), timeout=2.0):
                return
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


def _overlay(tmp: Path, namespace: str, swarm: str) -> Path:
    """This run's overlay: the local overlay in a namespace of its own, a swarm name of its own,
    a shorter synthetic world."""
    folder = tmp / "overlay"
    folder.mkdir()
    local = os.path.relpath(REPO / "k8s" / "overlays" / "local", folder)
    (folder / "kustomization.yaml").write_text(
        "apiVersion: kustomize.config.k8s.io/v1beta1\nkind: Kustomization\n"
        f"namespace: {namespace}\nresources: [{local}]\n"
        "configMapGenerator:\n"
        f"  - {{ name: swarm, behavior: merge, literals: [SWARMREC_SWARM={swarm}] }}\n"
        f"  - {{ name: synthetic-world, behavior: merge, literals: [FRAMES={FRAMES}] }}\n"
    )
    return folder


@pytest.fixture(scope="module")
def swarm(loaded: Cluster, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Swarm]:
    tmp = tmp_path_factory.mktemp("k8s-swarm")
    namespace, name = f"swarmrec-e2e-{os.getpid()}", f"e2e_k8s_{os.getpid()}"
    manifest = loaded.kubectl("kustomize", str(_overlay(tmp, namespace, name)))
    loaded.kubectl("create", "namespace", namespace)
    try:
        # The apiserver's own validation (strict field validation, enums, admission) of every object
        # before any is created (a dry run cannot create the namespace the others go in: made above).
        dry_run = loaded.kubectl("apply", "--dry-run=server", "-f", "-", stdin=manifest)
        s = Swarm(loaded, namespace, name, manifest, dry_run, loaded.timings)
        t0 = time.monotonic()
        loaded.kubectl("apply", "-f", "-", stdin=manifest)
        for kind, workload in WORKLOADS:
            s.rollout(kind, workload)
        s.timings["apply_to_all_ready_s"] = time.monotonic() - t0
        _wait_tcp(s.cluster_ip("router"), 7447, 60)
        yield s
    finally:
        loaded.kubectl("delete", "namespace", namespace, "--wait=true", "--timeout=180s", timeout_s=240)
        # The pods' folders on the node (hostPath): the namespace is gone, so are they.
        subprocess.run(["rm", "-rf", str(Path(cluster_env()["K8S_VOLUMES"]) / namespace)], check=True)
        print(json.dumps({"k8s_e2e_timings_s": loaded.timings}))


def test_the_apiserver_accepts_every_object_of_the_local_overlay(swarm: Swarm) -> None:
    created = [line for line in swarm.dry_run.splitlines() if line.strip()]
    assert len(created) == swarm.manifest.count("\nkind: ") + swarm.manifest.startswith("kind: ")
    assert all(line.endswith("(server dry run)") for line in created), created


def test_every_pod_is_ready_with_its_robot_id_and_the_router_service_reaches_them_all(swarm: Swarm) -> None:
    for kind in ROBOT_KINDS:
        pods = swarm.pods(kind)
        assert sorted(pods) == [f"{kind}-{r}" for r in range(ROBOTS)]
        assert all(p["ready"] for p in pods.values()), pods
    # Through the router's ClusterIP (kube-proxy): every robot's services, each under the robot id
    # its pod's ordinal gave it.
    with swarm.client() as client:
        client.wait_for({(k, r) for k in ROBOT_KINDS for r in range(ROBOTS)}, timeout_s=60)
        members = {(m.kind, m.robot) for m in client.members()}
    assert members == {(k, r) for k in ROBOT_KINDS for r in range(ROBOTS)}


def test_nothing_of_the_cluster_can_reach_beyond_this_machine(swarm: Swarm) -> None:
    # Checked without sending anything: the pods have no default route (only their subnet and the
    # Service range), and a Service address kube-proxy has not programmed yet is stopped on the node
    # instead of following the host's default route (deploy/k8s/cluster-up.sh).
    routes = swarm.k("exec", "index-shard-0", "-c", "service", "--", "cat", "/proc/net/route")
    destinations = {line.split()[1] for line in routes.splitlines()[1:]}
    assert "00000000" not in destinations, routes
    cidr = cluster_env()["SERVICE_CIDR"]
    for table, chain, target in (("filter", "OUTPUT", "REJECT"), ("mangle", "FORWARD", "DROP")):
        rules = _run(["iptables", "-t", table, "-S", chain], timeout_s=30).stdout.splitlines()
        assert any(r.startswith(f"-A {chain} -d {cidr} -m comment") and f"-j {target}" in r for r in rules)


def test_a_lockstep_replay_through_the_cluster_matches_the_offline_evaluation(
    swarm: Swarm, tmp_path: Path
) -> None:
    # The host replays the same world the detectors made (`swarmrec synth`, same seed and frames)
    # through the router Service, and reads the counters from the cluster's Prometheus.
    dataset = tmp_path / "dataset"
    _run(
        [str(REPO / ".venv/bin/swarmrec"), "synth", "--out", str(dataset), "--frames", str(FRAMES)],
        timeout_s=120,
    )
    # The shards' ranges as the services compute them (even for the paper preset).
    bounds = label_bounds_of(ServiceSettings(n_robots=ROBOTS, n_labels=80, preset="paper"))
    swarm_file = {
        "project": swarm.namespace,
        "swarm": swarm.swarm,
        "robots": ROBOTS,
        "preset": "paper",
        "n_labels": 80,
        "label_bounds": [int(b) for b in bounds],
        "lockstep": True,
        "request_timeout_s": 5.0,
        "router_endpoint": swarm.router(),
        "prometheus_url": f"http://{swarm.cluster_ip('prometheus')}:9090",
        "dataset": str(dataset),
        "labels": None,
        "groundtruth": str(dataset / "groundtruth.txt"),
        "compose_file": "",
    }
    folder = tmp_path / "k8s"
    folder.mkdir()
    (folder / "swarm.json").write_text(json.dumps(swarm_file))
    t0 = time.monotonic()
    summary = main_attached(folder, out=tmp_path / "report", progress=False, plots=False)
    swarm.timings["replay_300_frames_s"] = time.monotonic() - t0
    assert summary["queries"]["missing_slots"] == 0
    assert summary["queries"]["errors"] == []
    assert summary["offline_check"]["identical"] is True
    with swarm.client() as client:
        stored = {m.robot: m.stored_items for m in client.members() if m.kind == "index-shard"}
    assert sum(stored.values()) > 0


def _shard_records(swarm: Swarm) -> dict[int, int]:
    with swarm.client() as client:
        return {m.robot: m.stored_items for m in client.members() if m.kind == "index-shard"}


def _wait(what: str, cond: Any, timeout_s: float = 180.0) -> float:
    t0 = time.monotonic()
    while not cond():
        if time.monotonic() - t0 > timeout_s:
            pytest.fail(f"{what}: not after {timeout_s:g} s")
        time.sleep(0.5)
    return time.monotonic() - t0


def test_a_deleted_shard_pod_comes_back_with_its_records(swarm: Swarm) -> None:
    before = _shard_records(swarm)
    assert before[1] > 0
    old = swarm.pods("index-shard")["index-shard-1"]["uid"]
    t0 = time.monotonic()
    swarm.k("delete", "pod", "index-shard-1", "--wait=false")

    def back() -> bool:
        pod = swarm.pods("index-shard").get("index-shard-1")
        return pod is not None and pod["uid"] != old and pod["ready"]

    _wait("index-shard-1 recreated and ready", back)
    swarm.timings["pod_delete_to_ready_s"] = time.monotonic() - t0
    with swarm.client() as client:
        client.wait_for({("index-shard", 1)}, timeout_s=60)
    # Same name, same folder on the node: the record log replayed on start.
    assert _shard_records(swarm) == before


def test_the_shard_statefulset_scales_from_3_to_6_to_2_and_back(swarm: Swarm) -> None:
    records = _shard_records(swarm)
    uids = {n: p["uid"] for n, p in swarm.pods("index-shard").items()}
    configmap = swarm.swarm_configmap()

    def resize(n: int) -> float:
        # Today a shard's label range is fixed at start by (robot, SWARMREC_N_ROBOTS), and a robot id
        # outside the swarm is refused: pods created from now on are told the new size. (The elastic
        # index will make the membership decide, and `kubectl scale` alone enough.)
        patch = json.dumps({"data": {"SWARMREC_N_ROBOTS": str(n)}})
        swarm.k("patch", "configmap", configmap, "--type", "merge", "-p", patch)
        t0 = time.monotonic()
        swarm.k("scale", "statefulset/index-shard", f"--replicas={n}")

        def settled() -> bool:
            pods = swarm.pods("index-shard")
            return sorted(pods) == [f"index-shard-{r}" for r in range(n)] and all(
                p["ready"] for p in pods.values()
            )

        _wait(f"index-shard scaled to {n}", settled)
        took = time.monotonic() - t0
        with swarm.client() as client:
            client.wait_for({("index-shard", r) for r in range(n)}, timeout_s=60)
            _wait(
                f"{n} shards alive",
                lambda: {r for k, r in client.alive() if k == "index-shard"} == set(range(n)),
                timeout_s=30,
            )
        return took

    swarm.timings["scale_3_to_6_s"] = resize(6)
    now = swarm.pods("index-shard")
    assert all(now[n]["uid"] == uid for n, uid in uids.items())  # the first three were left alone
    added = _shard_records(swarm)
    assert {r: added[r] for r in range(3)} == records and {added[r] for r in range(3, 6)} == {0}

    swarm.timings["scale_6_to_2_s"] = resize(2)
    assert {n: p["uid"] for n, p in swarm.pods("index-shard").items()} == {
        n: uids[n] for n in ("index-shard-0", "index-shard-1")
    }

    swarm.timings["scale_2_to_3_s"] = resize(3)
    # index-shard-2 was scaled away and back: its folder stayed, so did its records.
    assert _shard_records(swarm) == records
