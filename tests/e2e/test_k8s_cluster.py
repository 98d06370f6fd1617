"""The swarm on a real Kubernetes cluster, under mutual TLS: deploy/k8s/cluster-up.sh's single node,
the swarm's images loaded into its containerd, and a :class:`KubernetesDeployment` of 3 robots in a
namespace of this run's own (the local overlay, a PKI made for the run, its Secrets).

Real pods, real kubelet, kube-proxy and CoreDNS: nothing is simulated. A cluster that is already up
is reused (and left up); one this module started is brought down at the end unless
``SWARMREC_K8S_KEEP=1``. The namespace, and its pods' folders on the node, are removed either way.

The module's fixture runs the main job through the cluster first (``swarmrec run --deployment k8s
--keep`` does the same): a lock-step replay whose pair scores must equal the offline evaluation's.
The tests then check the running swarm: identities, refused clients, the gateway from the host, a
deleted pod keeping its records, and the shard StatefulSet scaled.
"""

from __future__ import annotations

import json
import os
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import grpc
import pytest
import zenoh

from swarmrec.client import ZenohClient
from swarmrec.core.split import split_frames
from swarmrec.datasets.source import DatasetSource, load_dataset
from swarmrec.deployments.attach import attach
from swarmrec.deployments.kubernetes import (
    DEFAULT_OVERLAY,
    Kubectl,
    KubernetesDeployment,
    KubernetesSettings,
    write_overlay,
)
from swarmrec.errors import ConfigError
from swarmrec.experiments.places import PlacesSettings, PlacesSummary, main
from swarmrec.experiments.places.pipeline import prepare
from swarmrec.wire.gen.swarmrec.v1 import gateway_pb2, gateway_pb2_grpc
from tests.conftest import REPO
from tests.unit.test_k8s_manifests import ROBOT_KINDS, cluster_env

ROBOTS, FRAMES = 3, 300
#: Certificates for 6 robots: the scaling test takes the shards to 6.
MAX_ROBOTS = 6
KEEP = os.environ.get("SWARMREC_K8S_KEEP") == "1"


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


def _kubectl() -> Kubectl:
    env = cluster_env()
    return Kubectl((str(Path(env["K8S_BIN"]) / "kubectl"),), Path(env["KUBECONFIG_ADMIN"]))


@dataclass
class Cluster:
    started_here: bool
    timings: dict[str, float] = field(default_factory=dict)


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
    c = Cluster(started_here=not _api_answers())
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
    deployment: KubernetesDeployment
    run: PlacesSettings
    summary: PlacesSummary
    timings: dict[str, float]

    @property
    def namespace(self) -> str:
        return self.deployment.namespace

    @property
    def swarm(self) -> str:
        return self.run.swarm

    def k(self, *args: str, timeout_s: float = 120.0) -> str:
        return self.deployment.k(*args, timeout_s=timeout_s)

    def client(self) -> ZenohClient:
        """A read-only client from the host, through the router's Service."""
        return self.deployment.client(5.0, role="client")

    def pods(self, component: str) -> dict[str, dict[str, Any]]:
        """Pod name -> {uid, ready} of one component."""
        items = json.loads(
            self.k("get", "pods", "-l", f"app.kubernetes.io/component={component}", "-o", "json")
        )
        out = {}
        for p in items["items"]:
            conditions = {c["type"]: c["status"] for c in p["status"].get("conditions", [])}
            out[p["metadata"]["name"]] = {
                "uid": p["metadata"]["uid"],
                "ready": conditions.get("Ready") == "True" and "deletionTimestamp" not in p["metadata"],
            }
        return out


@pytest.fixture(scope="module")
def swarm(loaded: Cluster, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Swarm]:
    tmp = tmp_path_factory.mktemp("k8s-swarm")
    namespace, name = f"swarmrec-e2e-{os.getpid()}", f"e2e_k8s_{os.getpid()}"
    settings = KubernetesSettings(
        namespace=namespace, out=tmp / "k8s", kubectl=_kubectl(), max_robots=MAX_ROBOTS, keep=True
    )
    deployment = KubernetesDeployment(settings)
    run = PlacesSettings(
        source=DatasetSource(frames=FRAMES),
        robots=ROBOTS,
        swarm=name,
        request_timeout_s=5.0,
        out=tmp / "report",
        plots=False,
        progress=False,
    )
    try:
        # What `swarmrec run --deployment k8s --keep` does: deploy, replay in lock-step, report.
        t0 = time.monotonic()
        summary = main(run, deployment)
        loaded.timings["run_deploy_and_replay_s"] = time.monotonic() - t0
        loaded.timings.update({f"deploy_{k}": v for k, v in deployment.timings.items()})
        yield Swarm(deployment, run, summary, loaded.timings)
    finally:
        deployment.remove()
        print(json.dumps({"k8s_e2e_timings_s": loaded.timings}))


def test_a_lockstep_replay_through_the_cluster_matches_the_offline_evaluation(swarm: Swarm) -> None:
    s = swarm.summary
    assert s.swarm.deployment == f"kubernetes namespace {swarm.namespace}"
    assert (s.queries.frames_replayed, s.queries.missing_slots, s.queries.errors) == (FRAMES, 0, [])
    assert s.offline_check is not None and s.offline_check.identical, s.offline_check
    assert s.offline_check.positive_pairs_swarm > 0 and s.loop_closures.count > 0
    # Every service's counters came from the cluster's Prometheus (router and gateway included).
    assert s.scrape_failed == []
    assert s.bytes.per_query > 0 and len(s.shard_load.partial_queries) == ROBOTS


def test_the_apiserver_accepts_every_object_of_the_runs_overlay(swarm: Swarm, tmp_path: Path) -> None:
    # The apiserver's own validation (strict fields, enums, admission) of what the deployment applied.
    spec = prepare(swarm.run, dataset_dir=tmp_path / "dataset").spec
    folder = write_overlay(spec, swarm.namespace, DEFAULT_OVERLAY, tmp_path / "overlay")
    kubectl = swarm.deployment.kubectl
    manifest = kubectl.run("kustomize", str(folder))
    out = kubectl.run("apply", "--dry-run=server", "--validate=strict", "-f", "-", stdin=manifest)
    lines = [line for line in out.splitlines() if line.strip()]
    assert len(lines) == manifest.count("\nkind: ") + manifest.startswith("kind: ")
    assert all(line.endswith("(server dry run)") for line in lines), lines


def test_every_pod_is_ready_and_presents_its_own_certificate_only(swarm: Swarm) -> None:
    for kind in ROBOT_KINDS:
        pods = swarm.pods(kind)
        assert sorted(pods) == [f"{kind}-{r}" for r in range(ROBOTS)]
        assert all(p["ready"] for p in pods.values()), pods
    with swarm.client() as client:
        members = {(m.kind, m.robot) for m in client.members()}
    assert members == {(k, r) for k in ROBOT_KINDS for r in range(ROBOTS)} | {("router", 0), ("gateway", 0)}
    # Inside robot 1's shard: its own pair and the CA certificate, nothing of the Secret it came from.
    files = swarm.k("exec", "index-shard-1", "-c", "service", "--", "ls", "-l", "/run/swarmrec/pki")
    names = sorted(line.split()[-1] for line in files.splitlines()[1:])
    cn = f"r1.index-shard.{swarm.swarm}"
    assert names == ["ca.pem", f"{cn}.key", f"{cn}.pem"]
    assert next(line for line in files.splitlines() if line.endswith(".key")).startswith("-rw-------")
    mounts = swarm.k("exec", "index-shard-1", "-c", "service", "--", "cat", "/proc/self/mounts")
    assert "/run/swarmrec/secrets" not in mounts
    router = swarm.k("exec", "deploy/router", "-c", "router", "--", "ls", "/run/swarmrec/pki").split()
    assert sorted(router) == ["acl.json", "ca.pem", f"router.{swarm.swarm}.key", f"router.{swarm.swarm}.pem"]
    assert "ca.key" not in swarm.k("get", "secrets", "-o", "json")


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


def test_a_client_without_a_certificate_is_refused_by_the_router_and_the_gateway(swarm: Swarm) -> None:
    pki, endpoint = swarm.deployment.pki_dir, swarm.deployment.endpoint
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(pki / "ca.pem")))
    with pytest.raises(zenoh.ZError):
        zenoh.open(conf)
    plain = zenoh.Config()
    plain.insert_json5("mode", '"client"')
    plain.insert_json5("scouting/multicast/enabled", "false")
    plain.insert_json5("connect/endpoints", json.dumps([endpoint.replace("tls/", "tcp/")]))
    with pytest.raises(zenoh.ZError):
        zenoh.open(plain)
    # The gateway's gRPC port: the swarm's CA trusted, but no client certificate to show.
    target = swarm.deployment.gateway_address.removeprefix("grpc://")
    credentials = grpc.ssl_channel_credentials(root_certificates=(pki / "ca.pem").read_bytes())
    with grpc.secure_channel(target, credentials) as channel:
        stub = gateway_pb2_grpc.SwarmGatewayStub(channel)  # type: ignore[no-untyped-call]  # generated, untyped
        with pytest.raises(grpc.RpcError) as refused:
            stub.Members(gateway_pb2.MembersRequest(), timeout=10.0)
    assert refused.value.code() == grpc.StatusCode.UNAVAILABLE
    # And with the client's certificate, the same port answers (next test: what it answers).
    with swarm.deployment.gateway_client() as gateway:
        assert gateway.members()


def test_the_gateway_answers_a_grpc_query_from_the_host_as_the_router_does(swarm: Swarm) -> None:
    frames = load_dataset(DatasetSource(frames=FRAMES)).sequence
    g = FRAMES // 2  # a frame the swarm holds: robot r's block of the split, at its local index
    robot = next(r for r, block in enumerate(split_frames(FRAMES, ROBOTS)) if g in block)
    local = g - split_frames(FRAMES, ROBOTS)[robot].start
    with swarm.deployment.gateway_client(10.0) as gateway, swarm.client() as zenoh_client:
        assert {(m.kind, m.robot) for m in gateway.members()} == {
            (m.kind, m.robot) for m in zenoh_client.members()
        }
        through_grpc, through_zenoh = (
            gateway.query(frames.constellations[g]),
            zenoh_client.query(frames.constellations[g]),
        )
        assert through_grpc.complete and list(through_grpc.matches) == list(through_zenoh.matches)
        best = max(through_grpc.matches, key=lambda m: m.score)
        assert (best.match_robot_id, best.match_frame_index) == (robot, local)  # it finds itself first
        for r in range(ROBOTS):
            assert list(gateway.loop_closures(r)) == list(zenoh_client.loop_closures(r))
        assert any(gateway.loop_closures(r) for r in range(ROBOTS))


def test_swarm_json_attaches_to_the_running_swarm_and_refuses_another_spec(
    swarm: Swarm, tmp_path: Path
) -> None:
    path = swarm.deployment.write_attach_file(swarm.run.record())
    attached, info = attach(path.parent)
    assert isinstance(attached, KubernetesDeployment) and info.deployment == "kubernetes"
    run = PlacesSettings.from_record(info.experiment, out=tmp_path)
    spec = prepare(run, dataset_dir=tmp_path / "dataset").spec
    attached.start(spec)  # the running swarm is this spec: checked, not started
    with attached.client(role="client") as client:
        assert len(client.members()) == 2 + ROBOTS * len(ROBOT_KINDS)
    assert attached.stop() == {} and swarm.pods("router")  # attached: stop leaves it running
    other = prepare(run.with_(robots=ROBOTS + 1), dataset_dir=tmp_path / "other").spec
    with pytest.raises(ConfigError, match="not this run's"):
        KubernetesDeployment.attached(path.parent).start(other)


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
    # Same name, same folder on the node: the record log replayed on start; its identity installed
    # again by its init container from the Secret.
    assert _shard_records(swarm) == before


# --- Scaling the index shards -------------------------------------------------------------------------
#
# ELASTIC INDEX: CONNECT HERE. Today a shard's label range is fixed at start by (robot, SWARMREC_N_ROBOTS),
# so this test tells new pods the new size (ConfigMap patch) and checks only what Kubernetes itself
# guarantees: pods started and stopped, each with its own identity (certificates for MAX_ROBOTS robots),
# records kept across scale-down and back. When the elastic index lands (label groups placed on shards,
# versioned placement), replace `resize`'s ConfigMap patch by `kubectl scale` alone and add, after each
# resize: the placement version the shards report has moved on, every label group is held by the shards
# alive, and a lock-step replay of fresh frames through the resized swarm is identical to the offline
# evaluation with the new placement (docs/kubernetes.md, "Scaling").


def test_the_shard_statefulset_scales_from_3_to_6_to_2_and_back(swarm: Swarm) -> None:
    records = _shard_records(swarm)
    uids = {n: p["uid"] for n, p in swarm.pods("index-shard").items()}
    sts = json.loads(swarm.k("get", "statefulset", "index-shard", "-o", "json"))
    configmap = sts["spec"]["template"]["spec"]["containers"][0]["envFrom"][0]["configMapRef"]["name"]

    def resize(n: int) -> float:
        # Today a shard's label range is fixed at start by (robot, SWARMREC_N_ROBOTS, the run's label
        # bounds), and a robot id outside the swarm is refused: pods created from now on are told the
        # new size, and even ranges for it (empty bounds; the run wrote its own for 3 robots).
        patch = json.dumps({"data": {"SWARMREC_N_ROBOTS": str(n), "SWARMREC_LABEL_BOUNDS": ""}})
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
