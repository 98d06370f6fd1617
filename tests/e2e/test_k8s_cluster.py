"""The swarm on a real Kubernetes cluster, under mutual TLS: deploy/k8s/cluster-up.sh's single node,
the swarm's images loaded into its containerd, and a :class:`KubernetesDeployment` of 3 robots in a
namespace of this run's own (the local overlay, a PKI made for the run, its Secrets).

Real pods, real kubelet, kube-proxy and CoreDNS: nothing is simulated. A cluster that is already up
is reused (and left up); one this module started is brought down at the end unless
``SWARMREC_K8S_KEEP=1``. The namespace, and its pods' folders on the node, are removed either way.

The module's fixture runs the main job through the cluster first (``swarmrec run --deployment k8s
--keep`` does the same): a lock-step replay whose pair scores must equal the offline evaluation's.
The tests then check the running swarm: identities, refused clients, the gateway from the host, and
the elastic index under Kubernetes: a deleted shard pod, two deleted at once (both owners of a
label group), the shard StatefulSet scaled 3 -> 6 -> 2 -> 3 with ``kubectl scale`` alone; after
each, the index settles on the live shards, every group has its replicas among them, every owner
holds exactly what the dataset put in the group (read back through the shards' ``transfer``), and
queries of stored frames are answered by every shard asked. A run whose detectors cannot start
says what holds their pods. Last, a swarm of its own is scaled
3 -> 6 -> 2 while a paced replay runs: no store lost, every query answered or reported failed, and
no answer emptier than what the shards held long before it.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import grpc
import numpy as np
import numpy.typing as npt
import pytest
import zenoh

from swarmrec.client import ZenohClient
from swarmrec.core.descriptor import semantic_descriptor
from swarmrec.core.placement import Placement, balance_ratio, groups_from_bounds, shard_loads
from swarmrec.core.presets import get_preset
from swarmrec.core.split import split_frames
from swarmrec.core.types import ConstellationSequence
from swarmrec.deployments.attach import attach
from swarmrec.deployments.base import Deployment
from swarmrec.deployments.kubernetes import (
    DEFAULT_OVERLAY,
    Kubectl,
    KubernetesDeployment,
    KubernetesError,
    KubernetesSettings,
    write_overlay,
)
from swarmrec.errors import ConfigError
from swarmrec.evaluation.source import DatasetSource, load_dataset
from swarmrec.experiments.places import PlacesSettings, PlacesSummary, main
from swarmrec.experiments.places.pipeline import prepare
from swarmrec.runtime import keys
from swarmrec.runtime.rpc import Caller
from swarmrec.runtime.tls import TlsFiles
from swarmrec.services.settings import IndexSettings, PlaceSettings
from swarmrec.wire import messages as pb
from swarmrec.wire.gen.swarmrec.v1 import gateway_pb2, gateway_pb2_grpc
from tests.conftest import REPO
from tests.integration.support import group_rows
from tests.unit.test_k8s_manifests import ROBOT_KINDS, cluster_env

ROBOTS, FRAMES = 3, 300
#: Certificates for 6 robots: the scaling tests take the shards to 6 (SWARMREC_MAX_SHARDS follows).
MAX_ROBOTS = 6
PAPER = get_preset("paper")
#: Replicas of each label group (the default); with rebalancing off only membership moves groups,
#: so every group has exactly this many owners once settled (the load would add replicas of hot ones).
REPLICAS = IndexSettings().replicas
NO_REBALANCING = 1000.0
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


#: The namespaces this module makes end in its test process's id.
E2E_NAMESPACE = re.compile(r"^swarmrec-e2e-(?:[a-z]+-)?(\d+)$")


def _test_process_alive(pid: int) -> bool:
    """Whether ``pid`` is a running pytest, or a worker of a parallel one (pytest-xdist: its
    command line is execnet's; pytest put PYTEST_VERSION in the environment it started it
    with); a number reused by another program is not."""
    try:
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
        environ = Path(f"/proc/{pid}/environ").read_bytes()
    except OSError:
        return False
    return b"pytest" in cmdline or b"\0PYTEST_VERSION=" in b"\0" + environ


def stale_namespaces(names: Sequence[str], alive: Callable[[int], bool]) -> list[str]:
    """Of ``names``, this module's namespaces whose test process is gone."""
    stale = []
    for name in names:
        m = E2E_NAMESPACE.match(name)
        if m and int(m.group(1)) != os.getpid() and not alive(int(m.group(1))):
            stale.append(name)
    return stale


def _remove_stale_namespaces(kubectl: Kubectl) -> None:
    """Delete what test runs that never finished left in a reused cluster. A cluster state
    folder outlives a killed run (the machine stopped mid-test; cluster-up.sh then restarts
    the cluster from it), and its swarms' pods still hold the node's CPU requests: a CI run
    saw every descriptor pod of its own swarm Pending for "Insufficient cpu"."""
    names = kubectl.run("get", "namespaces", "-o", "jsonpath={.items[*].metadata.name}").split()
    for name in stale_namespaces(names, _test_process_alive):
        print(f"k8s: removing {name}, left by a test run that is no longer running", file=sys.stderr)
        kubectl.run("delete", "namespace", name, "--wait=true", "--timeout=240s", timeout_s=270)


@pytest.fixture(scope="module")
def cluster() -> Iterator[Cluster]:
    if os.geteuid() != 0:
        pytest.fail("the Kubernetes tests run a kubelet and containerd: run them as root")
    c = Cluster(started_here=not _api_answers())
    t0 = time.monotonic()
    _run([str(REPO / "deploy/k8s/cluster-up.sh")], timeout_s=1800)
    c.timings["cluster_up_s"] = time.monotonic() - t0
    _remove_stale_namespaces(_kubectl())
    try:
        yield c
    finally:
        if c.started_here and not KEEP:
            _run([str(REPO / "deploy/k8s/cluster-down.sh")], timeout_s=300)


def test_only_namespaces_of_test_runs_that_are_gone_count_as_stale() -> None:
    me = os.getpid()
    names = [
        "default",
        "kube-system",
        "swarmrec-e2e-111",  # gone
        "swarmrec-e2e-live-222",  # still running
        "swarmrec-e2e-broken-333",  # gone
        f"swarmrec-e2e-{me}",  # this run's own
        "swarmrec-e2e-notapid",
        "swarmrec-probes-tls",  # a benchmark's, not this module's
        "my-swarm-444",
    ]
    assert stale_namespaces(names, lambda pid: pid == 222) == ["swarmrec-e2e-111", "swarmrec-e2e-broken-333"]
    # This process is a pytest: a namespace named after it is never taken for stale.
    assert _test_process_alive(me)
    assert not _test_process_alive(2**22 + 1)  # above pid_max's default: no such process


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
        index=IndexSettings(rebalance_target=NO_REBALANCING),
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


# --- The elastic index on the cluster: holdings after pod loss and scaling ----------------------------
#
# What the checks compare with is computed from the dataset (each robot replays its block of the split;
# a frame with at least the preset's min_objects stores its non-empty slice of each label group), never
# asked of the swarm. What each shard holds is read back through its own `transfer` pages, speaking as
# a shard (r<k>.index-shard.<swarm>, from the run's PKI) through the router's Service from the host.

Rows = set[tuple[int, int]]


def label_groups(deployment: KubernetesDeployment) -> tuple[tuple[int, int], ...]:
    """The run's label groups: the ranges its label bounds make (the scaling changes none)."""
    spec = deployment.spec
    assert spec is not None
    places = spec.component(PlaceSettings)
    assert isinstance(places, PlaceSettings)
    return groups_from_bounds(places.bounds(spec.bus).tolist())


def frame_descriptors(
    seq: ConstellationSequence, robots: int
) -> dict[tuple[int, int], npt.NDArray[np.int64]]:
    """(robot, local frame) -> the descriptor of every frame the replay queries and stores."""
    out = {}
    for robot, block in enumerate(split_frames(len(seq), robots)):
        for frame, i in enumerate(block):
            c = seq.constellations[i]
            if len(c) >= PAPER.min_objects:
                out[(robot, frame)] = semantic_descriptor(c, seq.n_labels)
    return out


def expected_holdings(
    seq: ConstellationSequence, groups: Sequence[tuple[int, int]], robots: int
) -> dict[int, Rows]:
    """Per label group, the (robot, frame) of every frame with a non-empty slice in it."""
    descs = frame_descriptors(seq, robots)
    return {g: {rf for rf, d in descs.items() if d[lo:hi].any()} for g, (lo, hi) in enumerate(groups)}


def settled_on(deployment: KubernetesDeployment, live: set[int], timeout_s: float = 240.0) -> Placement:
    """The placement once the index has settled on exactly the ``live`` shards: every live shard
    answers and follows it, no handoff is in progress, no store is pending, its members are them."""
    deadline = time.monotonic() + timeout_s
    with deployment.client(10.0, role="client") as client:
        while True:
            state = client.wait_index_settled(timeout_s=max(deadline - time.monotonic(), 1.0))
            p = state.placement
            if state.settled and p is not None and set(p.members) == live and set(state.versions) == live:
                return p
            if time.monotonic() > deadline:
                pytest.fail(f"the index did not settle on shards {sorted(live)} in {timeout_s:g} s: {state}")
            time.sleep(0.5)


def check_index(
    deployment: KubernetesDeployment, placement: Placement, live: set[int], seq: ConstellationSequence
) -> None:
    """Every label group of the run has ``replicas`` owners among the ``live`` shards, and every
    owner holds exactly the slices the replayed dataset put in the group."""
    info = deployment.info
    assert info is not None
    assert placement.groups == label_groups(deployment)
    replicas = min(REPLICAS, len(live))
    assert all(set(o) <= live and len(o) == replicas for o in placement.owners), placement.owners
    expected = expected_holdings(seq, placement.groups, info.robots)
    assert all(expected.values())
    asker = min(live)
    tls = TlsFiles.in_dir(deployment.pki_dir, f"r{asker}.index-shard.{info.swarm}")
    with ZenohClient([deployment.endpoint], info.swarm, timeout_s=10.0, tls=tls) as shard:
        caller = Caller(shard.session, asker, 10.0)
        for g, owners in enumerate(placement.owners):
            for owner in owners:
                assert group_rows(caller, info.swarm, owner, g) == expected[g], (g, owner)


def check_queries(swarm: Swarm) -> None:
    """Read-only queries of stored frames through the router: every shard asked answers, and each
    frame finds itself with the best score. The frames asked are the two with the most objects
    of robots 1 and 2 (a client's query goes as robot 0's frame 0, so the preset's exclusion keeps
    robot 0's first frames, its whole block here, out of the matches)."""
    seq = load_dataset(DatasetSource(frames=FRAMES)).sequence
    blocks = split_frames(FRAMES, ROBOTS)
    with swarm.client() as client:
        for robot in range(1, ROBOTS):
            block = blocks[robot]
            richest = sorted(range(len(block)), key=lambda f: (-len(seq.constellations[block[f]]), f))
            for local in richest[:2]:
                result = client.query(seq.constellations[block[local]])
                assert result.failed_shards == [] and result.complete, result
                scores = {(m.match_robot_id, m.match_frame_index): m.score for m in result.matches}
                assert scores and scores.get((robot, local)) == max(scores.values()), (robot, local, scores)


def check_swarm(swarm: Swarm, live: set[int], placement: Placement | None = None) -> Placement:
    """The index settled on ``live`` (``placement``: found so already), holding everything,
    answering queries; the placement."""
    placement = placement or settled_on(swarm.deployment, live)
    check_index(swarm.deployment, placement, live, load_dataset(DatasetSource(frames=FRAMES)).sequence)
    check_queries(swarm)
    return placement


def _wait(what: str, cond: Any, timeout_s: float = 240.0) -> float:
    t0 = time.monotonic()
    while not cond():
        if time.monotonic() - t0 > timeout_s:
            pytest.fail(f"{what}: not after {timeout_s:g} s")
        time.sleep(0.5)
    return time.monotonic() - t0


def _recreated(swarm: Swarm, old: dict[str, str]) -> bool:
    """Each pod of ``old`` (name -> uid) has a successor that is Ready."""
    pods = swarm.pods("index-shard")
    return all(n in pods and pods[n]["uid"] != uid and pods[n]["ready"] for n, uid in old.items())


def test_a_deleted_shard_pod_comes_back_and_every_group_is_whole_again(swarm: Swarm) -> None:
    check_swarm(swarm, {0, 1, 2})
    old = {"index-shard-1": swarm.pods("index-shard")["index-shard-1"]["uid"]}
    t0 = time.monotonic()
    swarm.k("delete", "pod", "index-shard-1", "--wait=false")
    # It drains first (its groups to the other two while it answers), then its successor starts
    # with the same volume and identity and takes groups again.
    _wait("index-shard-1 recreated and ready", lambda: _recreated(swarm, old))
    swarm.timings["pod_delete_to_ready_s"] = time.monotonic() - t0
    check_swarm(swarm, {0, 1, 2})
    swarm.timings["pod_delete_to_settled_s"] = time.monotonic() - t0


def test_two_shard_pods_deleted_at_once_both_owners_of_a_group_come_back_with_everything(
    swarm: Swarm,
) -> None:
    # A node's worth of shards at once, on this single node: both owners of a label group (with two
    # replicas over three shards, each group's pair). Deleted together they drain together, into
    # the one shard left; the StatefulSet recreates both with their volumes and they take groups again.
    placement = check_swarm(swarm, {0, 1, 2})
    seq = load_dataset(DatasetSource(frames=FRAMES)).sequence
    expected = expected_holdings(seq, placement.groups, ROBOTS)
    group = max(range(len(placement.groups)), key=lambda g: len(expected[g]))
    pair = sorted(placement.owners[group])
    assert len(pair) == 2
    names = [f"index-shard-{r}" for r in pair]
    pods = swarm.pods("index-shard")
    old = {n: pods[n]["uid"] for n in names}
    t0 = time.monotonic()
    swarm.k("delete", "pod", *names, "--wait=false")
    _wait(f"{', '.join(names)} recreated and ready", lambda: _recreated(swarm, old))
    swarm.timings["two_pods_delete_to_ready_s"] = time.monotonic() - t0
    check_swarm(swarm, {0, 1, 2})
    swarm.timings["two_pods_delete_to_settled_s"] = time.monotonic() - t0


def test_the_shard_statefulset_scales_from_3_to_6_to_2_and_back(swarm: Swarm) -> None:
    # `kubectl scale` alone: the shards accept ordinals up to MAX_ROBOTS (the run's ConfigMap has
    # SWARMREC_MAX_SHARDS, the Secret their identities), and the elastic index places the run's
    # label groups (its bounds unchanged) on whichever shards are alive.
    before = check_swarm(swarm, {0, 1, 2})
    # The run's load per label group, as the shards counted it (Prometheus, every pod): the same
    # partial queries as the query reports say the shards answered. Each placement the scaling
    # settles on is recorded with the busiest / mean it gives that load.
    assert swarm.summary.index is not None
    group_load = dict(enumerate(float(n) for n in swarm.summary.index.group_queries))
    assert sum(group_load.values()) == sum(swarm.summary.shard_load.partial_queries) > 0
    uids = {n: p["uid"] for n, p in swarm.pods("index-shard").items()}
    maps = json.loads(swarm.k("get", "configmaps", "-o", "json"))["items"]
    (shared,) = [m["data"] for m in maps if "SWARMREC_N_ROBOTS" in m.get("data", {})]
    assert (shared["SWARMREC_N_ROBOTS"], shared["SWARMREC_MAX_SHARDS"]) == (str(ROBOTS), str(MAX_ROBOTS))

    def resize(n: int) -> Placement:
        t0 = time.monotonic()
        swarm.k("scale", "statefulset/index-shard", f"--replicas={n}")
        want = [f"index-shard-{r}" for r in range(n)]

        def pods_done() -> bool:
            pods = swarm.pods("index-shard")
            return sorted(pods) == want and all(p["ready"] for p in pods.values())

        _wait(f"index-shard scaled to {n}", pods_done)
        pods_s = time.monotonic() - t0
        placement = settled_on(swarm.deployment, set(range(n)))
        swarm.timings[f"scale_to_{n}_pods_s"] = pods_s
        swarm.timings[f"scale_to_{n}_settled_s"] = time.monotonic() - t0
        ratio = balance_ratio(shard_loads(placement, group_load))
        swarm.timings[f"scale_to_{n}_balance_ratio"] = ratio
        assert 1.0 <= ratio <= n, (n, ratio, placement.owners)
        return check_swarm(swarm, set(range(n)), placement)

    six = resize(6)
    assert six.version > before.version
    now = swarm.pods("index-shard")
    assert all(now[n]["uid"] == uid for n, uid in uids.items())  # the first three were left alone
    assert {3, 4, 5} & {m for own in six.owners for m in own}, six.owners  # the new shards took groups

    two = resize(2)
    assert two.version > six.version
    assert {n: p["uid"] for n, p in swarm.pods("index-shard").items()} == {
        n: uids[n] for n in ("index-shard-0", "index-shard-1")
    }

    three = resize(3)
    assert three.version > two.version
    # index-shard-2 was scaled away and back: same volume, same identity; it holds groups again.
    assert 2 in {m for own in three.owners for m in own}, three.owners


# --- Scaling while a run replays --------------------------------------------------------------------------

LIVE_FRAMES = 450  # 150 a robot
LIVE_RATE_HZ = 3.0  # frames a second each detector plays: a 50 s replay
#: Frames back in a robot's own sequence that every owner must hold when a later frame of that robot
#: queries: 10 s at the replay's rate, long after their stores were acknowledged (or retried).
STORED_BEFORE = 30


@dataclass
class LiveScaler:
    """Scales the shard StatefulSet 3 -> 6 -> 2 while a paced replay runs (from a thread started
    once the swarm is up), and keeps every query report the swarm publishes (its own subscriber,
    declared before the replay starts). ``marks``: what happened, with the reports seen by then."""

    reports: list[bytes] = field(default_factory=list)
    marks: dict[str, tuple[int, float]] = field(default_factory=dict)
    error: BaseException | None = None
    _client: ZenohClient | None = None
    _sub: Any = None
    _thread: threading.Thread | None = None
    _t0: float = 0.0

    def start(self, deployment: Deployment) -> None:
        assert isinstance(deployment, KubernetesDeployment)
        info = deployment.info
        assert info is not None
        self._client = deployment.client(10.0, role="client")
        self._client.open()
        # The callback only keeps the payload; the checks parse them after the run.
        self._sub = self._client.session.declare_subscriber(
            keys.event(info.swarm, "query", "*"),
            lambda sample: self.reports.append(sample.payload.to_bytes()),
        )
        self._t0 = time.monotonic()
        self._thread = threading.Thread(target=self._scale, args=(deployment,), daemon=True)
        self._thread.start()

    def mark(self, what: str) -> None:
        self.marks[what] = (len(self.reports), time.monotonic() - self._t0)

    def _until(self, what: str, cond: Any, timeout_s: float = 240.0) -> None:
        deadline = time.monotonic() + timeout_s
        while not cond():
            if time.monotonic() > deadline:
                raise TimeoutError(f"{what}: not after {timeout_s:g} s (marks {self.marks})")
            time.sleep(0.25)
        self.mark(what)

    def _owners(self) -> set[int]:
        assert self._client is not None
        placement = self._client.index_state().placement
        return {m for own in placement.owners for m in own} if placement is not None else set()

    def _scale(self, d: KubernetesDeployment) -> None:
        try:
            self._until("replaying", lambda: len(self.reports) >= LIVE_FRAMES // 10)
            d.k("scale", "statefulset/index-shard", "--replicas=6")
            self.mark("scale_to_6_issued")
            self._until("new_shards_own_groups", lambda: bool(self._owners() & {3, 4, 5}))
            self._until("half_replayed", lambda: len(self.reports) >= LIVE_FRAMES // 2)
            d.k("scale", "statefulset/index-shard", "--replicas=2")
            self.mark("scale_to_2_issued")
            self._until("groups_on_0_and_1", lambda: self._owners() == {0, 1})
            names = {"index-shard-0", "index-shard-1"}
            self._until("pods_3_to_5_and_2_gone", lambda: set(_pods(d, "index-shard")) == names)
        except BaseException as e:  # the test raises it (after_replay)
            self.error = e

    def stop(self) -> None:
        """Wait for the scaling to end; then no more reports are kept."""
        if self._thread is not None:
            self._thread.join(timeout=600)
        if self._sub is not None:
            self._sub.undeclare()
            self._sub = None
        if self._client is not None:
            self._client.close()
            self._client = None

    def finish(self) -> None:
        """:meth:`stop`, then what went wrong in the scaling thread, raised here."""
        self.stop()
        if self.error is not None:
            raise self.error


def _pods(d: KubernetesDeployment, component: str) -> list[str]:
    items = json.loads(d.k("get", "pods", "-l", f"app.kubernetes.io/component={component}", "-o", "json"))
    return [p["metadata"]["name"] for p in items["items"]]


def check_reports(
    reports: Sequence[pb.QueryReport],
    seq: ConstellationSequence,
    groups: Sequence[tuple[int, int]],
    robots: int,
    holdings: dict[int, Rows],
) -> dict[str, int]:
    """Every frame's report against the dataset and what the shards hold at the end: a frame with
    enough objects was queried, each of its non-empty label groups answered by a shard once or the
    report names failed shards, and every answer's candidate count is at most what the group holds
    sharing a label with the slice (n_ret at most) and at least what the robot's own frames
    ``STORED_BEFORE`` or more back that share one account for: never silently empty."""
    descs = frame_descriptors(seq, robots)
    slots = {(r, f) for r, block in enumerate(split_frames(len(seq), robots)) for f in range(len(block))}
    assert {(r.robot_id, r.frame_index) for r in reports} == slots  # a report for every frame
    seen = {"reports": len(reports), "answers": 0, "empty_answers": 0, "failed_groups": 0, "bounded_below": 0}
    for rep in reports:
        rf = (rep.robot_id, rep.frame_index)
        desc = descs.get(rf)
        assert rep.queried == (desc is not None), rf
        if desc is None:
            continue
        need = {g for g, (lo, hi) in enumerate(groups) if desc[lo:hi].any()}
        got = [sc.group for sc in rep.shard_candidates]
        assert len(got) == len(set(got)) and set(got) <= need, (rf, got, need)
        if need - set(got):
            assert rep.failed_shard_robot_ids, (rf, "a group neither answered nor reported failed")
            seen["failed_groups"] += len(need - set(got))
        for sc in rep.shard_candidates:
            lo, hi = groups[sc.group]
            bins = np.flatnonzero(desc[lo:hi])
            sharing = {other for other in holdings[sc.group] if descs[other][lo:hi][bins].any()}
            earlier = {(r, f) for r, f in sharing if r == rf[0] and f <= rf[1] - STORED_BEFORE}
            low, high = min(PAPER.n_ret, len(earlier)), min(PAPER.n_ret, len(sharing))
            assert low <= sc.n_candidates <= high, (rf, sc.group, sc.robot_id, sc.n_candidates, low, high)
            seen["answers"] += 1
            seen["empty_answers"] += sc.n_candidates == 0
            seen["bounded_below"] += low > 0
    return seen


def test_a_rollout_that_never_finishes_says_what_holds_its_pods(loaded: Cluster, tmp_path: Path) -> None:
    # An overlay on top of the local one whose detectors name an image the node does not have (and,
    # with imagePullPolicy Never, never pulls): every other workload rolls out, the detectors cannot.
    overlay = tmp_path / "broken-overlay"
    overlay.mkdir()
    image = [
        {"op": "replace", "path": "/spec/template/spec/containers/0/image", "value": "swarmrec-absent:0"}
    ]
    doc = {
        "apiVersion": "kustomize.config.k8s.io/v1beta1",
        "kind": "Kustomization",
        "resources": [os.path.relpath(DEFAULT_OVERLAY.resolve(), overlay)],
        "patches": [{"target": {"kind": "StatefulSet", "name": "detector"}, "patch": json.dumps(image)}],
    }
    (overlay / "kustomization.yaml").write_text(json.dumps(doc))
    namespace = f"swarmrec-e2e-broken-{os.getpid()}"
    deployment = KubernetesDeployment(
        KubernetesSettings(
            namespace=namespace, out=tmp_path / "k8s", overlay=overlay, kubectl=_kubectl(), wait_s=60
        )
    )
    run = PlacesSettings(
        source=DatasetSource(frames=60), robots=2, swarm=f"e2e_broken_{os.getpid()}", out=tmp_path / "report",
        plots=False, progress=False,
    )  # fmt: skip
    with pytest.raises(KubernetesError) as raised:
        main(run, deployment)
    said = str(raised.value)
    assert "statefulset/detector" in said, said
    # The pods and why they wait, not only "timed out waiting for the condition".
    assert "pod detector-0: Pending, not ready" in said, said
    assert "ErrImageNeverPull" in said, said
    # And the run removed what it made.
    assert not _kubectl().run("get", "namespace", namespace, "--ignore-not-found", "-o", "name").strip()


def test_scaling_the_shards_during_a_paced_replay_loses_no_store_and_leaves_no_query_silently_empty(
    loaded: Cluster, tmp_path: Path
) -> None:
    # A swarm of its own (free replay at a rate), while the module's keeps running: 3 -> 6 once a
    # tenth of the frames are in, 6 -> 2 at half, both with `kubectl scale` alone.
    namespace, name = f"swarmrec-e2e-live-{os.getpid()}", f"e2e_live_{os.getpid()}"
    settings = KubernetesSettings(
        namespace=namespace, out=tmp_path / "k8s", kubectl=_kubectl(), max_robots=MAX_ROBOTS
    )
    deployment = KubernetesDeployment(settings)
    run = PlacesSettings(
        source=DatasetSource(frames=LIVE_FRAMES),
        robots=ROBOTS,
        swarm=name,
        pace=str(LIVE_RATE_HZ),
        request_timeout_s=5.0,
        out=tmp_path / "report",
        plots=False,
        progress=False,
        index=IndexSettings(rebalance_target=NO_REBALANCING),
    )
    seq = load_dataset(DatasetSource(frames=LIVE_FRAMES)).sequence
    scaler = LiveScaler()
    seen: dict[str, Any] = {}

    def after(d: Deployment) -> None:
        assert isinstance(d, KubernetesDeployment)
        scaler.finish()
        placement = settled_on(d, {0, 1})
        check_index(d, placement, {0, 1}, seq)
        holdings = expected_holdings(seq, placement.groups, ROBOTS)
        reports = [pb.QueryReport.FromString(b) for b in scaler.reports]
        seen.update(check_reports(reports, seq, placement.groups, ROBOTS, holdings))

    t0 = time.monotonic()
    try:
        summary = main(run, deployment, swarm_hook=scaler.start, after_replay=after)
    finally:
        scaler.stop()
        if deployment.created:
            deployment.remove()
    loaded.timings["live_run_s"] = time.monotonic() - t0
    loaded.timings.update({f"live_{k}_at_s": t for k, (_, t) in scaler.marks.items()})
    print(json.dumps({"k8s_live_scaling": {"marks": scaler.marks, "reports": seen}}))
    assert summary.queries.missing_slots == 0 and summary.queries.errors == []
    assert summary.index is not None and summary.index.settled and summary.index.pending_stores == 0
    # The re-partitioning happened while frames were still coming: the new shards owned groups,
    # and the scale-down began, before the last report.
    assert scaler.marks["new_shards_own_groups"][0] < LIVE_FRAMES, scaler.marks
    assert scaler.marks["scale_to_2_issued"][0] < LIVE_FRAMES, scaler.marks
    assert seen["answers"] > 0 and seen["bounded_below"] > 0, seen
