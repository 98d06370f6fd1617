"""The landmark simulation through a compose swarm: a router, per robot a detector in
classifier mode and a fusion service, and Prometheus, all containers, driven from the
host (``swarmrec landmarks --attach``).

The containers find the shipped classifier in the image (``$SWARMREC_MODELS``); every
robot's posterior must equal the core's recomputation; the flooded messages
Prometheus counted for the run must be exactly Algorithm 1's; a second run on the
same, still running swarm continues the round ids and counts only its own traffic;
``compose down`` leaves nothing.
"""

from __future__ import annotations

import os
from pathlib import Path

import docker
import pytest

from swarmrec.deployments.compose import ComposeDeployment, ComposeSettings, down, up, write_compose
from swarmrec.deployments.local import free_port
from swarmrec.experiments.landmarks.simulation import LandmarkSettings, parse_law, run_simulation, swarm_spec
from tests.e2e.conftest import project_leftovers

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

ROBOTS = 4


def test_the_street_simulation_runs_through_containers_as_through_processes(
    engine: docker.DockerClient, tmp_path: Path
) -> None:
    project = f"swarmrec-e2e-landmarks-{os.getpid()}"
    swarm = project.replace("-", "_")
    spec = swarm_spec(LandmarkSettings(out=tmp_path / "unused", robots=ROBOTS, swarm=swarm))
    settings = ComposeSettings(
        project=project, out=tmp_path / "compose", router_port=free_port(), prometheus_port=free_port()
    )
    info = write_compose(spec, settings)
    try:
        up(info, timeout_s=300.0)
        for configurations, laws in ((5, ("paper:2", "agreement")), (2, ("paper:0",))):
            settings = LandmarkSettings(
                out=tmp_path / f"run{configurations}",
                configurations=configurations,
                robots=ROBOTS,
                laws=tuple(parse_law(law) for law in laws),
                swarm=swarm,
                progress=False,
            )
            result = run_simulation(settings, ComposeDeployment(tmp_path / "compose"))
            assert result.errors == [] and result.failures == {}
            assert len(result.rounds) == configurations * len(laws) * ROBOTS
            for r in result.rounds:
                assert r.complete and r.incorporated == ROBOTS - 1 and r.rejected == 0
                assert r.core_difference == 0.0
            # Prometheus' counters of this run only: n copies per link direction per round.
            sent = result.metrics.by_label("swarmrec_messages_sent_total", "message", scope="swarm")
            expected = sum(ROBOTS * int(c.adjacency.sum()) for c in result.configurations) * len(laws)
            assert sent["ClassifierOutput"] == expected
            assert result.metrics.failed == []
    finally:
        down(info)
    assert project_leftovers(engine, project) == {"containers": [], "networks": [], "volumes": []}
