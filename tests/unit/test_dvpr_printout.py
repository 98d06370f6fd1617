"""``swarmrec run --method dvpr``'s printout says where the swarm ran: the local processes it
started, or the description of a deployment that started none of its own (compose, Kubernetes)."""

from __future__ import annotations

from pathlib import Path

import pytest

from swarmrec.cli.vpr import print_dvpr
from swarmrec.deployments.kubernetes import KubernetesDeployment, KubernetesSettings
from swarmrec.experiments.vpr import DvprSummary
from swarmrec.experiments.vpr.report import DvprBytes, DvprQueries, OwnerLoad


def _summary(deployment: str, processes: int) -> DvprSummary:
    swarm = {
        "robots": 3,
        "pace": "lockstep",
        "clusters": 3,
        "clusters_per_robot": 1,
        "assignment": {"version": 1},
        "wire_code": "int8",
        "deployment": deployment,
        "processes": processes,
    }
    model = {"total": 0.0, "remote_share": 0.0}
    return DvprSummary(
        dataset={"name": "office", "frames": 6},
        swarm=swarm,
        queries=DvprQueries(6, 6, 0, 0, 0, 0, 0, [], {}, {}),
        bytes=DvprBytes(0.0, 0.0, {}, 0.0, 0.0, model, model, 0.0),
        load=OwnerLoad([2, 2, 2], 1.0, None),
        rejected_requests=0.0,
        peer_failures={},
        scrape_failed=[],
        exit_codes={},
        timings={},
    )


def _first_line(s: DvprSummary, capsys: pytest.CaptureFixture[str]) -> str:
    print_dvpr(s, Path("runs/dvpr"))
    return capsys.readouterr().out.splitlines()[0]


def test_a_kubernetes_run_names_its_namespace_not_zero_processes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # What the pipeline records: the deployment's description, and the processes its stop
    # reports (none: the pods are the cluster's).
    k8s = KubernetesDeployment(KubernetesSettings(namespace="run-ns", out=tmp_path))
    line = _first_line(_summary(k8s.description, len(k8s.stop())), capsys)
    assert "(6 frames, kubernetes namespace run-ns)" in line
    assert "processes" not in line


def test_a_compose_run_names_its_project(capsys: pytest.CaptureFixture[str]) -> None:
    line = _first_line(_summary("compose project lab", 0), capsys)
    assert "(6 frames, compose project lab)" in line


def test_a_local_run_counts_its_processes(capsys: pytest.CaptureFixture[str]) -> None:
    line = _first_line(_summary("local processes", 10), capsys)
    assert "(6 frames, 10 processes)" in line
