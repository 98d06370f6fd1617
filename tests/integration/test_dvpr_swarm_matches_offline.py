"""The full-image method with real processes: a lock-step dvpr swarm (a router, and per
robot a detector in rgbd mode describing each rendered frame, a place-owner and a verifier)
answers every frame exactly as the offline simulation of the descriptors its detectors
produced, and its loop closures are exactly the verified matches.

The expected answers are computed here with the offline code alone: the descriptors the
detectors wrote to their data folders, the shipped centres (nearest centre with
:func:`swarmrec.vpr.clusters.nearest_centre`), the paper's seeded assignment, the int8 code
of :mod:`swarmrec.vpr.quantize`, and :func:`swarmrec.vpr.simulation.run_queries` in the
simulation's arrival order. The expected loop closures: every answered frame with at least
3 objects whose match scores at least 0.3 in :func:`swarmrec.core.verification.verify`
against the constellations the detectors wrote (as the wire carries them, in millimetres).
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from swarmrec.core.presets import get_preset
from swarmrec.core.split import split_frames
from swarmrec.core.verification import verify
from swarmrec.datasets.constellations import read_constellations
from swarmrec.datasets.labels import COCO_NAMES
from swarmrec.datasets.tum_rgbd import frame_id_of, read_tum_rgbd
from swarmrec.deployments.base import Deployment
from swarmrec.deployments.local import LocalDeployment
from swarmrec.evaluation.source import DatasetSource
from swarmrec.experiments.places import PixelSettings, PlacesSettings
from swarmrec.experiments.places.pipeline import as_on_the_wire
from swarmrec.experiments.vpr import DvprSettings, DvprSummary, VprRunSettings, main
from swarmrec.models import DESCRIPTOR_CENTRES, shipped_model
from swarmrec.runtime import keys
from swarmrec.vpr.clusters import load_centres, nearest_centre, random_assignment
from swarmrec.vpr.quantize import Int8Quantizer
from swarmrec.vpr.simulation import arrival_order, robot_of_frames, run_queries
from swarmrec.wire import messages as pb

ROBOTS, C, FRAMES = 4, 5, 200


def _read_answers(path: Path) -> dict[int, dict[str, str]]:
    with path.open(encoding="utf-8") as f:
        return {int(row["frame"]): row for row in csv.DictReader(f)}


@pytest.mark.slow
def test_a_lockstep_dvpr_swarm_answers_every_frame_as_the_offline_simulation_of_its_own_descriptors(
    tmp_path: Path,
) -> None:
    out = tmp_path / "run"
    heard: list[pb.LoopClosure] = []
    held: dict[str, Any] = {}

    def listen(deployment: Deployment) -> None:
        # Every loop closure the place-owners publish, as a client of the swarm hears them.
        client = deployment.client(5.0, role="client")
        client.open()
        held["client"] = client
        key = keys.event(client.swarm, "loop_closure", "*")
        held["sub"] = client.session.declare_subscriber(
            key, lambda sample: heard.append(pb.LoopClosure.FromString(sample.payload.to_bytes()))
        )

    settings = VprRunSettings(
        run=PlacesSettings(
            source=DatasetSource(frames=FRAMES),
            robots=ROBOTS,
            out=out,
            progress=False,
            plots=False,
            pixels=PixelSettings(from_pixels=True),
        ),
        dvpr=DvprSettings(clusters_per_robot=C),
    )
    try:
        summary = main(settings, LocalDeployment.for_run, swarm_hook=listen)
    finally:
        if "sub" in held:
            held["sub"].undeclare()
        if "client" in held:
            held["client"].close()
    assert isinstance(summary, DvprSummary)
    assert summary.queries.frames == FRAMES and summary.queries.missing_slots == 0, summary.queries.errors

    # The descriptors the detectors produced, in frame order.
    frames = read_tum_rgbd(out / "rgbd").frames
    ids = [frame_id_of(f) for f in frames]
    blocks = split_frames(len(ids), ROBOTS)
    robots = robot_of_frames(len(ids), ROBOTS)
    folder = out / "data"
    x = np.stack(
        [
            np.load(folder / f"robot{r}" / "detector" / "descriptors" / f"{ids[g]}.npy")
            for r, block in enumerate(blocks)
            for g in block
        ]
    )
    assert x.shape == (FRAMES, 128) and x.dtype == np.float32

    # The offline simulation of those descriptors.
    centres = load_centres(shipped_model(DESCRIPTOR_CENTRES), ROBOTS * C)
    owners = np.asarray(random_assignment(ROBOTS, C, seed=0).owners, np.int64)[nearest_centre(centres, x)]
    int8 = Int8Quantizer(128)
    expected = run_queries(int8.decode(int8.encode(x)), robots, owners, arrival_order(robots))

    got = _read_answers(out / "answers.csv")
    assert sorted(got) == list(range(FRAMES))
    live_owners = np.array([int(got[g]["owner"]) for g in range(FRAMES)])
    live_matches = np.array([int(got[g]["match_frame"]) for g in range(FRAMES)])
    live_distances = np.array(
        [float(got[g]["distance"]) if got[g]["distance"] else np.inf for g in range(FRAMES)]
    )
    np.testing.assert_array_equal(live_owners, expected.owners)
    np.testing.assert_array_equal(live_matches, expected.matches)
    np.testing.assert_array_equal(live_distances.astype(np.float32), expected.distances.astype(np.float32))
    # The comparison is about something: most frames matched, many queries crossed robots.
    assert np.count_nonzero(expected.matches >= 0) > 0.9 * FRAMES
    assert 0.3 < np.mean(expected.owners != robots) < 1.0
    assert summary.offline_check is not None and summary.offline_check.identical
    # The load each owner counted is the simulation's.
    assert summary.load.queries == np.bincount(expected.owners, minlength=ROBOTS).tolist()

    # Loop closures: every answered frame of >= 3 objects whose match verifies at >= 0.3.
    names = COCO_NAMES
    seqs = [
        as_on_the_wire(read_constellations(folder / f"robot{r}" / "detector" / "constellations", names))
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
        (scored,) = verify(query, (r, t), mr, [(mt, seqs[mr].constellations[mt])], len(names), preset)
        assert float(got[g]["score"]) == pytest.approx(scored.score, abs=5e-7)  # the CSV keeps 6 decimals
        if scored.score > 0 and scored.score >= 0.3:
            closures_expected[(r, t)] = (mr, mt, scored.score)
    with (out / "loop_closures.csv").open(encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    live_closures = {
        (int(c["query_robot"]), int(c["query_frame"])): (int(c["match_robot"]), int(c["match_frame"]))
        for c in rows
    }
    assert len(closures_expected) >= 5
    assert live_closures == {k: v[:2] for k, v in closures_expected.items()}
    # Published on events/loop_closure/<robot> with the verifier's exact score.
    assert {(c.query_robot_id, c.query_frame_index): (c.match_robot_id, c.match_frame_index, c.score)
            for c in heard} == closures_expected  # fmt: skip
    # Bytes were measured on the wire: the query and its answer, and the verification.
    by_message = summary.bytes.per_query_by_message
    assert set(by_message) == {"PlaceQuery", "PlaceMatch", "VerifyRequest", "VerifyReply"}
    assert summary.bytes.model_float32["remote_share"] == pytest.approx(np.mean(expected.owners != robots))
    assert all(code == 0 for code in summary.exit_codes.values()), summary.exit_codes
