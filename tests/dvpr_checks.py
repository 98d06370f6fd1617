"""What every full-image swarm test checks, wherever the swarm ran (local processes, compose,
Kubernetes): the detectors' own descriptors, the offline simulation of them, and the answers
and loop closures the run wrote against it.

The expected values come from the offline simulation (``swarmrec.vpr.simulation``) and the
verifier's core (``swarmrec.core.verification``), never from the swarm's code path."""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from swarmrec.core.presets import get_preset
from swarmrec.core.split import split_frames
from swarmrec.core.verification import verify
from swarmrec.datasets.constellations import read_constellations
from swarmrec.datasets.labels import COCO_NAMES
from swarmrec.datasets.tum_rgbd import frame_id_of, read_tum_rgbd
from swarmrec.experiments.places.pipeline import as_on_the_wire
from swarmrec.vpr.balance import replica_owners
from swarmrec.vpr.clusters import Assignment, nearest_centre
from swarmrec.vpr.quantize import Int8Quantizer
from swarmrec.vpr.simulation import Answers, Reassignment, arrival_order, robot_of_frames, run_queries
from swarmrec.wire import messages as pb

#: The score a verified match needs to be a loop closure (the place owners' default).
CLOSURE_MIN_SCORE = 0.3


@dataclass(frozen=True)
class Frames:
    """A run's frames: their robots, each robot's block, and the descriptors its detector wrote."""

    robots: npt.NDArray[np.int64]
    blocks: list[range]
    descriptors: npt.NDArray[np.float32]


def detector_frames(rgbd: Path, data: Path, n_robots: int) -> Frames:
    """The descriptors each robot's detector wrote under ``data/robot<r>/detector/descriptors``
    for the RGB-D folder ``rgbd``, in frame order."""
    ids = [frame_id_of(f) for f in read_tum_rgbd(rgbd).frames]
    blocks = split_frames(len(ids), n_robots)
    x = np.stack(
        [
            np.load(data / f"robot{r}" / "detector" / "descriptors" / f"{ids[g]}.npy")
            for r, block in enumerate(blocks)
            for g in block
        ]
    )
    assert x.shape == (len(ids), 128) and x.dtype == np.float32
    return Frames(robot_of_frames(len(ids), n_robots), blocks, x)


def offline_answers(
    frames: Frames, centres: npt.NDArray[np.float32], owner_of_cluster: npt.ArrayLike
) -> Answers:
    """The offline simulation of the frames' descriptors: each routed to the owner of its
    nearest centre, as int8 codes on the wire, queried in arrival order."""
    owners = np.asarray(owner_of_cluster, np.int64)[nearest_centre(centres, frames.descriptors)]
    int8 = Int8Quantizer(128)
    codes = int8.decode(int8.encode(frames.descriptors))
    return run_queries(codes, frames.robots, owners, arrival_order(frames.robots))


def offline_answers_with_tables(
    frames: Frames,
    centres: npt.NDArray[np.float32],
    owner_of_cluster: npt.ArrayLike,
    tables: list[tuple[int, pb.ClusterTable]],
) -> Answers:
    """:func:`offline_answers` with live re-balancings: from arrival position ``at`` on, each
    table routes the queries by their float32 descriptors; what was stored before moves to
    the owner and the copy holders (``replica_owners``) of its decoded int8 code, as its
    holder computes them; later queries are also stored at their code's copy holders."""
    n_robots = len(frames.blocks)
    order = arrival_order(frames.robots)
    arrival = np.empty(len(order), np.int64)
    arrival[order] = np.arange(len(order))
    int8 = Int8Quantizer(128)
    codes = int8.decode(int8.encode(frames.descriptors))
    switches = []
    for at, t in tables:
        c = np.frombuffer(t.centres, "<f4").reshape(len(t.owners), 128)
        owners = np.asarray(t.owners, np.int64)
        routed = np.where(
            arrival < at, owners[nearest_centre(c, codes)], owners[nearest_centre(c, frames.descriptors)]
        )
        table = Assignment(tuple(int(o) for o in t.owners), n_robots)
        copies = replica_owners(c, table, codes, t.copy_margin, t.copy_neighbours)
        switches.append(Reassignment(at, routed, copies))
    start = np.asarray(owner_of_cluster, np.int64)[nearest_centre(centres, frames.descriptors)]
    return run_queries(codes, frames.robots, start, order, switches)


def read_answers(path: Path) -> dict[int, dict[str, str]]:
    """A run's ``answers.csv``, by global frame index."""
    with path.open(encoding="utf-8") as f:
        return {int(row["frame"]): row for row in csv.DictReader(f)}


def assert_answers_are(path: Path, expected: Answers, frames: Frames, *, matched: float) -> None:
    """Every frame's owner, match and distance in ``answers.csv`` are the simulation's, and
    the comparison is about something: more than ``matched`` of the frames matched and many
    queries crossed robots."""
    n = len(frames.robots)
    got = read_answers(path)
    assert sorted(got) == list(range(n))
    np.testing.assert_array_equal([int(got[g]["owner"]) for g in range(n)], expected.owners)
    np.testing.assert_array_equal([int(got[g]["match_frame"]) for g in range(n)], expected.matches)
    live = np.array([float(got[g]["distance"]) if got[g]["distance"] else np.inf for g in range(n)])
    np.testing.assert_array_equal(live.astype(np.float32), expected.distances.astype(np.float32))
    assert np.count_nonzero(expected.matches >= 0) > matched * n
    assert 0.3 < np.mean(expected.owners != frames.robots) < 1.0


Verified = dict[tuple[int, int], tuple[int, int, float]]


def verified_matches(data: Path, frames: Frames, expected: Answers) -> Verified:
    """(robot, frame) -> (match robot, match frame, score) for every answered frame of enough
    objects (the preset's ``min_objects``): its match verified on the constellations the
    detectors wrote under ``data`` (as the wire carries them)."""
    seqs = [
        as_on_the_wire(read_constellations(data / f"robot{r}" / "detector" / "constellations", COCO_NAMES))
        for r in range(len(frames.blocks))
    ]
    preset = get_preset("paper")
    out = {}
    for g, h in enumerate(expected.matches.tolist()):
        r = int(frames.robots[g])
        t = g - frames.blocks[r].start
        query = seqs[r].constellations[t]
        if h < 0 or len(query) < preset.min_objects:
            continue
        mr = int(frames.robots[h])
        mt = h - frames.blocks[mr].start
        (scored,) = verify(query, (r, t), mr, [(mt, seqs[mr].constellations[mt])], len(COCO_NAMES), preset)
        out[(r, t)] = (mr, mt, scored.score)
    return out


def closures_of(verified: Verified) -> Verified:
    """The verified matches that are loop closures: a score > 0 and at least ``CLOSURE_MIN_SCORE``."""
    return {k: v for k, v in verified.items() if v[2] > 0 and v[2] >= CLOSURE_MIN_SCORE}


def read_closures(path: Path) -> dict[tuple[int, int], tuple[int, int]]:
    """A run's ``loop_closures.csv``: (robot, frame) -> (match robot, match frame)."""
    with path.open(encoding="utf-8") as f:
        return {
            (int(c["query_robot"]), int(c["query_frame"])): (int(c["match_robot"]), int(c["match_frame"]))
            for c in csv.DictReader(f)
        }
