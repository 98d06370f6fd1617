"""Full-image place recognition in containers: a 3-robot dvpr swarm (a router, the gateway,
per robot a detector in rgbd mode, a place-owner and a verifier, and Prometheus) composed by
``swarmrec compose up --workload dvpr`` and replayed in lock-step from the host as
``swarmrec run --attach`` does, under mutual TLS, the cluster owners re-balanced live after
every 20 steps (``--rebalance-every``: docs/vpr.md, "Re-balancing a live swarm").

The expected answers come from the offline code alone, as in
tests/integration/test_dvpr_swarm_matches_offline.py for local processes: the descriptors the
containers' detectors wrote (to their data folders, bind mounts on the host), the shipped
k = 10 centres, the assignment table given to the swarm, the tables the coordinator rolled
out (``tables/v<n>.pb`` of the report), the int8 code, and
:func:`swarmrec.vpr.simulation.run_queries` in the simulation's arrival order; the loop
closures from :func:`swarmrec.core.verification.verify` on the constellations the detectors
wrote. Prometheus must have scraped every service, and a second run on the swarm, which
now holds the first one's frames, is refused; ``compose down`` leaves nothing.
"""

from __future__ import annotations

import json
import os
import urllib.request
from pathlib import Path

import docker
import numpy as np
import pytest

from swarmrec.deployments.compose import ComposeDeployment, ComposeSettings, down, up
from swarmrec.deployments.local import free_port
from swarmrec.errors import ConfigError
from swarmrec.evaluation.source import DatasetSource
from swarmrec.experiments.places import PixelSettings, PlacesSettings
from swarmrec.experiments.vpr import DvprSettings, DvprSummary, VprRunSettings, main
from swarmrec.experiments.vpr.keep import compose, from_record
from swarmrec.models import DESCRIPTOR_CENTRES, shipped_model
from swarmrec.vpr.clusters import ASSIGNMENT_FORMAT, load_centres
from swarmrec.wire import messages as pb
from tests.dvpr_checks import (
    assert_answers_are,
    closures_of,
    detector_frames,
    offline_answers_with_tables,
    read_closures,
    verified_matches,
)
from tests.e2e.conftest import project_leftovers

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

ROBOTS, FRAMES = 3, 240
KINDS = ("verifier", "place-owner", "detector")
#: The shipped centres hold k = 10 (not 3 x c): a table gives the 10 clusters to 3 robots.
OWNERS = (0, 1, 2, 0, 1, 2, 0, 1, 2, 0)
#: Lock-step steps between live re-balancings: after steps 20, 40 and 60 of 80.
EVERY = 20


def _targets(prometheus_url: str) -> dict[tuple[str, str], str]:
    with urllib.request.urlopen(f"{prometheus_url}/api/v1/targets?state=active", timeout=10) as resp:
        body = json.loads(resp.read())
    return {
        (t["labels"]["service"], t["labels"]["robot"]): t["health"] for t in body["data"]["activeTargets"]
    }


def test_a_compose_dvpr_swarm_answers_every_frame_as_the_offline_simulation_of_its_own_descriptors(
    engine: docker.DockerClient, tmp_path: Path
) -> None:
    project = f"swarmrec-e2e-dvpr-{os.getpid()}"
    table = tmp_path / "assignment.json"
    table.write_text(json.dumps({"format": ASSIGNMENT_FORMAT, "n_robots": ROBOTS, "owners": list(OWNERS)}))
    folder = tmp_path / "compose"
    composed = VprRunSettings(
        run=PlacesSettings(
            source=DatasetSource(frames=FRAMES),
            robots=ROBOTS,
            swarm=project.replace("-", "_"),
            out=folder,
            progress=False,
            pixels=PixelSettings(from_pixels=True),
        ),
        dvpr=DvprSettings(assignment=table, rebalance_every=EVERY),
    )
    info = compose(
        composed,
        ComposeSettings(
            project=project,
            out=folder,
            router_port=free_port(),
            prometheus_port=free_port(),
            gateway_port=free_port(),
        ),
    )
    out = tmp_path / "report"
    try:
        up(info, timeout_s=300.0)
        deployment = ComposeDeployment(folder)
        settings = from_record(deployment.info.experiment, out=out, plots=False, progress=False)
        summary = main(settings, lambda _folder: deployment)
        targets = _targets(info.prometheus_url)
        # The swarm keeps what it stored: a second run would find the first one's frames.
        with pytest.raises(ConfigError, match="already holds data"):
            main(settings.with_(run=settings.run.with_(out=tmp_path / "again")), lambda _folder: deployment)
    finally:
        down(info)
    assert project_leftovers(engine, project) == {"containers": [], "networks": [], "volumes": []}

    assert isinstance(summary, DvprSummary)
    assert summary.queries.frames == FRAMES and summary.queries.missing_slots == 0, summary.queries.errors
    expected_targets = {("router", "0"), ("gateway", "0")} | {
        (k, str(r)) for r in range(ROBOTS) for k in KINDS
    }
    assert targets == dict.fromkeys(expected_targets, "up")

    # The descriptors the containers' detectors produced, on the host, and their offline simulation.
    data = folder / "data"
    frames = detector_frames(folder / "dataset", data, ROBOTS)
    assert len(frames.robots) == FRAMES
    centres = load_centres(shipped_model(DESCRIPTOR_CENTRES), len(OWNERS))
    assert summary.rebalancing is not None and [r.after_step for r in summary.rebalancing] == [20, 40, 60]
    tables = [
        (r.at_frame, pb.ClusterTable.FromString((out / "tables" / f"v{r.version}.pb").read_bytes()))
        for r in summary.rebalancing
    ]
    expected = offline_answers_with_tables(frames, centres, OWNERS, tables)
    assert_answers_are(out / "answers.csv", expected, frames, matched=0.8)
    assert summary.offline_check is not None and summary.offline_check.identical
    # The load each owner counted, read through Prometheus, is the simulation's.
    assert summary.load.queries == np.bincount(expected.owners, minlength=ROBOTS).tolist()
    # Loop closures: every answered frame of >= 3 objects whose match verifies at >= 0.3.
    closures = closures_of(verified_matches(data, frames, expected))
    assert len(closures) >= 5
    assert read_closures(out / "loop_closures.csv") == {k: v[:2] for k, v in closures.items()}
    # Bytes were measured on the wire (Prometheus' counters of this run), the re-balancing's too.
    assert {"PlaceQuery", "PlaceMatch", "VerifyRequest", "VerifyReply"} <= set(
        summary.bytes.per_query_by_message
    )
    assert {"ClusterLoad", "AdoptTableRequest", "StoreEntriesRequest"} <= set(
        summary.bytes.per_query_by_message
    )
