"""The place-recognition run's report: pair scores, accuracy, bytes and load, measured.

Bytes per query and the shard load come from the services' Prometheus metrics
as the deployment read them at the end of the run, not from a formula:
``bytes`` sums the payload bytes every service counted as sent between robots
(``swarmrec_message_bytes_sent_total{scope="swarm"}``). The summary is a typed
record (:class:`PlacesSummary`); ``summary.json`` is its dictionary. The files
are described in docs/swarm.md ("The main job").

The loop-closure funnel (``funnel.csv``, ``funnel_queries.csv``, ``funnel`` in the
summary, ``funnel.png``) is read from the query reports the descriptors sent
back: where each candidate of each query stopped, and why (docs/swarm.md, "Why
was a loop closure not found"); the run checks that it adds up.
"""

from __future__ import annotations

import csv
import json
import threading
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from swarmrec.client import IndexState
from swarmrec.core.association import FrameTable, build_table
from swarmrec.core.funnel import Reason, Stage, passed_stages
from swarmrec.core.presets import Preset
from swarmrec.core.types import ConstellationSequence, Trajectory
from swarmrec.datasets.constellations import label_counts
from swarmrec.deployments.mesh import MeshReport
from swarmrec.deployments.metrics import Scrape
from swarmrec.evaluation.bandwidth import HolderLoad
from swarmrec.evaluation.groundtruth import GroundTruth, ground_truth
from swarmrec.evaluation.partition import Holdings, Reach
from swarmrec.evaluation.plots import (
    plot_bytes,
    plot_closures_map,
    plot_funnel,
    plot_holder_load,
    plot_pr,
    plot_similarity,
)
from swarmrec.evaluation.pr import PRCurve, precision_recall
from swarmrec.evaluation.scoring import ScoreMatrix, decentralized_marks, same_objects, score_decentralized
from swarmrec.experiments.places.replay import Replay
from swarmrec.experiments.places.settings import ReportSettings
from swarmrec.services.coordinator import reason_name
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import outcomes_from_proto

__all__ = [
    "ByteStats",
    "ClosureStats",
    "DatasetInfo",
    "DetectorFigures",
    "FunnelStats",
    "IndexSummary",
    "OfflineCheck",
    "OfflineEvaluation",
    "PairStats",
    "PlacesSummary",
    "QueryStats",
    "ShardLoad",
    "SwarmInfo",
    "pair_matrix",
    "placement_history",
    "write_report",
]


@dataclass
class DatasetInfo:
    name: str
    source: str
    frames: int
    labels: int
    groundtruth: bool
    #: The constellation files the detectors replayed (or the detections read back), and
    #: their label list ("": COCO): what ``swarmrec explain`` reads again.
    folder: str = ""
    labels_file: str = ""


@dataclass
class SwarmInfo:
    robots: int
    pace: str
    preset: dict[str, Any]
    label_bounds: list[int]
    #: How object positions travelled: "mm" or "exact" (doubles).
    wire_positions: str
    deployment: str
    #: Processes the deployment started (0 for a swarm that was already running).
    processes: int


@dataclass
class QueryStats:
    frames_replayed: int
    queried: int
    missing_slots: int
    missing_by_robot: dict[str, int]
    failed_shard_requests: int
    failed_verifier_requests: int
    errors: list[str]
    latency_ms: dict[str, float]
    step_latency_ms: dict[str, float]
    #: Frames a detector could not hand on at their step, delivered later from its outbox.
    late_frames: int = 0
    #: Frames still waiting in the detectors' outboxes at the end (lost to this report).
    pending_frames: int = 0


@dataclass
class ByteStats:
    between_robots_total: float
    per_query: float
    per_frame: float
    per_query_by_message: dict[str, float]
    messages_per_query: dict[str, float]
    within_robot_total: float
    to_clients_total: float
    #: Bytes a query costs beyond the paper's two steps: copies of its slices on the other
    #: replicas of their groups, and the elastic index's own traffic (placements, handoffs).
    replication_per_query: float = 0.0
    index_control_per_query: float = 0.0
    #: Everything between robots, per query (per_query is the two-step query alone).
    all_per_query: float = 0.0
    note: str = (
        "protobuf payload bytes sent between robots, summed from every service's "
        "swarmrec_message_bytes_sent_total{scope='swarm'}; per_query counts the two-step query's "
        "messages (PartialQuery, CandidatesReply, VerifyRequest, VerifyReply: the paper's measure) "
        "and divides by the frames that queried, per_frame by every (robot, step) slot as the "
        "paper's byte model averages; replication and index control are counted apart"
    )


@dataclass
class ShardLoad:
    partial_queries: list[int]
    balance_ratio: float
    #: The shards' own counters at the end (a shard that died or restarted lost its count).
    scraped: list[int] = field(default_factory=list)
    note: str = (
        "partial queries each index shard answered, counted from the query reports (which shard "
        "answered each label group), so a shard killed mid-run keeps its count; scraped: the shards' "
        "swarmrec_shard_partial_queries_total at the end; balance_ratio is the busiest shard over the mean"
    )


@dataclass
class IndexSummary:
    """The elastic index after the replay (docs/elastic-index.md)."""

    #: The placement's version at the end (0: never changed) and replicas per group.
    version: int
    replicas: int
    #: The shards owning each label group at the end.
    owners: list[list[int]]
    #: Every shard followed that placement and every store was acknowledged.
    settled: bool
    #: Slices the descriptors still had to store when the report was written.
    pending_stores: int
    #: Placements the coordinator published, descriptors copied in handoffs, requests
    #: refused by reason (stale placement, unconfirmed shard, group not held).
    placements_published: float
    handoff_records: float
    refused: dict[str, float]
    #: A ShardStore's CPU time over a partial query's, as the shards measured them (the
    #: coordinator weighs a replica's stores with it when it rebalances); None when the
    #: run had no stores or no queries.
    store_weight: float | None = None
    #: Robots' partial queries served per label group, by every owner together
    #: (``swarmrec_shard_group_queries_total``): the load the coordinator rebalances on.
    group_queries: list[int] = field(default_factory=list)
    #: Every placement the coordinator published during the run, oldest first, and why
    #: (its ``PlacementChange`` events; :func:`placement_history`).
    history: list[dict[str, Any]] = field(default_factory=list)


@dataclass
class ClosureStats:
    count: int
    scraped_total: float
    #: The threshold this run's descriptors published loop closures at.
    min_score: float


@dataclass
class PairStats:
    checked_positive: int
    conflicting: int


@dataclass
class OfflineCheck:
    identical: bool
    positive_pairs_swarm: int
    positive_pairs_offline: int
    scores_differ: int
    only_in_swarm: int
    only_offline: int
    #: A mesh's team that split: the steps it was split, simulated offline on the same schedule.
    split_steps: int = 0
    #: In that simulation: partial queries that found no owner of their group in reach, and
    #: verifications whose robot was out of reach (no pair from them).
    unreached_group_queries: int = 0
    unreachable_verifications: int = 0


@dataclass
class PositionsEffect:
    """What carrying positions in millimetres cost, measured offline on the same frames."""

    auc_offline_exact_positions: float
    auc_offline_mm_positions: float
    pair_scores_changed: int
    note: str = (
        "the offline decentralized evaluation of this run's frames with exact positions and with the "
        "millimetres the swarm carried; pair_scores_changed counts pairs whose score differs"
    )


@dataclass
class LinkReport:
    """The emulated links of a run (docs/links.md): each robot's link and what changed when."""

    rate_kbps: float | None
    latency_ms: float | None
    schedule_unit: str
    #: (time in the schedule's unit, what happened), in order.
    events: list[tuple[float, str]]


@dataclass
class DetectorFigures:
    """A run from pixels: how the detectors were set up and what they counted."""

    mode: str
    folder: str
    model: str
    conf_threshold: float
    camera: dict[str, float]
    frames_without_constellation: int
    render: dict[str, Any] | None
    frames: int = 0
    frames_by_outcome: dict[str, int] = field(default_factory=dict)
    skipped: dict[str, int] = field(default_factory=dict)
    boxes_dropped: dict[str, int] = field(default_factory=dict)
    objects: int = 0
    objects_per_frame: float = 0.0
    stage_ms_mean: dict[str, float] = field(default_factory=dict)
    note: str = (
        "scraped from the detectors' swarmrec_detector_* metrics; objects_per_frame is over "
        "the frames a constellation was made of (detected or no_objects)"
    )


@dataclass
class FunnelStats:
    """The loop-closure funnel of every query of the run (docs/swarm.md)."""

    frames: int
    queried: int
    #: Frames with fewer objects than the preset's min_objects: not queried.
    too_few_objects: int
    #: Candidates the shards returned, every shard's counted (a frame two shards
    #: returned counts twice), and the distinct frames among them per query.
    candidates_returned: int
    distinct_candidates: int
    #: Distinct candidates by the stage and by the reason they stopped at.
    by_stage: dict[str, int]
    by_reason: dict[str, int]
    #: By querying robot, then reason.
    by_robot: dict[str, dict[str, int]]
    #: Candidates left after each stage (returned, robot chosen, verifier answered, matched, accepted).
    levels: list[tuple[str, int]]
    accepted: int
    #: accepted == the loop closures the descriptors hold.
    accepted_equals_loop_closures: bool
    #: Queries whose funnel does not add up (shard counts against n_candidates, one outcome
    #: per distinct candidate, a reason for each, at most one accepted); 0 when it does.
    inconsistent_queries: int
    #: swarmrec_funnel_candidates_total by reason, scraped from the descriptors.
    scraped_by_reason: dict[str, float]
    #: Mean serialized QueryReport, with and without the funnel's fields, bytes.
    report_bytes_mean: float
    report_bytes_mean_without_funnel: float
    note: str = (
        "each distinct candidate of a query ends at exactly one stage (shard, selection, verification, "
        "closure); a report travels from the descriptor to its own detector and to listeners of "
        "events/query, never between robots, so the funnel adds no byte between robots"
    )


@dataclass
class PlacesSummary:
    """Everything a run reports; ``summary.json`` holds :meth:`to_dict`."""

    dataset: DatasetInfo
    swarm: SwarmInfo
    queries: QueryStats
    bytes: ByteStats
    shard_load: ShardLoad
    rejected_requests: float
    peer_failures: dict[str, float]
    loop_closures: ClosureStats
    pairs: PairStats
    scrape_failed: list[str]
    exit_codes: dict[str, int]
    timings: dict[str, float]
    auc: float | None = None
    offline_check: OfflineCheck | None = None
    #: Why the pair scores were not compared with the offline evaluation ("" when they were).
    offline_not_compared: str = ""
    positions_effect: PositionsEffect | None = None
    links: LinkReport | None = None
    mesh: MeshReport | None = None
    detector: DetectorFigures | None = None
    index: IndexSummary | None = None
    funnel: FunnelStats | None = None

    def to_dict(self) -> dict[str, Any]:
        """The summary as JSON-ready data; optional parts absent from the run are left out."""
        out = asdict(self)
        return {k: v for k, v in out.items() if v is not None}


def pair_matrix(
    reports: list[pb.QueryReport], seq: ConstellationSequence, blocks: list[range], preset: Preset
) -> tuple[ScoreMatrix, int]:
    """The swarm's verified pairs as a ScoreMatrix over global frame indices
    (robot r's frame f is ``blocks[r].start + f``), in the offline convention;
    also the number of pairs reached from both sides with different scores."""
    n = len(seq)
    scores: dict[tuple[int, int], float] = {}
    conflicts = 0
    for rep in reports:
        g = blocks[rep.robot_id].start + rep.frame_index
        for m in rep.matches:
            h = blocks[m.match_robot_id].start + m.match_frame_index
            key = (min(g, h), max(g, h))
            if key in scores and scores[key] != m.score:
                conflicts += 1
            scores[key] = m.score
    keys_sorted = sorted(scores)
    lo = np.array([k[0] for k in keys_sorted], np.int64)
    hi = np.array([k[1] for k in keys_sorted], np.int64)
    sizes = np.array([len(c) for c in seq.constellations])
    valid = sizes >= preset.min_objects
    marked = decentralized_marks(valid, blocks)
    values = np.array([scores[k] for k in keys_sorted], np.float64)
    return ScoreMatrix(lo, hi, values, n, preset.exclusion, ~valid, marked), conflicts


def _positive(matrix: ScoreMatrix) -> dict[tuple[int, int], float]:
    keep = matrix.scores > 0
    return {
        (int(i), int(j)): float(s)
        for i, j, s in zip(matrix.pairs_i[keep], matrix.pairs_j[keep], matrix.scores[keep], strict=True)
    }


class OfflineEvaluation:
    """The offline decentralized evaluation of the run's frames as they went on the wire
    and with exact positions, and the ground truth: each computed once (the report asks
    for the first twice: the identity check and what millimetres cost).

    The two evaluations differ only in positions, and which pairs a decentralized run
    checks depends on labels alone: the second is the first's pairs scored again
    (:meth:`ScoreMatrix.rescored`), the same doubles as evaluating it from scratch at a
    third of the time.

    None of it depends on what the swarm answered: :meth:`start` computes it on a thread
    while the pipeline scrapes and stops the swarm (100 robots: 4 s of the report, done
    while the processes exit), and the report's first question waits for it.
    """

    def __init__(
        self,
        seq: ConstellationSequence,
        wire_seq: ConstellationSequence,
        trajectory: Trajectory | None,
        preset: Preset,
        bounds: npt.NDArray[np.int64],
        robots: int,
        reach: Reach | None = None,
    ) -> None:
        self.seq, self.wire_seq, self.trajectory = seq, wire_seq, trajectory
        self.preset, self.bounds, self.robots = preset, bounds, robots
        #: A mesh's team that split: the evaluation simulates the same connectivity schedule,
        #: and keeps what each owner held (:class:`~swarmrec.evaluation.partition.Holdings`).
        self.reach = reach
        self.holdings: Holdings | None = None
        # By sequence: with exact positions on the wire, both are the same frames.
        self._done: dict[int, tuple[FrameTable, ScoreMatrix]] = {}
        self._truth: GroundTruth | None = None
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    def start(self, *, check_offline: bool) -> OfflineEvaluation:
        """Compute, on a thread of their own, what the report of a run will ask: the ground
        truth, and with ``check_offline`` the wire's evaluation and (with a trajectory, and
        other positions on the wire) the exact one."""

        def work() -> None:
            try:
                self._ground_truth()
                if check_offline:
                    self._matrix(wire=True)
                    if self.trajectory is not None and self.wire_seq is not self.seq:
                        self._matrix(wire=False)
            except BaseException as e:  # handed to the report's thread, which raises it
                self._error = e

        self._thread = threading.Thread(target=work, name="offline-evaluation", daemon=True)
        self._thread.start()
        return self

    def _join(self) -> None:
        if self._thread is not None:
            self._thread.join()
            self._thread = None
            if self._error is not None:
                raise self._error

    def matrix(self, *, wire: bool) -> ScoreMatrix:
        self._join()
        return self._matrix(wire=wire)

    def ground_truth(self) -> GroundTruth | None:
        """The true closures of the wire's frames; None without a trajectory."""
        self._join()
        return self._ground_truth()

    def _ground_truth(self) -> GroundTruth | None:
        if self._truth is None and self.trajectory is not None:
            self._truth = ground_truth(self.wire_seq, self.trajectory, exclusion=self.preset.exclusion)
        return self._truth

    def _matrix(self, *, wire: bool) -> ScoreMatrix:
        seq = self.wire_seq if wire else self.seq
        if id(seq) not in self._done:
            table = build_table(seq.constellations, seq.n_labels)
            done = next((m for t, m in self._done.values() if same_objects(t, table)), None)
            if done is not None:
                matrix = done.rescored(table, self.preset)
            else:
                scored = score_decentralized(
                    seq, self.robots, self.preset, table=table, bounds=self.bounds, reach=self.reach
                )
                matrix = scored.matrix
                if scored.holdings is not None:
                    self.holdings = scored.holdings
            self._done[id(seq)] = (table, matrix)
        return self._done[id(seq)][1]


def _why_not_compared(settings: ReportSettings, missing: int, late: int) -> str:
    """Why a run's pair scores are not compared with the offline evaluation, in a few words."""
    if not settings.check_offline:
        return "--no-offline-check"
    if not settings.lockstep:
        return f"pace {settings.pace}: only a lock-step replay is the offline evaluation's sequence"
    if missing:
        return f"{missing} answer slots missing"
    return f"{late} frames delivered after their step"


def _compare_offline(matrix: ScoreMatrix, offline: ScoreMatrix) -> OfflineCheck:
    ours, theirs = _positive(matrix), _positive(offline)
    differ = sum(1 for k in ours.keys() & theirs.keys() if ours[k] != theirs[k])
    only_swarm, only_offline = len(ours.keys() - theirs.keys()), len(theirs.keys() - ours.keys())
    return OfflineCheck(
        identical=differ == 0 and only_swarm == 0 and only_offline == 0,
        positive_pairs_swarm=len(ours),
        positive_pairs_offline=len(theirs),
        scores_differ=differ,
        only_in_swarm=only_swarm,
        only_offline=only_offline,
    )


def _positions_effect(offline: OfflineEvaluation, truth: npt.NDArray[np.bool_]) -> PositionsEffect:
    exact = offline.matrix(wire=False).dense()
    carried = offline.matrix(wire=True).dense()
    return PositionsEffect(
        auc_offline_exact_positions=precision_recall(exact, truth).auc,
        auc_offline_mm_positions=precision_recall(carried, truth).auc,
        pair_scores_changed=int(np.count_nonzero(np.triu(exact != carried))),
    )


#: The two-step query's messages (the paper's bytes per query).
QUERY_MESSAGES = ("PartialQuery", "CandidatesReply", "VerifyRequest", "VerifyReply")
#: A slice stored on the other replicas of its group, and their answers.
REPLICATION_MESSAGES = ("ShardStore", "StoreReply")
#: The elastic index's own traffic: placements, shard states, handoff pages.
INDEX_CONTROL_MESSAGES = (
    "PlacementRequest",
    "ShardState",
    "AdoptRequest",
    "TransferRequest",
    "TransferReply",
)


def _bytes(metrics: Scrape, n_queries: int, n_slots: int) -> ByteStats:
    by_type = metrics.by_label("swarmrec_message_bytes_sent_total", "message", scope="swarm")
    msgs = metrics.by_label("swarmrec_messages_sent_total", "message", scope="swarm")
    total = sum(by_type.values())
    query = sum(by_type.get(m, 0.0) for m in QUERY_MESSAGES)

    def per(names: tuple[str, ...]) -> float:
        return sum(by_type.get(m, 0.0) for m in names) / n_queries if n_queries else 0.0

    return ByteStats(
        between_robots_total=total,
        per_query=query / n_queries if n_queries else 0.0,
        per_frame=query / n_slots if n_slots else 0.0,
        replication_per_query=per(REPLICATION_MESSAGES),
        index_control_per_query=per(INDEX_CONTROL_MESSAGES),
        all_per_query=total / n_queries if n_queries else 0.0,
        per_query_by_message={k: v / n_queries for k, v in sorted(by_type.items())} if n_queries else {},
        messages_per_query={k: v / n_queries for k, v in sorted(msgs.items())} if n_queries else {},
        within_robot_total=metrics.total("swarmrec_message_bytes_sent_total", scope="robot"),
        to_clients_total=metrics.total("swarmrec_message_bytes_sent_total", scope="client"),
    )


def _detector_figures(detector: DetectorFigures, metrics: Scrape) -> DetectorFigures:
    """``detector`` with what the rgbd detectors counted: frames by outcome, skips, dropped
    boxes, objects, stage times."""
    by_outcome = metrics.by_label("swarmrec_detector_frames_total", "outcome")
    outcomes = {k: int(v) for k, v in sorted(by_outcome.items())}
    made = outcomes.get("detected", 0) + outcomes.get("no_objects", 0)
    objects = metrics.total("swarmrec_detector_objects_total")
    sums = metrics.by_label("swarmrec_detector_stage_seconds_sum", "stage")
    counts = metrics.by_label("swarmrec_detector_stage_seconds_count", "stage")
    detector.frames = sum(outcomes.values())
    detector.frames_by_outcome = outcomes
    detector.skipped = {k: v for k, v in outcomes.items() if k not in ("detected", "no_objects")}
    dropped = metrics.by_label("swarmrec_detector_boxes_dropped_total", "reason")
    detector.boxes_dropped = {k: int(v) for k, v in dropped.items()}
    detector.objects = int(objects)
    detector.objects_per_frame = objects / made if made else 0.0
    detector.stage_ms_mean = {k: 1e3 * sums[k] / counts[k] for k in sorted(sums) if counts.get(k)}
    return detector


@dataclass(frozen=True, eq=False)
class RunRecord:
    """What the pipeline hands the report: the data, the swarm's answers and counters."""

    seq: ConstellationSequence
    #: The offline evaluation of ``seq`` as the services saw it (started while the swarm
    #: stopped, where the pipeline could).
    offline: OfflineEvaluation
    trajectory: Trajectory | None
    preset: Preset
    bounds: npt.NDArray[np.int64]
    blocks: list[range]
    replay: Replay
    metrics: Scrape
    closures: list[pb.LoopClosure]
    exit_codes: dict[str, int]
    timings: dict[str, float]
    deployment: str
    loop_closure_min_score: float
    index: IndexState | None = None
    #: The coordinator's PlacementChange events heard during the run.
    placement_changes: list[pb.PlacementChange] = field(default_factory=list)
    detector: DetectorFigures | None = None
    links: LinkReport | None = None
    #: A mesh run's radio graph and link bytes (None: one router).
    mesh: MeshReport | None = None
    #: Where the replayed constellations are on disk, and their label list (None: COCO).
    dataset_folder: Path | None = None
    labels_file: Path | None = None

    @property
    def wire_seq(self) -> ConstellationSequence:
        """The sequence as the services saw it (positions as the wire carried them)."""
        return self.offline.wire_seq


def measured_store_weight(metrics: Scrape) -> float | None:
    """The shards' mean CPU time a ShardStore over their mean a partial query."""
    shards = metrics.of_kind("index-shard")
    mean: dict[str, float] = {}
    for endpoint in ("query", "store"):
        n = shards.total("swarmrec_request_duration_seconds_count", endpoint=endpoint)
        cpu = shards.total("swarmrec_request_cpu_seconds_total", endpoint=endpoint)
        if n <= 0 or cpu <= 0:
            return None
        mean[endpoint] = cpu / n
    return mean["store"] / mean["query"]


def placement_history(changes: Iterable[pb.PlacementChange]) -> list[dict[str, Any]]:
    """The placement changes a run saw, one dict each, by version (a change heard twice, say
    from a coordinator that took over, is kept once)."""
    by_version: dict[int, pb.PlacementChange] = {}
    for c in changes:
        by_version.setdefault(c.version, c)
    out = []
    for v in sorted(by_version):
        c = by_version[v]
        entry: dict[str, Any] = {
            "version": v,
            "reason": reason_name(c.reason),
            "coordinator": c.coordinator,
            "unix_time_ns": c.unix_time_ns,
            "groups": {str(g.group): {"gained": list(g.gained), "lost": list(g.lost)} for g in c.changes},
        }
        if c.reason == pb.PlacementReason.PLACEMENT_REASON_REBALANCE:
            entry["plan"] = {
                "queries": c.queries,
                "store_weight": round(c.store_weight, 4),
                "busiest_before": round(c.busiest_before, 2),
                "busiest_after": round(c.busiest_after, 2),
                "mean": round(c.mean_load, 2),
            }
        out.append(entry)
    return out


def _group_queries(metrics: Scrape, n_groups: int) -> list[int]:
    by_group = metrics.of_kind("index-shard").by_label("swarmrec_shard_group_queries_total", "group")
    return [int(by_group.get(str(g), 0.0)) for g in range(n_groups)]


def _index_summary(
    state: IndexState, metrics: Scrape, replicas: int, changes: Sequence[pb.PlacementChange]
) -> IndexSummary:
    p = state.placement
    return IndexSummary(
        version=p.version if p is not None else -1,
        replicas=p.replicas if p is not None else replicas,
        owners=[list(o) for o in p.owners] if p is not None else [],
        settled=state.settled,
        pending_stores=state.pending,
        placements_published=metrics.total("swarmrec_shard_placements_published_total"),
        handoff_records=metrics.total("swarmrec_shard_handoff_records_total"),
        refused=metrics.by_label("swarmrec_shard_refused_total", "reason"),
        store_weight=measured_store_weight(metrics),
        group_queries=_group_queries(metrics, len(p.groups)) if p is not None else [],
        history=placement_history(changes),
    )


def write_report(settings: ReportSettings, run: RunRecord) -> PlacesSummary:
    """Write the report files under ``settings.out`` and return the summary."""
    out = settings.out
    replay, metrics, seq, wire_seq = run.replay, run.metrics, run.seq, run.wire_seq
    matrix, conflicts = pair_matrix(replay.reports, wire_seq, run.blocks, run.preset)
    queried = [r for r in replay.reports if r.queried]
    n_slots = settings.robots * max((len(b) for b in run.blocks), default=0)
    scraped = metrics.per_service("swarmrec_shard_partial_queries_total", "index-shard")
    answered = Counter(sc.robot_id for r in queried for sc in r.shard_candidates)
    loads = [int(answered.get(r, 0)) for r in range(settings.robots)]
    mean_load = float(np.mean(loads)) if loads else 0.0
    missing_by_robot: dict[str, int] = {}
    for r, _t in replay.missing:
        missing_by_robot[str(r)] = missing_by_robot.get(str(r), 0) + 1
    summary = PlacesSummary(
        dataset=DatasetInfo(
            name=seq.name,
            source=settings.dataset,
            frames=len(seq),
            labels=seq.n_labels,
            groundtruth=run.trajectory is not None,
            folder=str(run.dataset_folder.resolve()) if run.dataset_folder else "",
            labels_file=str(run.labels_file.resolve()) if run.labels_file else "",
        ),
        swarm=SwarmInfo(
            robots=settings.robots,
            pace=settings.pace,
            preset=asdict(run.preset),
            label_bounds=[int(b) for b in run.bounds],
            wire_positions="exact" if run.wire_seq is run.seq else "mm",
            deployment=run.deployment,
            processes=len(run.exit_codes),
        ),
        queries=QueryStats(
            frames_replayed=len(replay.reports),
            queried=len(queried),
            missing_slots=len(replay.missing),
            missing_by_robot=missing_by_robot,
            failed_shard_requests=sum(len(r.failed_shard_robot_ids) for r in replay.reports),
            failed_verifier_requests=sum(len(r.failed_verifier_robot_ids) for r in replay.reports),
            errors=replay.errors[:50],
            latency_ms={k: v / 1e3 for k, v in _pct([r.duration_us for r in queried]).items()},
            step_latency_ms={k: v * 1e3 for k, v in _pct(replay.step_seconds).items()},
            late_frames=len(replay.late),
            pending_frames=replay.pending,
        ),
        bytes=_bytes(metrics, len(queried), n_slots),
        shard_load=ShardLoad(
            partial_queries=loads,
            balance_ratio=float(max(loads) / mean_load) if mean_load > 0 else 0.0,
            scraped=[int(scraped.get(r, 0)) for r in range(settings.robots)],
        ),
        rejected_requests=metrics.total("swarmrec_rejected_requests_total"),
        peer_failures=metrics.by_label("swarmrec_peer_failures_total", "reason"),
        loop_closures=ClosureStats(
            count=len(run.closures),
            scraped_total=metrics.total("swarmrec_loop_closures_total"),
            min_score=run.loop_closure_min_score,
        ),
        pairs=PairStats(checked_positive=int(np.count_nonzero(matrix.scores > 0)), conflicting=conflicts),
        scrape_failed=metrics.failed,
        exit_codes=run.exit_codes,
        timings=run.timings,
        links=run.links,
        mesh=run.mesh,
    )
    if run.detector is not None:
        summary.detector = _detector_figures(run.detector, metrics)
    if run.index is not None:
        summary.index = _index_summary(run.index, metrics, settings.replicas, run.placement_changes)
    summary.funnel = funnel_stats(replay.reports, run.closures, metrics)
    offline = run.offline
    # Frames delivered late were stored after their step: the lock-step identity is off then.
    if settings.check_offline and settings.lockstep and not replay.missing and not replay.late:
        summary.offline_check = _compare_offline(matrix, offline.matrix(wire=True))
        if offline.reach is not None and offline.holdings is not None:
            reach = offline.reach
            summary.offline_check.split_steps = sum(reach.split_at(t) for t in range(len(reach.components)))
            summary.offline_check.unreached_group_queries = len(offline.holdings.unreached)
            summary.offline_check.unreachable_verifications = len(offline.holdings.unverified)
    else:
        summary.offline_not_compared = _why_not_compared(settings, len(replay.missing), len(replay.late))
    dense = matrix.dense()
    curves: dict[str, PRCurve] = {}
    truth = None
    gt = offline.ground_truth()
    if gt is not None:
        name = f"swarm x{settings.robots}"
        curves[name] = precision_recall(dense, gt.closures)
        summary.auc = curves[name].auc
        truth = gt.closures
        if run.wire_seq is not run.seq and settings.check_offline:
            summary.positions_effect = _positions_effect(offline, gt.closures)
    _write_pairs(out / "pairs.csv", matrix, wire_seq)
    _write_closures(out / "loop_closures.csv", run.closures, run.blocks, seq, truth)
    write_funnel(out, replay.reports, run.closures, run.blocks, seq)
    if settings.plots:
        _plots(settings, summary, dense, curves, wire_seq, run.bounds, run.blocks, loads)
        if gt is not None and offline.trajectory is not None:
            # Where poses are known, the closures on the camera trajectory.
            positions = offline.trajectory.positions[gt.poses.index]
            pairs = [_frames_of(c, run.blocks) for c in run.closures]
            starts = [b.start for b in run.blocks]
            title = f"{wire_seq.name}, {settings.robots} robots"
            plot_closures_map(positions, starts, pairs, gt.closures, title, out / "closures_map.png")
    (out / "summary.json").write_text(json.dumps(summary.to_dict(), indent=2) + "\n")
    return summary


def _pct(values: list[float] | list[int]) -> dict[str, float]:
    if not values:
        return {}
    arr = np.asarray(values, dtype=np.float64)
    return {f"p{q}": float(np.percentile(arr, q)) for q in (50, 90, 99)} | {"mean": float(arr.mean())}


def _write_pairs(path: Path, matrix: ScoreMatrix, seq: ConstellationSequence) -> None:
    keep = matrix.scores > 0
    with path.open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["frame_i", "frame_j", "frame_id_i", "frame_id_j", "score"])
        for i, j, s in zip(matrix.pairs_i[keep], matrix.pairs_j[keep], matrix.scores[keep], strict=True):
            w.writerow([int(i), int(j), seq.frame_ids[i], seq.frame_ids[j], repr(float(s))])


def _frames_of(closure: pb.LoopClosure, blocks: list[range]) -> tuple[int, int]:
    """The sequence's (global) indices of a loop closure's query and matched frames."""
    return (
        blocks[closure.query_robot_id].start + closure.query_frame_index,
        blocks[closure.match_robot_id].start + closure.match_frame_index,
    )


def _write_closures(
    path: Path,
    closures: list[pb.LoopClosure],
    blocks: list[range],
    seq: ConstellationSequence,
    truth: npt.NDArray[np.bool_] | None,
) -> None:
    with path.open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(
            [
                "query_robot",
                "query_frame",
                "match_robot",
                "match_frame",
                "query_frame_id",
                "match_frame_id",
                "score",
                "n_matched",
                "true_closure",
            ]
        )
        for c in sorted(closures, key=lambda c: (c.query_robot_id, c.query_frame_index)):
            g, h = _frames_of(c, blocks)
            true = "" if truth is None else int(truth[g, h])
            w.writerow(
                [
                    c.query_robot_id,
                    c.query_frame_index,
                    c.match_robot_id,
                    c.match_frame_index,
                    seq.frame_ids[g],
                    seq.frame_ids[h],
                    f"{c.score:.6f}",
                    c.n_matched,
                    true,
                ]
            )


def _plots(
    settings: ReportSettings,
    summary: PlacesSummary,
    dense: npt.NDArray[np.float64],
    curves: dict[str, PRCurve],
    seq: ConstellationSequence,
    bounds: npt.NDArray[np.int64],
    blocks: list[range],
    loads: list[int],
) -> None:
    out = settings.out
    starts = [b.start for b in blocks]
    plot_similarity(
        dense, f"{seq.name}: swarm of {settings.robots} robots", out / "similarity.png", robot_starts=starts
    )
    if curves:
        plot_pr(curves, out / "precision_recall.png")
    counts = label_counts(seq.constellations, seq.n_labels)
    holder = np.repeat(np.arange(len(loads)), np.diff(bounds))
    labels = np.bincount(holder, weights=(counts > 0), minlength=len(loads)).astype(int).tolist()
    objects = np.bincount(holder, weights=counts, minlength=len(loads)).astype(int).tolist()
    load = HolderLoad(bounds=[int(b) for b in bounds], partial_queries=loads, labels=labels, objects=objects)
    plot_holder_load(load, counts, seq.label_names, out / "shard_load.png")
    plot_bytes(summary.bytes.per_query_by_message, out / "bytes_per_query.png")
    if summary.funnel is not None:
        plot_funnel(
            summary.funnel.levels,
            {int(r): stops for r, stops in summary.funnel.by_robot.items()},
            out / "funnel.png",
            order=[r.label for r in reversed(Reason)],
        )


# --- the loop-closure funnel ---------------------------------------------------------


def _funnel_fields_cleared(report: pb.QueryReport) -> pb.QueryReport:
    bare = pb.QueryReport()
    bare.CopyFrom(report)
    for name in ("n_objects", "shard_candidates", "candidates"):
        bare.ClearField(name)
    return bare


def _adds_up(report: pb.QueryReport) -> bool:
    """One query's funnel is consistent: the shards' counts sum to n_candidates, each
    distinct candidate has one known reason, and at most one is the loop closure."""
    outcomes = outcomes_from_proto(report)
    keys = [(o.robot, o.frame) for o in outcomes]
    returned = sum(s.n_candidates for s in report.shard_candidates)
    return (
        returned == report.n_candidates
        and len(set(keys)) == len(keys) <= returned
        and all(o.reason != Reason.UNSPECIFIED for o in outcomes)
        and sum(o.reason == Reason.ACCEPTED for o in outcomes) <= 1
        and (report.queried or not outcomes)
    )


def funnel_stats(
    reports: list[pb.QueryReport], closures: list[pb.LoopClosure], metrics: Scrape
) -> FunnelStats:
    """The funnel of ``reports``, checked against the loop closures the descriptors hold."""
    reasons: Counter[Reason] = Counter()
    by_robot: dict[str, Counter[str]] = {}
    for rep in reports:
        mine = by_robot.setdefault(str(rep.robot_id), Counter())
        for o in outcomes_from_proto(rep):
            reasons[o.reason] += 1
            mine[o.reason.label] += 1
    stages: Counter[str] = Counter()
    for reason, n in reasons.items():
        stages[reason.stage.label] += n
    sizes = [len(r.SerializeToString()) for r in reports]
    bare = [len(_funnel_fields_cleared(r).SerializeToString()) for r in reports]
    queried = sum(r.queried for r in reports)
    return FunnelStats(
        frames=len(reports),
        queried=queried,
        too_few_objects=len(reports) - queried,
        candidates_returned=sum(r.n_candidates for r in reports),
        distinct_candidates=sum(reasons.values()),
        by_stage={s.label: stages[s.label] for s in Stage if stages[s.label]},
        by_reason={r.label: reasons[r] for r in Reason if reasons[r]},
        by_robot={
            r: {x.label: c[x.label] for x in Reason if c[x.label]}
            for r, c in sorted(by_robot.items(), key=lambda kv: int(kv[0]))
        },
        levels=passed_stages(reasons.elements()),
        accepted=reasons[Reason.ACCEPTED],
        accepted_equals_loop_closures=reasons[Reason.ACCEPTED] == len(closures),
        inconsistent_queries=sum(not _adds_up(r) for r in reports),
        scraped_by_reason=metrics.by_label("swarmrec_funnel_candidates_total", "reason"),
        report_bytes_mean=float(np.mean(sizes)) if sizes else 0.0,
        report_bytes_mean_without_funnel=float(np.mean(bare)) if bare else 0.0,
    )


#: funnel.csv's columns: one row per distinct candidate of each query.
FUNNEL_COLUMNS = (
    "query_robot",
    "query_frame",
    "candidate_robot",
    "candidate_frame",
    "stage",
    "reason",
    "score",
    "query_frame_id",
    "candidate_frame_id",
)
#: funnel_queries.csv's columns: one row per frame a descriptor reported on.
QUERY_COLUMNS = (
    "robot",
    "frame",
    "frame_id",
    "queried",
    "n_objects",
    "n_candidates",
    "shard_candidates",
    "failed_shards",
    "verified_robots",
    "failed_verifiers",
    "loop_closure",
)

#: Reasons of a candidate that was never scored (no score column).
_NOT_SCORED = frozenset({Reason.ROBOT_NOT_CHOSEN, Reason.VERIFIER_UNREACHABLE, Reason.VERIFIER_TIMEOUT,
                         Reason.VERIFIER_ERROR, Reason.BELOW_SHARD_CUT})  # fmt: skip


def _frame_id(seq: ConstellationSequence, blocks: list[range], robot: int, frame: int) -> str:
    if robot < len(blocks) and frame < len(blocks[robot]):
        return seq.frame_ids[blocks[robot][frame]]
    return ""


def write_funnel(
    out: Path,
    reports: list[pb.QueryReport],
    closures: list[pb.LoopClosure],
    blocks: list[range],
    seq: ConstellationSequence,
) -> None:
    """``funnel.csv`` (every candidate of every query, where it stopped) and
    ``funnel_queries.csv`` (every frame: queried or why not, what each shard returned,
    who verified, its loop closure)."""
    ordered = sorted(reports, key=lambda r: (r.robot_id, r.frame_index))
    closure_of = {(c.query_robot_id, c.query_frame_index): c for c in closures}
    with (out / "funnel.csv").open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(FUNNEL_COLUMNS)
        for rep in ordered:
            q_id = _frame_id(seq, blocks, rep.robot_id, rep.frame_index)
            for o in outcomes_from_proto(rep):
                w.writerow(
                    [
                        rep.robot_id,
                        rep.frame_index,
                        o.robot,
                        o.frame,
                        o.stage.label,
                        o.reason.label,
                        "" if o.reason in _NOT_SCORED else repr(o.score),
                        q_id,
                        _frame_id(seq, blocks, o.robot, o.frame),
                    ]
                )
    with (out / "funnel_queries.csv").open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(QUERY_COLUMNS)
        for rep in ordered:
            c = closure_of.get((rep.robot_id, rep.frame_index))
            w.writerow(
                [
                    rep.robot_id,
                    rep.frame_index,
                    _frame_id(seq, blocks, rep.robot_id, rep.frame_index),
                    int(rep.queried),
                    rep.n_objects,
                    rep.n_candidates,
                    " ".join(f"{s.group}/{s.robot_id}:{s.n_candidates}" for s in rep.shard_candidates),
                    " ".join(str(r) for r in rep.failed_shard_robot_ids),
                    " ".join(str(r) for r in rep.verified_robot_ids),
                    " ".join(str(r) for r in rep.failed_verifier_robot_ids),
                    "" if c is None else f"{c.match_robot_id}:{c.match_frame_index}",
                ]
            )
