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

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from swarmrec.deployments.base import Deployment
from swarmrec.deployments.local import LocalDeployment
from swarmrec.evaluation.source import DatasetSource
from swarmrec.experiments.places import PixelSettings, PlacesSettings
from swarmrec.experiments.vpr import DvprSettings, DvprSummary, VprRunSettings, main
from swarmrec.models import DESCRIPTOR_CENTRES, shipped_model
from swarmrec.runtime import keys
from swarmrec.vpr.clusters import load_centres, random_assignment
from swarmrec.wire import messages as pb
from tests.dvpr_checks import (
    assert_answers_are,
    closures_of,
    detector_frames,
    offline_answers,
    offline_answers_with_tables,
    read_answers,
    read_closures,
    verified_matches,
)

ROBOTS, C, FRAMES = 4, 5, 200


def _run(out: Path) -> PlacesSettings:
    """Both tests' run: FRAMES of the synthetic world rendered, ROBOTS robots, no plots."""
    return PlacesSettings(
        source=DatasetSource(frames=FRAMES),
        robots=ROBOTS,
        out=out,
        progress=False,
        plots=False,
        pixels=PixelSettings(from_pixels=True),
    )


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

    settings = VprRunSettings(run=_run(out), dvpr=DvprSettings(clusters_per_robot=C))
    try:
        summary = main(settings, LocalDeployment.for_run, swarm_hook=listen)
    finally:
        if "sub" in held:
            held["sub"].undeclare()
        if "client" in held:
            held["client"].close()
    assert isinstance(summary, DvprSummary)
    assert summary.queries.frames == FRAMES and summary.queries.missing_slots == 0, summary.queries.errors

    # The descriptors the detectors produced, and their offline simulation.
    folder = out / "data"
    frames = detector_frames(out / "rgbd", folder, ROBOTS)
    assert len(frames.robots) == FRAMES
    centres = load_centres(shipped_model(DESCRIPTOR_CENTRES), ROBOTS * C)
    expected = offline_answers(frames, centres, random_assignment(ROBOTS, C, seed=0).owners)
    assert_answers_are(out / "answers.csv", expected, frames, matched=0.9)
    assert summary.offline_check is not None and summary.offline_check.identical
    # The load each owner counted is the simulation's.
    assert summary.load.queries == np.bincount(expected.owners, minlength=ROBOTS).tolist()

    # Every answered frame of >= 3 objects: its score as the verifier computes it (the CSV keeps
    # 6 decimals); the loop closures are those that verify at >= 0.3.
    verified = verified_matches(folder, frames, expected)
    got = read_answers(out / "answers.csv")
    for (r, t), (_mr, _mt, score) in verified.items():
        assert float(got[frames.blocks[r].start + t]["score"]) == pytest.approx(score, abs=5e-7)
    closures_expected = closures_of(verified)
    assert len(closures_expected) >= 5
    assert read_closures(out / "loop_closures.csv") == {k: v[:2] for k, v in closures_expected.items()}
    # Published on events/loop_closure/<robot> with the verifier's exact score.
    assert {(c.query_robot_id, c.query_frame_index): (c.match_robot_id, c.match_frame_index, c.score)
            for c in heard} == closures_expected  # fmt: skip
    # Bytes were measured on the wire: the query and its answer, and the verification.
    by_message = summary.bytes.per_query_by_message
    assert set(by_message) == {"PlaceQuery", "PlaceMatch", "VerifyRequest", "VerifyReply"}
    assert summary.bytes.model_float32["remote_share"] == pytest.approx(
        np.mean(expected.owners != frames.robots)
    )
    assert all(code == 0 for code in summary.exit_codes.values()), summary.exit_codes


@pytest.mark.slow
def test_a_lockstep_dvpr_run_rebalanced_live_answers_as_the_offline_simulation_of_its_tables(
    tmp_path: Path,
) -> None:
    """``--rebalance-every``: the job asks the coordinator between steps; the report names
    each table and the load it gave, writes the tables, and its answers are the offline
    simulation of those tables on the detectors' descriptors (built here: tests/dvpr_checks)."""
    out = tmp_path / "run"
    c, every = 10, 10  # k = 40: shipped centres
    settings = VprRunSettings(run=_run(out), dvpr=DvprSettings(clusters_per_robot=c, rebalance_every=every))
    summary = main(settings, LocalDeployment.for_run)
    assert isinstance(summary, DvprSummary)
    assert summary.queries.frames == FRAMES and summary.queries.missing_slots == 0, summary.queries.errors
    steps = FRAMES // ROBOTS
    assert summary.rebalancing is not None
    assert [r.after_step for r in summary.rebalancing] == list(range(every, steps, every))
    assert [r.version for r in summary.rebalancing] == list(range(1, len(summary.rebalancing) + 1))
    tables = [
        (r.at_frame, pb.ClusterTable.FromString((out / "tables" / f"v{r.version}.pb").read_bytes()))
        for r in summary.rebalancing
    ]
    frames = detector_frames(out / "rgbd", out / "data", ROBOTS)
    centres = load_centres(shipped_model(DESCRIPTOR_CENTRES), ROBOTS * c)
    expected = offline_answers_with_tables(
        frames, centres, random_assignment(ROBOTS, c, seed=0).owners, tables
    )
    assert_answers_are(out / "answers.csv", expected, frames, matched=0.9)
    assert summary.offline_check is not None and summary.offline_check.identical
    assert summary.load.queries == np.bincount(expected.owners, minlength=ROBOTS).tolist()
    # The moves and copies travelled between robots, measured like the queries.
    assert {"StoreEntriesRequest", "ClusterLoad", "AdoptTableRequest"} <= set(
        summary.bytes.per_query_by_message
    )
    assert sum(r.moved for r in summary.rebalancing) > 0
