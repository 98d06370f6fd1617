"""The full-image run's report: the owners' answers scored, bytes and load measured, the
offline simulation of the same descriptors beside them, and (``--method both``) the two
methods side by side.

Frames are numbered globally: robot r's frame t is ``blocks[r].start + t`` (the robots
cut the sequence into consecutive blocks, as :func:`swarmrec.vpr.simulation.robot_of_frames`).

* **AUC** (the paper's protocol, :mod:`swarmrec.vpr.simulation`): each query's answer is the
  owner's best match; queries walked by distance; a true answer shows the same place
  (cameras within 0.5 m and 30 deg, :mod:`swarmrec.vpr.places`); recall over the queries
  with a same-place frame among those that arrived before on another robot. The
  centralized AUC is one index answering every query in the same order, computed here
  offline on the same descriptors; relative AUC = swarm / centralized.
* **Operating point**: the loop closures (matches verified geometrically, score at least
  ``loop_closure_min_score``). Precision: the share of cross-robot closures that show the
  same place; recall: query frames with a true cross-robot closure over the query frames
  with a same-place frame on another robot that arrived before. The constellation run is
  scored the same way for the side-by-side (its own-trajectory closures are counted apart).
* **Bytes**: every service's ``swarmrec_message_bytes_sent_total{scope="swarm"}`` by message
  type over the frames replayed; the paper's byte model (4 d + 5 B up and 13 B down for a
  query whose owner is another robot, 0 B otherwise; :func:`swarmrec.vpr.simulation.bytes_per_query`)
  is computed on the same answers, for float32 and for the code the swarm used.
* **Load**: queries each owner answered (``swarmrec_place_owner_queries_total``), busiest /
  mean, against the simulation's count.
* **Offline check** (lock-step): the descriptors the detectors produced (their data
  folders), routed to the nearest centre with the run's table, quantised as on the wire and
  replayed through :func:`swarmrec.vpr.simulation.run_queries` in the arrival order; every
  frame's owner, match and distance must equal the swarm's.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from swarmrec.core.types import Trajectory
from swarmrec.datasets.tum import associate_poses
from swarmrec.deployments.metrics import Scrape
from swarmrec.evaluation.plots import plot_bytes, plot_pr
from swarmrec.evaluation.pr import PRCurve
from swarmrec.experiments.places.report import DetectorFigures, PlacesSummary
from swarmrec.experiments.vpr.replay import PlaceReplay, TableChange
from swarmrec.vpr.balance import replica_owners
from swarmrec.vpr.clusters import Assignment, Router
from swarmrec.vpr.places import PlaceThresholds, same_place, view_directions
from swarmrec.vpr.quantize import Int8Quantizer
from swarmrec.vpr.simulation import (
    Answers,
    Reassignment,
    answers_curve,
    arrival_order,
    bytes_per_query,
    eligible,
    run_queries,
)
from swarmrec.wire import messages as pb

__all__ = [
    "Comparison",
    "DvprSummary",
    "GroundTruth",
    "MethodFigures",
    "OfflineAgreement",
    "OperatingPoint",
    "RunData",
    "as_stored",
    "compare",
    "ground_truth",
    "offline_answers",
    "operating_point",
    "write_report",
]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

#: Message types of the query itself (the paper's byte model covers these), and of verification.
QUERY_MESSAGES = ("PlaceQuery", "PlaceMatch")
VERIFY_MESSAGES = ("VerifyRequest", "VerifyReply")


@dataclass
class OfflineAgreement:
    identical: bool
    frames_compared: int
    owners_differ: int
    matches_differ: int
    distances_differ: int
    note: str = (
        "the detectors' own descriptors through swarmrec.vpr.simulation.run_queries (routed with the "
        "run's centres and table, quantised as on the wire, in the lock-step arrival order): every "
        "frame's owner, match and squared distance against the swarm's"
    )


@dataclass
class OperatingPoint:
    loop_closures: int
    cross_robot: int
    true_cross_robot: int
    own_robot: int
    precision: float
    recall: float
    queries_with_a_match: int
    note: str = (
        "loop closures against the same-place ground truth (0.5 m, 30 deg): precision over the "
        "cross-robot closures, recall over the query frames that had a same-place frame on another "
        "robot before them (arrival order)"
    )


@dataclass
class DvprBytes:
    between_robots_total: float
    per_query: float
    per_query_by_message: dict[str, float]
    query_per_query: float
    verification_per_query: float
    model_float32: dict[str, float]
    model_wire_code: dict[str, float]
    within_robot_total: float
    note: str = (
        "protobuf payload bytes sent between robots (every service's swarmrec_message_bytes_sent_total"
        "{scope='swarm'}) over the frames replayed; query_per_query counts PlaceQuery + PlaceMatch "
        "(what the paper's byte model covers), verification_per_query VerifyRequest + VerifyReply; the "
        "model: 4 d + 5 B up, 13 B down for a query whose owner is another robot, 0 B otherwise"
    )


@dataclass
class OwnerLoad:
    queries: list[int]
    balance_ratio: float
    offline: list[int] | None
    note: str = (
        "queries each owner answered (swarmrec_place_owner_queries_total), its own robot's included; "
        "balance_ratio is the busiest over the mean (the paper's worst balance ratio); offline: the "
        "simulation's count of the same routes"
    )


@dataclass
class Rebalancing:
    """One live re-balancing of the run (docs/vpr.md, "Re-balancing a live swarm")."""

    after_step: int
    at_frame: int
    version: int
    clusters: int
    #: Copies of descriptors within this gap of a boundary; None: of every descriptor; < 0: none.
    copy_margin: float | None
    observed_queries: int
    moved: int
    pending: int
    #: Queries each owner answered from this table on (until the next), and busiest / mean.
    queries: list[int]
    balance_ratio: float


@dataclass
class DvprQueries:
    frames: int
    answered: int
    matched: int
    verified: int
    loop_closures: int
    owner_failures: int
    missing_slots: int
    errors: list[str]
    latency_ms: dict[str, float]
    step_latency_ms: dict[str, float]


@dataclass
class DvprSummary:
    """Everything a full-image run reports; ``summary.json`` holds :meth:`to_dict`."""

    dataset: dict[str, Any]
    swarm: dict[str, Any]
    queries: DvprQueries
    bytes: DvprBytes
    load: OwnerLoad
    rejected_requests: float
    peer_failures: dict[str, float]
    scrape_failed: list[str]
    exit_codes: dict[str, int]
    timings: dict[str, float]
    auc: float | None = None
    centralized_auc: float | None = None
    relative_auc: float | None = None
    operating_point: OperatingPoint | None = None
    offline_check: OfflineAgreement | None = None
    detector: DetectorFigures | None = None
    #: The live re-balancings, in order, and the load before the first (None: none asked).
    rebalancing: list[Rebalancing] | None = None
    load_before_rebalancing: OwnerLoad | None = None

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        return {k: v for k, v in out.items() if v is not None}


@dataclass(frozen=True, eq=False)
class GroundTruth:
    """Same-place pairs of the whole sequence, and what each query could match."""

    same: BoolArray  # (N, N) cameras within 0.5 m and 30 deg
    robots: IntArray  # robot of each global frame
    order: IntArray  # the lock-step arrival order
    eligible: BoolArray  # (N, N) j arrived before i, on another robot


def ground_truth(trajectory: Trajectory, stamps: FloatArray, blocks: list[range]) -> GroundTruth:
    """The poses nearest in time to the frames, and the pairs that show the same place."""
    poses = associate_poses(trajectory, stamps)
    positions = trajectory.positions[poses.index]
    directions = view_directions(trajectory.quaternions[poses.index])
    n = len(stamps)
    same = same_place(
        positions, directions, np.arange(n, dtype=np.int64), PlaceThresholds(exclusion_frames=0)
    )
    robots = np.concatenate([np.full(len(b), r, np.int64) for r, b in enumerate(blocks)])
    order = arrival_order(robots)
    return GroundTruth(same, robots, order, eligible(robots, order))


def offline_answers(
    descriptors: npt.NDArray[np.float32],
    router: Router,
    blocks: list[range],
    code: str,
    tables: Sequence[tuple[int, pb.ClusterTable]] = (),
) -> Answers:
    """What :func:`swarmrec.vpr.simulation.run_queries` answers for these descriptors: each
    routed with its float values, stored and searched as the owner decodes it. ``tables``:
    the live re-balancings' tables and the arrival position each took effect at; a query
    from then on is routed by its float values with that table, a descriptor stored before
    moves to the owner and copy holders of its decoded value (as its holder computes them),
    and every later query is also stored at the copy holders of its decoded value."""
    robots = np.concatenate([np.full(len(b), r, np.int64) for r, b in enumerate(blocks)])
    _clusters, owners = router.route_many(descriptors)
    order = arrival_order(robots)
    stored = as_stored(descriptors, code)
    arrival = np.empty(len(order), np.int64)
    arrival[order] = np.arange(len(order))
    switches = []
    for at, table in tables:
        k, d = len(table.owners), table.dimension
        centres = np.frombuffer(table.centres, "<f4").astype(np.float32).reshape(k, d)
        assignment = Assignment(tuple(int(o) for o in table.owners), len(blocks), version=int(table.version))
        routed = Router(centres, assignment)
        moved = np.where(arrival < at, routed.route_many(stored)[1], routed.route_many(descriptors)[1])
        copies = None
        if table.copy_margin >= 0:
            copies = replica_owners(
                centres, assignment, stored, table.copy_margin, int(table.copy_neighbours)
            )
        switches.append(Reassignment(at, moved.astype(np.int64), copies))
    return run_queries(stored, robots, owners.astype(np.int64), order, switches)


def as_stored(descriptors: npt.NDArray[np.float32], code: str) -> npt.NDArray[np.float32]:
    """The descriptors as an owner stores them: decoded from the wire's ``code``."""
    if code == "float32":
        return descriptors
    quantizer = Int8Quantizer(descriptors.shape[1])
    return quantizer.decode(quantizer.encode(descriptors))


def live_answers(reports: dict[tuple[int, int], pb.PlaceReport], blocks: list[range]) -> Answers:
    """The swarm's answers in the simulation's form (global frame numbers; -1 / inf: none)."""
    n = sum(len(b) for b in blocks)
    owners = np.full(n, -1, np.int64)
    matches = np.full(n, -1, np.int64)
    distances = np.full(n, np.inf)
    for (r, t), rep in reports.items():
        g = blocks[r].start + t
        owners[g] = rep.owner_robot_id
        if rep.answered and rep.match.found:
            matches[g] = blocks[rep.match.robot_id].start + rep.match.frame_index
            distances[g] = rep.match.distance
    return Answers(owners, matches, distances)


def operating_point(
    closures: list[tuple[int, int]], truth: GroundTruth, robots_of: IntArray | None = None
) -> OperatingPoint:
    """Precision and recall of loop closures ``(query, match)`` in global frame numbers."""
    robots = truth.robots if robots_of is None else robots_of
    cross = [(i, j) for i, j in closures if robots[i] != robots[j]]
    true_cross = [(i, j) for i, j in cross if truth.same[i, j]]
    relevant = truth.same & truth.eligible
    with_match = int(relevant.any(axis=1).sum())
    found = len({i for i, j in true_cross if relevant[i, j]})
    return OperatingPoint(
        loop_closures=len(closures),
        cross_robot=len(cross),
        true_cross_robot=len(true_cross),
        own_robot=len(closures) - len(cross),
        precision=len(true_cross) / len(cross) if cross else 0.0,
        recall=found / with_match if with_match else 0.0,
        queries_with_a_match=with_match,
    )


def _agreement(
    live: Answers, offline: Answers, reports: dict[tuple[int, int], pb.PlaceReport]
) -> OfflineAgreement:
    owners = int(np.count_nonzero(live.owners != offline.owners))
    matches = int(np.count_nonzero(live.matches != offline.matches))
    # The wire carries the distance as float32, the value faiss computed.
    both = (live.matches >= 0) & (offline.matches >= 0)
    distances = int(np.count_nonzero(np.float32(live.distances[both]) != np.float32(offline.distances[both])))
    return OfflineAgreement(
        identical=owners == matches == distances == 0,
        frames_compared=len(reports),
        owners_differ=owners,
        matches_differ=matches,
        distances_differ=distances,
    )


def _pct(values: list[float]) -> dict[str, float]:
    if not values:
        return {}
    arr = np.asarray(values, dtype=np.float64)
    return {f"p{q}": float(np.percentile(arr, q)) for q in (50, 90, 99)} | {"mean": float(arr.mean())}


@dataclass(frozen=True, eq=False)
class RunData:
    """What the pipeline hands the report."""

    name: str
    folder: str
    blocks: list[range]
    frame_ids: tuple[str, ...]
    stamps: FloatArray
    trajectory: Trajectory | None
    replay: PlaceReplay
    closures: list[pb.LoopClosure]
    metrics: Scrape
    router: Router
    centres: Path
    digest: str
    wire_code: str
    descriptors: npt.NDArray[np.float32] | None  # the detectors' own, (N, d); None if some are missing
    swarm: dict[str, Any]
    exit_codes: dict[str, int]
    timings: dict[str, float]
    lockstep: bool
    detector: DetectorFigures | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    #: The live re-balancings, in order.
    tables: list[TableChange] = field(default_factory=list)


def write_report(out: Path, run: RunData, *, plots: bool = True) -> DvprSummary:
    """Write ``summary.json``, ``answers.csv``, ``loop_closures.csv`` and the figures under ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    blocks, replay, metrics = run.blocks, run.replay, run.metrics
    n = sum(len(b) for b in blocks)
    live = live_answers(replay.reports, blocks)
    robots = np.concatenate([np.full(len(b), r, np.int64) for r, b in enumerate(blocks)])
    reports = list(replay.reports.values())
    n_robots = len(blocks)
    d = run.router.dimension
    answered = [r for r in reports if r.answered]
    by_type = metrics.by_label("swarmrec_message_bytes_sent_total", "message", scope="swarm")
    total = sum(by_type.values())
    q = len(reports)
    code_bytes = d + 4 if run.wire_code == "int8" else 4 * d
    routed = Answers(np.where(live.owners >= 0, live.owners, robots), live.matches, live.distances)
    byte_stats = DvprBytes(
        between_robots_total=total,
        per_query=total / q if q else 0.0,
        per_query_by_message={k: v / q for k, v in sorted(by_type.items())} if q else {},
        query_per_query=sum(by_type.get(m, 0.0) for m in QUERY_MESSAGES) / q if q else 0.0,
        verification_per_query=sum(by_type.get(m, 0.0) for m in VERIFY_MESSAGES) / q if q else 0.0,
        model_float32=bytes_per_query(routed, robots, 4 * d),
        model_wire_code=bytes_per_query(routed, robots, code_bytes),
        within_robot_total=metrics.total("swarmrec_message_bytes_sent_total", scope="robot"),
    )
    served = metrics.per_service("swarmrec_place_owner_queries_total", "place-owner")
    loads = [int(served.get(r, 0)) for r in range(n_robots)]
    mean = float(np.mean(loads)) if loads else 0.0
    summary = DvprSummary(
        dataset={
            "name": run.name,
            "folder": run.folder,
            "frames": n,
            "groundtruth": run.trajectory is not None,
        },
        swarm=run.swarm,
        queries=DvprQueries(
            frames=q,
            answered=len(answered),
            matched=sum(1 for r in answered if r.match.found),
            verified=sum(1 for r in reports if r.verified),
            loop_closures=len(run.closures),
            owner_failures=sum(1 for r in reports if not r.answered),
            missing_slots=len(replay.missing),
            errors=replay.errors[:50],
            latency_ms={k: v / 1e3 for k, v in _pct([float(r.duration_us) for r in reports]).items()},
            step_latency_ms={k: v * 1e3 for k, v in _pct(replay.step_seconds).items()},
        ),
        bytes=byte_stats,
        load=OwnerLoad(loads, float(max(loads) / mean) if mean > 0 else 0.0, None),
        rejected_requests=metrics.total("swarmrec_rejected_requests_total"),
        peer_failures=metrics.by_label("swarmrec_peer_failures_total", "reason"),
        scrape_failed=metrics.failed,
        exit_codes=run.exit_codes,
        timings=run.timings,
        detector=run.detector,
    )
    if run.tables:
        _rebalancing(summary, run, live, robots)
    expected = None
    if run.descriptors is not None and run.lockstep and not replay.missing:
        tables = [(c.at, c.reply.table) for c in run.tables]
        expected = offline_answers(run.descriptors, run.router, blocks, run.wire_code, tables)
        summary.offline_check = _agreement(live, expected, replay.reports)
        summary.load.offline = np.bincount(expected.owners, minlength=n_robots).astype(int).tolist()
    truth = None
    curves: dict[str, PRCurve] = {}
    if run.trajectory is not None:
        truth = ground_truth(run.trajectory, run.stamps, blocks)
        closures_truth = truth.same & truth.eligible
        curves[f"swarm x{n_robots}"] = answers_curve(live, closures_truth, truth.eligible)
        summary.auc = curves[f"swarm x{n_robots}"].auc
        if run.descriptors is not None:
            stored = as_stored(run.descriptors, run.wire_code)
            central = run_queries(stored, robots, np.zeros(n, np.int64), truth.order)
            curves["centralized"] = answers_curve(central, closures_truth, truth.eligible)
            summary.centralized_auc = curves["centralized"].auc
            if summary.centralized_auc > 0:
                summary.relative_auc = summary.auc / summary.centralized_auc
        pairs = [_global(c, blocks) for c in run.closures]
        summary.operating_point = operating_point(pairs, truth)
    if run.tables:
        # Every rolled-out table, for re-checking the run offline (tables/v<version>.pb).
        folder = out / "tables"
        folder.mkdir(exist_ok=True)
        for change in run.tables:
            (folder / f"v{change.reply.table.version}.pb").write_bytes(change.reply.table.SerializeToString())
    _write_answers(out / "answers.csv", replay.reports, blocks, run.frame_ids, truth)
    _write_closures(out / "loop_closures.csv", run.closures, blocks, run.frame_ids, truth)
    if plots:
        if curves:
            plot_pr(curves, out / "precision_recall.png")
        if summary.bytes.per_query_by_message:
            plot_bytes(summary.bytes.per_query_by_message, out / "bytes_per_query.png")
    (out / "summary.json").write_text(json.dumps(summary.to_dict(), indent=2) + "\n")
    return summary


def _rebalancing(summary: DvprSummary, run: RunData, live: Answers, robots: IntArray) -> None:
    """Each re-balancing's table and the load it gave until the next (live owners by arrival)."""
    n_robots = len(run.blocks)
    order = arrival_order(robots)
    owners = live.owners[order]  # in arrival order
    bounds = [c.at for c in run.tables] + [len(order)]

    def load(lo: int, hi: int) -> tuple[list[int], float]:
        part = owners[lo:hi]
        counts = np.bincount(part[part >= 0], minlength=n_robots).astype(int).tolist()
        mean = float(np.mean(counts)) if counts else 0.0
        return counts, float(max(counts) / mean) if mean > 0 else 0.0

    first, ratio = load(0, bounds[0])
    summary.load_before_rebalancing = OwnerLoad(first, ratio, None)
    summary.rebalancing = []
    for i, c in enumerate(run.tables):
        counts, ratio = load(bounds[i], bounds[i + 1])
        t = c.reply.table
        summary.rebalancing.append(
            Rebalancing(
                after_step=c.step,
                at_frame=c.at,
                version=int(t.version),
                clusters=len(t.owners),
                copy_margin=None if math.isinf(t.copy_margin) else float(t.copy_margin),
                observed_queries=int(c.reply.observed_queries),
                moved=int(c.reply.moved),
                pending=int(c.reply.pending),
                queries=counts,
                balance_ratio=ratio,
            )
        )


def _global(c: pb.LoopClosure, blocks: list[range]) -> tuple[int, int]:
    return blocks[c.query_robot_id].start + c.query_frame_index, blocks[
        c.match_robot_id
    ].start + c.match_frame_index


def _write_answers(
    path: Path,
    reports: dict[tuple[int, int], pb.PlaceReport],
    blocks: list[range],
    frame_ids: tuple[str, ...],
    truth: GroundTruth | None,
) -> None:
    with path.open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["frame", "frame_id", "robot", "robot_frame", "cluster", "owner", "match_frame",
                    "match_robot", "match_robot_frame", "distance", "verified", "score", "loop_closure",
                    "same_place"])  # fmt: skip
        for (r, t), rep in sorted(reports.items(), key=lambda kv: blocks[kv[0][0]].start + kv[0][1]):
            g = blocks[r].start + t
            m = rep.match
            found = rep.answered and m.found
            h = blocks[m.robot_id].start + m.frame_index if found else -1
            same = "" if truth is None or h < 0 else int(truth.same[g, h])
            w.writerow([g, frame_ids[g], r, t, rep.cluster, rep.owner_robot_id, h,
                        m.robot_id if found else "", m.frame_index if found else "",
                        repr(float(m.distance)) if found else "", int(rep.verified), f"{rep.score:.6f}",
                        int(rep.loop_closure), same])  # fmt: skip


def _write_closures(
    path: Path,
    closures: list[pb.LoopClosure],
    blocks: list[range],
    frame_ids: tuple[str, ...],
    truth: GroundTruth | None,
) -> None:
    with path.open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["query_robot", "query_frame", "match_robot", "match_frame", "query_frame_id",
                    "match_frame_id", "score", "n_matched", "same_place"])  # fmt: skip
        for c in sorted(closures, key=lambda c: (c.query_robot_id, c.query_frame_index)):
            g, h = _global(c, blocks)
            same = "" if truth is None else int(truth.same[g, h])
            w.writerow([c.query_robot_id, c.query_frame_index, c.match_robot_id, c.match_frame_index,
                        frame_ids[g], frame_ids[h], f"{c.score:.6f}", c.n_matched, same])  # fmt: skip


# --- both methods side by side -------------------------------------------------------


@dataclass
class MethodFigures:
    """One method's row of the side-by-side table."""

    method: str
    auc: float | None
    auc_protocol: str
    loop_closures: int
    precision: float | None
    recall: float | None
    bytes_per_query: float
    bytes_per_frame: float
    byte_model_per_query: float | None
    balance_ratio: float
    latency_p50_ms: float | None
    latency_p99_ms: float | None
    queries: int


@dataclass
class Comparison:
    frames: int
    robots: int
    methods: list[MethodFigures]
    note: str = (
        "each AUC in its own paper's protocol (constellations: every verified pair score against "
        "scene-point ground truth; dvpr: each query's best owner answer against same-place ground "
        "truth); precision and recall of the loop closures against one ground truth for both (same "
        "place: 0.5 m, 30 deg; cross-robot closures); bytes measured on the wire; the byte model is "
        "the dvpr paper's (4 d + 5 up, 13 down, float32)"
    )


def compare(
    dvpr: DvprSummary,
    places: PlacesSummary,
    places_closures: list[tuple[int, int]],
    truth: GroundTruth | None,
) -> Comparison:
    """The side-by-side of a ``--method both`` run: ``places_closures`` are the constellation
    run's loop closures as global (query, match) frames, scored on the same ground truth."""
    op = operating_point(places_closures, truth) if truth is not None else None
    slots = places.bytes.per_frame
    lat = places.queries.latency_ms
    dlat = dvpr.queries.latency_ms
    dop = dvpr.operating_point
    return Comparison(
        frames=dvpr.dataset["frames"],
        robots=len(dvpr.load.queries),
        methods=[
            MethodFigures(
                method="constellations",
                auc=places.auc,
                auc_protocol="constellation paper: pair scores, scene points within 2 m",
                loop_closures=places.loop_closures.count,
                precision=op.precision if op else None,
                recall=op.recall if op else None,
                bytes_per_query=places.bytes.per_query,
                bytes_per_frame=slots,
                byte_model_per_query=None,
                balance_ratio=places.shard_load.balance_ratio,
                latency_p50_ms=lat.get("p50"),
                latency_p99_ms=lat.get("p99"),
                queries=places.queries.queried,
            ),
            MethodFigures(
                method="dvpr",
                auc=dvpr.auc,
                auc_protocol="full-image paper: best owner answer by distance, same place 0.5 m, 30 deg",
                loop_closures=dvpr.queries.loop_closures,
                precision=dop.precision if dop else None,
                recall=dop.recall if dop else None,
                bytes_per_query=dvpr.bytes.per_query,
                bytes_per_frame=dvpr.bytes.per_query,
                byte_model_per_query=dvpr.bytes.model_float32["total"],
                balance_ratio=dvpr.load.balance_ratio,
                latency_p50_ms=dlat.get("p50"),
                latency_p99_ms=dlat.get("p99"),
                queries=dvpr.queries.frames,
            ),
        ],
    )
