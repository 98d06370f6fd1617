"""The live distributed SLAM solve in containers: a 3-robot team (a router, the gateway, one
slam service per robot, and Prometheus) composed by ``swarmrec compose up --workload slam``
and solved from the host as ``swarmrec slam run --attach`` does, under mutual TLS.

The reference is :func:`swarmrec.slam.dgs.run_dgs` in this process on the robot folder the
containers read: the team's merged estimate must be its estimate, written to g2o the same
way byte for byte; the messages Prometheus counted must be exactly its messages; a second
solve on the same, still running team must be identical again; ``compose down`` leaves
nothing.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import docker
import pytest

from swarmrec.deployments.compose import ComposeDeployment, ComposeSettings, SwarmFile, down, up
from swarmrec.deployments.local import free_port
from swarmrec.deployments.metrics import scrape_prometheus
from swarmrec.experiments.slam import LiveSlamSettings, main
from swarmrec.experiments.slam.keep import compose, from_record
from swarmrec.slam.dgs import DgsSettings, run_dgs
from swarmrec.slam.g2o import read_robot_folder, write_g2o
from tests.e2e.conftest import project_leftovers

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

ROBOTS = 3


def _sent_messages(info: SwarmFile) -> float:
    """The estimates every slam service says it sent, summed, once Prometheus has scraped every
    service after now (a read right after the solve could precede the scrape of its counters)."""
    fresh = scrape_prometheus(info.prometheus_url, fresh_after=time.time())
    assert not fresh.failed, fresh.failed
    return fresh.total("swarmrec_slam_sent_messages_total", carries="estimates")


def test_a_compose_slam_team_solves_as_run_dgs_in_one_process(
    engine: docker.DockerClient, tmp_path: Path
) -> None:
    project = f"swarmrec-e2e-slam-{os.getpid()}"
    folder = tmp_path / "compose"
    team = LiveSlamSettings(
        out=folder, world="chairs", robots=ROBOTS, seed=0, swarm=project.replace("-", "_"), progress=False
    )
    info = compose(
        team,
        ComposeSettings(
            project=project,
            out=folder,
            router_port=free_port(),
            prometheus_port=free_port(),
            gateway_port=free_port(),
        ),
    )
    summaries = []
    try:
        up(info, timeout_s=300.0)
        deployment = ComposeDeployment(folder)
        for run in ("first", "second"):
            settings = from_record(
                deployment.info.experiment, out=tmp_path / run, plots=False, progress=False
            )
            summaries.append(main(settings, deployment))
            if run == "first":
                sent_first = _sent_messages(info)
    finally:
        down(info)
    assert project_leftovers(engine, project) == {"containers": [], "networks": [], "volumes": []}

    # The reference: run_dgs in this process on the folder the containers read.
    graph = read_robot_folder(folder / "slam").graph
    assert len(graph.robots) == ROBOTS
    reference = run_dgs(graph, DgsSettings())
    write_g2o(tmp_path / "reference.g2o", graph, reference.poses)
    for run, summary in zip(("first", "second"), summaries, strict=True):
        assert summary.outcome == "converged", summary.robot_outcomes
        assert summary.check is not None and summary.check.identical, summary.check
        # The merged estimate, as the report wrote it, is run_dgs's to the last bit.
        assert (tmp_path / run / "merged.g2o").read_bytes() == (tmp_path / "reference.g2o").read_bytes()
    assert [s.solve_id for s in summaries] == [1, 2]
    assert sent_first == len(reference.messages) > 0
