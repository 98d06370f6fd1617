"""Real containers: the images are built (deploy/build.sh) and each test module
brings up its own compose project on free loopback ports.

Nothing here is skipped when the engine is missing: deploy/build.sh installs
and starts one (deploy/engine.sh), so a machine that cannot run containers
fails these tests with the reason.
"""

from __future__ import annotations

import subprocess
from collections.abc import Iterator
from pathlib import Path

import docker
import pytest

from swarmrec.deployments.compose import (
    ComposeDeployment,
    ComposeSettings,
    SwarmFile,
    down,
    up,
)
from swarmrec.deployments.local import free_port
from swarmrec.evaluation.source import DatasetSource
from swarmrec.experiments.places import PlacesSettings, PlacesSummary, main
from swarmrec.experiments.places.keep import compose
from tests.conftest import REPO


@pytest.fixture(scope="session")
def images() -> None:
    """The service and Prometheus images, built from this checkout (cached layers make a rebuild quick)."""
    proc = subprocess.run([str(REPO / "deploy" / "build.sh")], capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        pytest.fail(f"deploy/build.sh failed ({proc.returncode}):\n{proc.stderr[-4000:]}")


@pytest.fixture(scope="session")
def engine(images: None) -> Iterator[docker.DockerClient]:
    client = docker.from_env()
    yield client
    client.close()


def project_leftovers(client: docker.DockerClient, project: str) -> dict[str, list[str]]:
    """Containers, networks and volumes compose made for ``project`` that still exist."""
    label = {"label": f"com.docker.compose.project={project}"}
    return {
        "containers": [c.name for c in client.containers.list(all=True, filters=label)],
        "networks": [n.name for n in client.networks.list(filters=label)],
        "volumes": [v.name for v in client.volumes.list(filters=label)],
    }


def start_swarm(tmp: Path, project: str, robots: int, frames: int) -> SwarmFile:
    """A places swarm of ``robots`` composed for the first ``frames`` of the synthetic world, up."""
    run = PlacesSettings(
        source=DatasetSource(frames=frames),
        robots=robots,
        swarm=project.replace("-", "_"),
        request_timeout_s=2.0,
        out=tmp,
    )
    settings = ComposeSettings(
        project=project,
        out=tmp,
        router_port=free_port(),
        prometheus_port=free_port(),
        gateway_port=free_port(),
    )
    info = compose(run, settings)
    try:
        up(info, timeout_s=300.0)
    except Exception:
        down(info)
        raise
    return info


def run_attached(folder: Path, out: Path, **hooks: object) -> PlacesSummary:
    """``swarmrec run --attach folder`` as the CLI does it (no plots, no progress bars)."""
    deployment = ComposeDeployment(folder)
    settings = PlacesSettings.from_record(deployment.info.experiment, out=out, plots=False, progress=False)
    return main(settings, deployment, **hooks)  # type: ignore[arg-type]
