"""The other workloads on the real Kubernetes cluster, under mutual TLS: a full-image place
recognition swarm (``swarmrec run --method dvpr --deployment k8s``: per robot a detector in rgbd
mode, a place-owner and a verifier) and a SLAM team (``swarmrec slam run --deployment k8s``: one
slam service per robot), each a :class:`KubernetesDeployment` of 3 robots in a namespace of its
own, on the cluster tests/e2e/test_k8s_cluster.py starts (its fixtures: the cluster is reused
when up, the images loaded once).

The expected answers come from the offline code alone, as for local processes and compose
(tests/e2e/test_compose_dvpr.py, tests/e2e/test_compose_slam.py): the owners, matches and
distances of :func:`swarmrec.vpr.simulation.run_queries` on the descriptors the pods' detectors
wrote, the loop closures of :func:`swarmrec.core.verification.verify` on their constellations;
the SLAM team's merged estimate is :func:`swarmrec.slam.dgs.run_dgs`'s in this process, byte for
byte, and Prometheus counted exactly its messages. Prometheus scraped every pod of each kind, each
pod mounted only its own kind's Secret, and nothing is left on the cluster or the node after.
"""

from __future__ import annotations

import json
import os
import time
import urllib.parse
import urllib.request
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from swarmrec.deployments.base import Deployment
from swarmrec.deployments.kubernetes import KubernetesDeployment, KubernetesSettings, secret_name
from swarmrec.deployments.metrics import scrape_prometheus
from swarmrec.evaluation.source import DatasetSource
from swarmrec.experiments.landmarks.simulation import LandmarkSettings, parse_law, run_simulation
from swarmrec.experiments.places import PixelSettings, PlacesSettings
from swarmrec.experiments.slam import LiveSlamSettings
from swarmrec.experiments.slam import main as slam_main
from swarmrec.experiments.vpr import DvprSettings, DvprSummary, VprRunSettings
from swarmrec.experiments.vpr import main as vpr_main
from swarmrec.models import DESCRIPTOR_CENTRES, shipped_model
from swarmrec.slam.dgs import DgsSettings, run_dgs
from swarmrec.slam.g2o import read_robot_folder, write_g2o
from swarmrec.vpr.clusters import ASSIGNMENT_FORMAT, load_centres
from tests.dvpr_checks import (
    assert_answers_are,
    closures_of,
    detector_frames,
    offline_answers,
    read_closures,
    verified_matches,
)
from tests.e2e import test_k8s_cluster
from tests.e2e.test_k8s_cluster import _kubectl

# The cluster's own fixtures, for this module: the cluster up (reused when up), the images loaded.
cluster = test_k8s_cluster.cluster
loaded = test_k8s_cluster.loaded

pytestmark = [pytest.mark.e2e, pytest.mark.slow, pytest.mark.usefixtures("loaded")]

ROBOTS, FRAMES = 3, 90
DVPR_KINDS = ("verifier", "place-owner", "detector")
#: The shipped centres hold k = 10 (not 3 x c): a table gives the 10 clusters to 3 robots.
OWNERS = (0, 1, 2, 0, 1, 2, 0, 1, 2, 0)


def _prometheus(url: str, path: str) -> Any:
    with urllib.request.urlopen(f"{url}{path}", timeout=10) as resp:
        return json.loads(resp.read())


def _targets(url: str) -> dict[tuple[str, str], str]:
    body = _prometheus(url, "/api/v1/targets?state=active")
    return {
        (t["labels"]["service"], t["labels"]["robot"]): t["health"] for t in body["data"]["activeTargets"]
    }


def _mounted_secrets(deployment: KubernetesDeployment) -> dict[str, set[str]]:
    """Pod -> the Secrets its volumes name (projected ones included)."""
    pods = json.loads(deployment.k("get", "pods", "-o", "json"))["items"]
    out = {}
    for pod in pods:
        names = set()
        for v in pod["spec"].get("volumes", []):
            if "secret" in v:
                names.add(v["secret"]["secretName"])
            for src in v.get("projected", {}).get("sources", []):
                if "secret" in src:
                    names.add(src["secret"]["name"])
        out[pod["metadata"]["name"]] = names
    return out


def _robot_pods_use_their_own_kinds_secret(mounted: dict[str, set[str]], kinds: tuple[str, ...]) -> None:
    expected = {f"{k}-{r}": {secret_name(k)} for k in kinds for r in range(ROBOTS)}
    assert {p: s for p, s in mounted.items() if p.rsplit("-", 1)[0] in kinds} == expected


def _node_folders_gone(deployment: KubernetesDeployment) -> bool:
    info = deployment.info
    return info is not None and all(not Path(f).exists() for f in info.node_volumes)


def test_a_dvpr_swarm_on_kubernetes_answers_every_frame_as_the_offline_simulation(tmp_path: Path) -> None:
    pid = os.getpid()
    table = tmp_path / "assignment.json"
    table.write_text(json.dumps({"format": ASSIGNMENT_FORMAT, "n_robots": ROBOTS, "owners": list(OWNERS)}))
    out = tmp_path / "report"
    settings = VprRunSettings(
        run=PlacesSettings(
            source=DatasetSource(frames=FRAMES),
            robots=ROBOTS,
            swarm=f"e2e_k8s_dvpr_{pid}",
            out=out,
            plots=False,
            progress=False,
            pixels=PixelSettings(from_pixels=True),
        ),
        dvpr=DvprSettings(assignment=table),
    )
    # What `swarmrec run --method dvpr --deployment k8s` builds (its folder: OUT/k8s).
    deployment = KubernetesDeployment(
        KubernetesSettings(namespace=f"swarmrec-e2e-dvpr-{pid}", out=out / "k8s", kubectl=_kubectl())
    )
    seen: dict[str, Any] = {}

    def look(d: Deployment) -> None:
        assert d is deployment
        seen["targets"] = _targets(deployment._info().prometheus_url)
        seen["secrets"] = _mounted_secrets(deployment)

    try:
        summary = vpr_main(settings, lambda _folder: deployment, replayed_hook=look)
    finally:
        deployment.remove()
    assert _node_folders_gone(deployment)

    assert isinstance(summary, DvprSummary)
    assert summary.swarm["deployment"] == f"kubernetes namespace swarmrec-e2e-dvpr-{pid}"
    assert summary.queries.frames == FRAMES and summary.queries.missing_slots == 0, summary.queries.errors
    expected_targets = {("router", "0"), ("gateway", "0")} | {
        (k, str(r)) for r in range(ROBOTS) for k in DVPR_KINDS
    }
    assert seen["targets"] == dict.fromkeys(expected_targets, "up")
    _robot_pods_use_their_own_kinds_secret(seen["secrets"], DVPR_KINDS)

    # The descriptors the pods' detectors produced (copied from their node folders), and their
    # offline simulation.
    data = out / "k8s" / "data"
    frames = detector_frames(out / "rgbd", data, ROBOTS)
    assert len(frames.robots) == FRAMES
    centres = load_centres(shipped_model(DESCRIPTOR_CENTRES), len(OWNERS))
    expected = offline_answers(frames, centres, OWNERS)
    assert_answers_are(out / "answers.csv", expected, frames, matched=0.8)
    assert summary.offline_check is not None and summary.offline_check.identical
    # The load each owner counted, read through the cluster's Prometheus, is the simulation's.
    assert summary.load.queries == np.bincount(expected.owners, minlength=ROBOTS).tolist()
    # Loop closures: every answered frame of >= 3 objects whose match verifies at >= 0.3.
    closures = closures_of(verified_matches(data, frames, expected))
    assert len(closures) >= 2  # 2 on these 90 frames
    assert read_closures(out / "loop_closures.csv") == {k: v[:2] for k, v in closures.items()}
    assert set(summary.bytes.per_query_by_message) == {
        "PlaceQuery",
        "PlaceMatch",
        "VerifyRequest",
        "VerifyReply",
    }


def _sent_messages(prometheus_url: str) -> float:
    """The estimates every slam service says it sent, summed, once Prometheus has scraped every
    service after now (a read right after the solve could precede the scrape of its counters)."""
    fresh = scrape_prometheus(prometheus_url, fresh_after=time.time())
    assert not fresh.failed, fresh.failed
    return fresh.total("swarmrec_slam_sent_messages_total", carries="estimates")


def test_a_slam_team_on_kubernetes_solves_as_run_dgs_in_one_process(tmp_path: Path) -> None:
    pid = os.getpid()
    # What `swarmrec slam run --deployment k8s` builds, kept for a second solve on the same team.
    deployment = KubernetesDeployment(
        KubernetesSettings(
            namespace=f"swarmrec-e2e-slam-{pid}", out=tmp_path / "k8s", kubectl=_kubectl(), keep=True
        )
    )
    summaries, sent = [], []
    try:
        for run in ("first", "second"):
            # The second solve is the same team's: the robot folder the first wrote (the same spec).
            folder = tmp_path / "first" / "input" if run == "second" else None
            settings = LiveSlamSettings(
                out=tmp_path / run,
                folder=folder,
                world="chairs",
                robots=ROBOTS,
                seed=0,
                swarm=f"e2e_k8s_slam_{pid}",
                plots=False,
                progress=False,
            )
            summaries.append(slam_main(settings, deployment))
            sent.append(_sent_messages(deployment._info().prometheus_url))
        targets = _targets(deployment._info().prometheus_url)
        secrets = _mounted_secrets(deployment)
    finally:
        deployment.remove()
    assert _node_folders_gone(deployment)
    assert targets == dict.fromkeys(
        {("router", "0"), ("gateway", "0")} | {("slam", str(r)) for r in range(ROBOTS)}, "up"
    )
    _robot_pods_use_their_own_kinds_secret(secrets, ("slam",))

    # The reference: run_dgs in this process on the folder the pods read (from the input ConfigMap).
    graph = read_robot_folder(tmp_path / "first" / "input").graph
    assert len(graph.robots) == ROBOTS
    reference = run_dgs(graph, DgsSettings())
    write_g2o(tmp_path / "reference.g2o", graph, reference.poses)
    for run, summary in zip(("first", "second"), summaries, strict=True):
        assert summary.outcome == "converged", summary.robot_outcomes
        assert summary.check is not None and summary.check.identical, summary.check
        assert summary.deployment == f"kubernetes namespace swarmrec-e2e-slam-{pid}"
        # The merged estimate, as the report wrote it, is run_dgs's to the last bit.
        assert (tmp_path / run / "merged.g2o").read_bytes() == (tmp_path / "reference.g2o").read_bytes()
    assert [s.solve_id for s in summaries] == [1, 2]
    # Prometheus' counters: the first solve sent exactly run_dgs's messages, the second as many again.
    assert sent == [len(reference.messages), 2 * len(reference.messages)] and sent[0] > 0


def test_the_street_simulation_runs_through_kubernetes_as_through_processes(tmp_path: Path) -> None:
    pid = os.getpid()
    # What `swarmrec landmarks --deployment k8s` builds: per robot a detector (classifier) and a fusion pod.
    namespace = f"swarmrec-e2e-landmarks-{pid}"
    deployment = KubernetesDeployment(
        KubernetesSettings(namespace=namespace, out=tmp_path / "k8s", kubectl=_kubectl())
    )
    laws = ("paper:2", "agreement")
    settings = LandmarkSettings(
        out=tmp_path / "run",
        configurations=3,
        robots=ROBOTS,
        laws=tuple(parse_law(law) for law in laws),
        swarm=f"e2e_k8s_landmarks_{pid}",
        progress=False,
    )
    seen: dict[str, Any] = {}

    def look(d: Deployment) -> None:
        assert d is deployment
        seen["secrets"] = _mounted_secrets(deployment)

    try:
        result = run_simulation(settings, deployment, swarm_hook=look)
    finally:
        deployment.remove()
    _robot_pods_use_their_own_kinds_secret(seen["secrets"], ("fusion", "detector"))
    assert result.errors == [] and result.failures == {}
    assert len(result.rounds) == settings.configurations * len(laws) * ROBOTS
    for r in result.rounds:
        # Every robot heard every other robot, and fused exactly as the core recomputes it.
        assert r.complete and r.incorporated == ROBOTS - 1 and r.rejected == 0
        assert r.core_difference == 0.0
    # The cluster's Prometheus counted Algorithm 1's copies: n per link direction per round.
    sent = result.metrics.by_label("swarmrec_messages_sent_total", "message", scope="swarm")
    expected = sum(ROBOTS * int(c.adjacency.sum()) for c in result.configurations) * len(laws)
    assert sent["ClassifierOutput"] == expected > 0
    assert result.metrics.failed == []
