"""Full-image place recognition in containers: a 3-robot dvpr swarm (a router, the gateway,
per robot a detector in rgbd mode, a place-owner and a verifier, and Prometheus) composed by
``swarmrec compose up --workload dvpr`` and replayed in lock-step from the host as
``swarmrec run --attach`` does, under mutual TLS.

The expected answers come from the offline code alone, as in
tests/integration/test_dvpr_swarm_matches_offline.py for local processes: the descriptors the
containers' detectors wrote (to their data folders, bind mounts on the host), the shipped
k = 10 centres, the assignment table given to the swarm, the int8 code, and
:func:`swarmrec.vpr.simulation.run_queries` in the simulation's arrival order; the loop
closures from :func:`swarmrec.core.verification.verify` on the constellations the detectors
wrote. Prometheus must have scraped every service, and a second run on the swarm, which
now holds the first one's frames, is refused; ``compose down`` leaves nothing.
"""

from __future__ import annotations

import csv
import json
import os
import urllib.request
from pathlib import Path

import docker
import numpy as np
import pytest

from swarmrec.core.presets import get_preset
from swarmrec.core.split import split_frames
from swarmrec.core.verification import verify
from swarmrec.datasets.constellations import read_constellations
from swarmrec.datasets.labels import COCO_NAMES
from swarmrec.datasets.tum_rgbd import frame_id_of, read_tum_rgbd
from swarmrec.deployments.compose import ComposeDeployment, ComposeSettings, down, up
from swarmrec.deployments.local import free_port
from swarmrec.errors import ConfigError
from swarmrec.evaluation.source import DatasetSource
from swarmrec.experiments.places import PixelSettings, PlacesSettings
from swarmrec.experiments.places.pipeline import as_on_the_wire
from swarmrec.experiments.vpr import DvprSettings, DvprSummary, VprRunSettings, main
from swarmrec.experiments.vpr.keep import compose, from_record
from swarmrec.models import DESCRIPTOR_CENTRES, shipped_model
from swarmrec.vpr.clusters import ASSIGNMENT_FORMAT, load_centres, nearest_centre
from swarmrec.vpr.quantize import Int8Quantizer
from swarmrec.vpr.simulation import arrival_order, robot_of_frames, run_queries
from tests.e2e.conftest import project_leftovers

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

ROBOTS, FRAMES = 3, 240
KINDS = ("verifier", "place-owner", "detector")
#: The shipped centres hold k = 10 (not 3 x c): a table gives the 10 clusters to 3 robots.
OWNERS = (0, 1, 2, 0, 1, 2, 0, 1, 2, 0)


def _answers(path: Path) -> dict[int, dict[str, str]]:
    with path.open(encoding="utf-8") as f:
        return {int(row["frame"]): row for row in csv.DictReader(f)}


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
        dvpr=DvprSettings(assignment=table),
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

    # The descriptors the containers' detectors produced, in frame order, on the host.
    frames = read_tum_rgbd(folder / "dataset").frames
    ids = [frame_id_of(f) for f in frames]
    assert len(ids) == FRAMES
    blocks = split_frames(FRAMES, ROBOTS)
    robots = robot_of_frames(FRAMES, ROBOTS)
    data = folder / "data"
    x = np.stack(
        [
            np.load(data / f"robot{r}" / "detector" / "descriptors" / f"{ids[g]}.npy")
            for r, block in enumerate(blocks)
            for g in block
        ]
    )
    assert x.shape == (FRAMES, 128) and x.dtype == np.float32

    # The offline simulation of those descriptors.
    centres = load_centres(shipped_model(DESCRIPTOR_CENTRES), len(OWNERS))
    owners = np.asarray(OWNERS, np.int64)[nearest_centre(centres, x)]
    int8 = Int8Quantizer(128)
    expected = run_queries(int8.decode(int8.encode(x)), robots, owners, arrival_order(robots))

    got = _answers(out / "answers.csv")
    assert sorted(got) == list(range(FRAMES))
    np.testing.assert_array_equal([int(got[g]["owner"]) for g in range(FRAMES)], expected.owners)
    np.testing.assert_array_equal([int(got[g]["match_frame"]) for g in range(FRAMES)], expected.matches)
    live_distances = np.array(
        [float(got[g]["distance"]) if got[g]["distance"] else np.inf for g in range(FRAMES)]
    )
    np.testing.assert_array_equal(live_distances.astype(np.float32), expected.distances.astype(np.float32))
    # The comparison is about something: most frames matched, queries crossed robots.
    assert np.count_nonzero(expected.matches >= 0) > 0.8 * FRAMES
    assert 0.3 < np.mean(expected.owners != robots) < 1.0
    assert summary.offline_check is not None and summary.offline_check.identical
    # The load each owner counted, read through Prometheus, is the simulation's.
    assert summary.load.queries == np.bincount(expected.owners, minlength=ROBOTS).tolist()

    # Loop closures: every answered frame of >= 3 objects whose match verifies at >= 0.3.
    seqs = [
        as_on_the_wire(read_constellations(data / f"robot{r}" / "detector" / "constellations", COCO_NAMES))
        for r in range(ROBOTS)
    ]
    preset = get_preset("paper")
    closures_expected = {}
    for g in range(FRAMES):
        h = int(expected.matches[g])
        r, t = int(robots[g]), g - blocks[int(robots[g])].start
        query = seqs[r].constellations[t]
        if h < 0 or len(query) < preset.min_objects:
            continue
        mr, mt = int(robots[h]), h - blocks[int(robots[h])].start
        (scored,) = verify(query, (r, t), mr, [(mt, seqs[mr].constellations[mt])], len(COCO_NAMES), preset)
        if scored.score > 0 and scored.score >= 0.3:
            closures_expected[(r, t)] = (mr, mt)
    with (out / "loop_closures.csv").open(encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    live_closures = {
        (int(c["query_robot"]), int(c["query_frame"])): (int(c["match_robot"]), int(c["match_frame"]))
        for c in rows
    }
    assert len(closures_expected) >= 5
    assert live_closures == closures_expected
    # Bytes were measured on the wire (Prometheus' counters of this run).
    assert set(summary.bytes.per_query_by_message) == {
        "PlaceQuery",
        "PlaceMatch",
        "VerifyRequest",
        "VerifyReply",
    }
