"""The live distributed solve's report: outcome, iterations, accuracy, bytes measured, the check.

What the swarm did comes from the robots themselves (their status, estimate and
the estimates they sent) and from their Prometheus counters as the deployment
read them at the end; nothing is recomputed from a formula but the model the
bytes are compared with (9 floats per separator key in the rotation stage, 6 in
a pose stage, 8 bytes each). The reference is :func:`~swarmrec.slam.dgs.run_dgs`
on the same graph and settings in this process: every robot's messages, reports
and estimate must equal it bit for bit (after an abort: its messages and reports
a prefix of it, its estimate run_dgs's after the iteration the survivors ended
at). ``summary.json`` is :class:`LiveSlamSummary`; the files are listed in
docs/slam.md ("The live service").
"""

from __future__ import annotations

import json
import math
import struct
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from swarmrec.deployments.metrics import Scrape
from swarmrec.experiments.slam.settings import SUMMARY_NAME, LiveSlamSettings
from swarmrec.slam.agent import LocalProblem
from swarmrec.slam.centralized import solve_centralized
from swarmrec.slam.dgs import DistributedResult, run_dgs
from swarmrec.slam.g2o import robot_file_name, write_g2o
from swarmrec.slam.graph import PoseGraph, is_landmark_key
from swarmrec.slam.lie import Pose
from swarmrec.slam.messages import FLOATS_PER_ESTIMATE, DgsMessage, StepReport
from swarmrec.slam.metrics import are_star, ate_star
from swarmrec.slam.offline import finite_json
from swarmrec.slam.scenarios import Scenario
from swarmrec.wire import messages as pb
from swarmrec.wire.slam import estimate_from_proto, report_from_proto, turn_from_proto

__all__ = [
    "BYTES_PER_FLOAT",
    "Check",
    "LinkBytes",
    "LiveRecord",
    "LiveSlamSummary",
    "RobotOutcome",
    "RobotResult",
    "format_summary",
    "plot_maps",
    "write_report",
]

#: The model's float: what the agents compute in and the wire carries (float64).
BYTES_PER_FLOAT = 8


@dataclass(frozen=True)
class RobotResult:
    """What one robot answered at the end: its status, its estimate, the estimates it sent."""

    robot: int
    status: pb.SlamStatus
    estimate: pb.SlamEstimate
    sent: Sequence[pb.SlamStep]


@dataclass(eq=False)
class LiveRecord:
    """Everything a live solve produced, for :func:`write_report`."""

    settings: LiveSlamSettings
    folder: str
    graph: PoseGraph
    truth: dict[int, Pose] | None
    scenario: Scenario | None
    solve_id: int
    results: dict[int, RobotResult]
    metrics: Scrape
    exit_codes: dict[str, int]
    deployment: str
    timings: dict[str, float]


@dataclass(frozen=True)
class RobotOutcome:
    robot: int
    state: str
    reason: str
    #: The position its estimate is at: (linearisation, iteration).
    position: tuple[int, int]
    #: Team members' messages it refused (nothing changed).
    rejected: int


@dataclass(frozen=True)
class LinkBytes:
    """One directed link in one stage: the separator estimates sent over it, measured and modelled.

    ``iterations`` is the number of messages that carried estimates (one per iteration
    in which the sender solved); ``bytes`` their protobuf payload (report, keys and
    estimates); ``model_bytes`` = ``keys`` x 9 (rotation) or 6 (pose) x 8 B per iteration.
    """

    sender: int
    receiver: int
    stage: str
    keys: int
    iterations: int
    bytes: int
    floats: int
    bytes_per_iteration: float
    model_bytes_per_iteration: float


@dataclass(frozen=True)
class Check:
    """The live solve against run_dgs in one process (bit for bit)."""

    reference: str
    messages_live: int
    messages_reference: int
    messages_identical: bool
    reports_identical: bool
    estimates_identical: bool
    differences: list[str] = field(default_factory=list)

    @property
    def identical(self) -> bool:
        return self.messages_identical and self.reports_identical and self.estimates_identical


@dataclass
class LiveSlamSummary:
    """Everything ``summary.json`` holds (:meth:`to_dict`)."""

    source: str
    robots: int
    vertices: int
    edges: int
    separators: int
    solve_id: int
    solver: dict[str, Any]
    outcome: str
    robot_outcomes: list[RobotOutcome]
    order: list[int]
    #: (stage, linearisation, iterations, converged) of each stage, as the robots ran them.
    stages: list[tuple[str, int, int, bool]]
    stages_agree: bool
    cost_initial: float
    cost_distributed: float | None
    cost_centralized: float
    centralized_method: str
    ate_poses_m: float
    ate_landmarks_m: float
    are_poses_deg: float
    ate_vs_truth_m: float | None
    ate_centralized_vs_truth_m: float | None
    links: list[LinkBytes]
    #: Mean over links of measured / modelled bytes per iteration, per stage.
    bytes_per_iteration: dict[str, dict[str, float]]
    swarm_bytes: dict[str, float]
    rejected: dict[str, float]
    check: Check | None
    deployment: str
    exit_codes: dict[str, int]
    timings: dict[str, float]
    files: list[str]

    @property
    def complete(self) -> bool:
        return self.outcome in ("converged", "unconverged")

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = finite_json(asdict(self))
        if self.check is not None:
            out["check"]["identical"] = self.check.identical
        return out


# --- the check ------------------------------------------------------------------------


def _bits(values: Sequence[float]) -> bytes:
    return struct.pack(f"<{len(values)}d", *values)


def _same_message(a: DgsMessage, b: DgsMessage) -> bool:
    head = (a.sender, a.receiver, a.stage, a.linearisation, a.iteration)
    if head != (b.sender, b.receiver, b.stage, b.linearisation, b.iteration):
        return False
    if list(a.estimates) != list(b.estimates) and sorted(a.estimates) != sorted(b.estimates):
        return False
    return all(_bits(a.estimates[k]) == _bits(b.estimates[k]) for k in a.estimates)


def _same_report(a: StepReport, b: StepReport) -> bool:
    head = (a.robot, a.stage, a.linearisation, a.iteration, a.solved)
    return head == (b.robot, b.stage, b.linearisation, b.iteration, b.solved) and _bits([a.change]) == _bits(
        [b.change]
    )


def _same_pose(a: Pose, b: Pose) -> bool:
    return a.rotation.tobytes() == b.rotation.tobytes() and a.translation.tobytes() == b.translation.tobytes()


def check_against_reference(
    results: Mapping[int, RobotResult], reference: DistributedResult, graph: PoseGraph
) -> Check:
    """Every robot's messages, reports and estimate against ``reference`` (run with a trace
    when a robot aborted), bit for bit."""
    trace = {(t.linearisation, t.iteration): t.poses for t in reference.trace}
    differences: list[str] = []
    n_live = 0
    messages_ok = reports_ok = estimates_ok = True
    positions = set()
    for r, res in sorted(results.items()):
        ended = res.status.state == pb.SlamState.SLAM_STATE_DONE
        live = [turn_from_proto(s).message for s in res.sent]
        ref = [m for m in reference.messages if m.sender == r]
        n_live += len(live)
        same = all(m is not None and _same_message(m, n) for m, n in zip(live, ref, strict=False))
        if not same or len(live) > len(ref) or (ended and len(live) != len(ref)):
            messages_ok = False
            differences.append(
                f"robot {r}: {len(live)} messages sent, run_dgs sends {len(ref)}, same: {same}"
            )
        reports = [report_from_proto(r, x) for x in res.status.reports]
        ref_reports = [x for x in reference.reports if x.robot == r]
        same = all(_same_report(a, b) for a, b in zip(reports, ref_reports, strict=False))
        if not same or len(reports) > len(ref_reports) or (ended and len(reports) != len(ref_reports)):
            reports_ok = False
            differences.append(f"robot {r}: {len(reports)} reports, run_dgs {len(ref_reports)}, same: {same}")
        position = (res.estimate.linearisation, res.estimate.iteration)
        positions.add(position)
        if ended:
            expected: Mapping[int, Pose] = reference.poses
        elif position == (0, 0):
            expected = graph.poses
        else:
            expected = trace.get(position, {})
        estimate = estimate_from_proto(res.estimate)
        if set(estimate) != set(graph.robot_keys(r)) or not all(
            k in expected and _same_pose(p, expected[k]) for k, p in estimate.items()
        ):
            estimates_ok = False
            differences.append(f"robot {r}: estimate at {position} differs from run_dgs's")
    done = all(res.status.state == pb.SlamState.SLAM_STATE_DONE for res in results.values())
    where = "run_dgs's final estimate" if done else f"run_dgs's estimate after {sorted(positions)}"
    return Check(where, n_live, len(reference.messages), messages_ok, reports_ok, estimates_ok, differences)


# --- bytes ----------------------------------------------------------------------------


def _link_bytes(metrics: Scrape, graph: PoseGraph) -> list[LinkBytes]:
    """Per directed link and stage, from each sender's own counters."""
    sums: dict[tuple[int, int, str], dict[str, float]] = {}
    for (kind, robot), series in metrics.samples.items():
        if kind != "slam":
            continue
        for (name, labels), value in series.items():
            lab = dict(labels)
            if lab.get("carries", "estimates") != "estimates" or "peer" not in lab:
                continue
            column = {
                "swarmrec_slam_sent_bytes_total": "bytes",
                "swarmrec_slam_sent_messages_total": "messages",
                "swarmrec_slam_sent_floats_total": "floats",
            }.get(name)
            if column is not None:
                entry = sums.setdefault((robot, int(lab["peer"]), lab["stage"]), {})
                entry[column] = entry.get(column, 0.0) + value
    anchor = graph.anchor_key()
    problems = {r: LocalProblem.from_graph(graph, r, anchor=anchor) for r in graph.robots}
    out = []
    for (s, r, stage), v in sorted(sums.items()):
        n = int(v.get("messages", 0))
        keys = len(problems[s].shared.get(r, ())) if s in problems else 0
        model = keys * FLOATS_PER_ESTIMATE["rotation" if stage == "rotation" else "pose"] * BYTES_PER_FLOAT
        out.append(
            LinkBytes(
                s,
                r,
                stage,
                keys,
                n,
                int(v.get("bytes", 0)),
                int(v.get("floats", 0)),
                v.get("bytes", 0.0) / n if n else math.nan,
                float(model),
            )
        )
    return out


def _per_stage(links: Sequence[LinkBytes]) -> dict[str, dict[str, float]]:
    out: dict[str, dict[str, float]] = {}
    for stage in ("rotation", "pose"):
        rows = [link for link in links if link.stage == stage and link.iterations]
        if rows:
            measured = float(np.mean([x.bytes_per_iteration for x in rows]))
            model = float(np.mean([x.model_bytes_per_iteration for x in rows]))
            floats = float(np.mean([x.floats / x.iterations for x in rows]))
            out[stage] = {
                "measured_bytes": measured,
                "model_bytes": model,
                "floats": floats,
                "ratio": measured / model if model else math.nan,
            }
    return out


# --- the report -----------------------------------------------------------------------


# matplotlib's tab10, then tab20's lighter shades: 20 robots before a colour repeats.
_COLOURS = (
    "#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22",
    "#17becf", "#aec7e8", "#ffbb78", "#98df8a", "#ff9896", "#c5b0d5", "#c49c94", "#f7b6d2", "#c7c7c7",
    "#dbdb8d", "#9edae5",
)  # fmt: skip


def plot_maps(
    path: Path, graph: PoseGraph, maps: Mapping[str, Mapping[int, Pose]], scenario: Scenario | None = None
) -> None:
    """Fig. 4-style: one panel per map, each robot's trajectory and objects in its colour
    (a simulated world's true objects as grey crosses)."""
    import matplotlib

    matplotlib.use("Agg")  # files only: never needs a display
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(
        1, len(maps), figsize=(6 * len(maps), 5.5), sharex=True, sharey=True, squeeze=False
    )
    for ax, (title, poses) in zip(axes[0], maps.items(), strict=True):
        if scenario is not None:
            truth = np.array([o.pose.translation[:2] for o in scenario.objects])
            ax.scatter(truth[:, 0], truth[:, 1], marker="x", c="0.6", s=30, label="true objects")
        for robot in graph.robots:
            keys = [k for k in graph.robot_keys(robot) if k in poses]
            colour = _COLOURS[robot % len(_COLOURS)]
            path_xy = np.array([poses[k].translation[:2] for k in keys if not is_landmark_key(k)])
            objects = np.array([poses[k].translation[:2] for k in keys if is_landmark_key(k)])
            if len(path_xy):
                ax.plot(path_xy[:, 0], path_xy[:, 1], "-", color=colour, lw=1.2, label=f"robot {robot}")
            if len(objects):
                ax.scatter(objects[:, 0], objects[:, 1], color=colour, s=12)
        ax.set_title(title)
        ax.set_aspect("equal")
        ax.grid(True, alpha=0.3)
        ax.set_xlabel("x (m)")
    axes[0][0].set_ylabel("y (m)")
    axes[0][0].legend(fontsize=8, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _outcome(results: Mapping[int, RobotResult], robots: int) -> str:
    states = {pb.SlamState.Name(res.status.state) for res in results.values()}
    if "SLAM_STATE_FAILED" in states:
        return "failed"
    if "SLAM_STATE_ABORTED" in states or len(results) < robots:
        return "aborted"
    if all(res.status.converged for res in results.values()):
        return "converged"
    return "unconverged"


def write_report(record: LiveRecord, t_start: float) -> LiveSlamSummary:
    """Compare, measure, write ``<r>.g2o``, ``merged.g2o``, ``centralized.g2o``, the map figure and
    ``summary.json`` under ``settings.out``; returns the summary."""
    s, graph, results = record.settings, record.graph, record.results
    out = s.out
    robots = len(graph.robots)
    timings = dict(record.timings)
    merged: dict[int, Pose] = {}
    for res in results.values():
        merged.update(estimate_from_proto(res.estimate))
    outcome = _outcome(results, robots)
    t0 = time.perf_counter()
    centralized = solve_centralized(graph, method=s.centralized, anchor=graph.anchor_key())
    timings["centralized_s"] = time.perf_counter() - t0
    check = None
    if s.check:
        t0 = time.perf_counter()
        reference = run_dgs(graph, s.solver, trace=outcome not in ("converged", "unconverged"))
        timings["reference_s"] = time.perf_counter() - t0
        check = check_against_reference(results, reference, graph)
    poses = [k for k in graph.keys if k in merged and not is_landmark_key(k)]
    landmarks = [k for k in graph.keys if k in merged and is_landmark_key(k)]
    files = []
    for r in sorted(results):
        keys = graph.robot_keys(r)
        files.append(
            write_g2o(out / robot_file_name(r), graph, merged, keys=keys, edges=graph.robot_edges(r))
        )
    if len(merged) == len(graph.poses):
        files.append(write_g2o(out / "merged.g2o", graph, merged))
    files.append(write_g2o(out / "centralized.g2o", graph, centralized.poses))
    if s.plots:
        figure = out / "map.png"
        title = f"live distributed ({outcome})"
        plot_maps(
            figure,
            graph,
            {"centralized Gauss-Newton (gtsam)": centralized.poses, title: merged},
            record.scenario,
        )
        files.append(figure)
    first = results[min(results)].status if results else pb.SlamStatus()
    stages = [
        (pb.SlamStage.Name(x.stage)[11:].lower(), x.linearisation, x.iterations, x.converged)
        for x in first.stages
    ]
    agree = all(
        [(x.linearisation, x.iterations, x.converged) for x in res.status.stages]
        == [(x[1], x[2], x[3]) for x in stages]
        for res in results.values()
    )
    links = _link_bytes(record.metrics, graph)
    truth = record.truth
    summary = LiveSlamSummary(
        source=record.folder
        if s.folder is not None
        else f"{s.world} world, {s.robots} robots, seed {s.seed}",
        robots=robots,
        vertices=len(graph.poses),
        edges=len(graph.edges),
        separators=len(graph.separators()),
        solve_id=record.solve_id,
        solver=asdict(s.solver) | {"gamma": s.solver.over_relaxation},
        outcome=outcome,
        robot_outcomes=[
            RobotOutcome(
                r,
                pb.SlamState.Name(res.status.state)[11:].lower(),
                res.status.reason,
                (res.estimate.linearisation, res.estimate.iteration),
                int(res.status.rejected),
            )
            for r, res in sorted(results.items())
        ],
        order=list(first.order),
        stages=stages,
        stages_agree=agree,
        cost_initial=graph.cost(),
        cost_distributed=graph.cost(merged) if len(merged) == len(graph.poses) else None,
        cost_centralized=graph.cost(centralized.poses),
        centralized_method=s.centralized,
        ate_poses_m=ate_star(merged, centralized.poses, poses),
        ate_landmarks_m=ate_star(merged, centralized.poses, landmarks),
        are_poses_deg=math.degrees(are_star(merged, centralized.poses, poses)),
        ate_vs_truth_m=ate_star(merged, truth, poses) if truth is not None else None,
        ate_centralized_vs_truth_m=ate_star(
            centralized.poses, truth, [k for k in graph.keys if not is_landmark_key(k)]
        )
        if truth is not None
        else None,
        links=links,
        bytes_per_iteration=_per_stage(links),
        swarm_bytes={
            m: record.metrics.total("swarmrec_message_bytes_sent_total", message=m, scope="swarm")
            for m in ("SlamStep", "SlamControl")
        },
        rejected=record.metrics.by_label("swarmrec_slam_rejected_total", "reason"),
        check=check,
        deployment=record.deployment,
        exit_codes=record.exit_codes,
        timings=timings | {"total_s": time.perf_counter() - t_start},
        files=[str(f) for f in files],
    )
    (out / SUMMARY_NAME).write_text(json.dumps(summary.to_dict(), indent=2) + "\n", encoding="utf-8")
    return summary


def format_summary(summary: LiveSlamSummary) -> str:
    """A few lines for a terminal."""
    lines = [
        f"live distributed {summary.solver['mode']} on {summary.source}: {summary.robots} robots "
        "(one slam service each), "
        f"{summary.vertices} vertices, {summary.separators} separators, order {summary.order}",
        f"  outcome: {summary.outcome}; iterations "
        + ", ".join(f"{st} {lin}: {n}{'' if ok else ' (max)'}" for st, lin, n, ok in summary.stages),
    ]
    for o in summary.robot_outcomes:
        if o.state != "done":
            lines.append(f"  robot {o.robot}: {o.state} at {o.position}: {o.reason}")
    cost = "n/a" if summary.cost_distributed is None else f"{summary.cost_distributed:.6g}"
    lines.append(
        f"  cost: initial {summary.cost_initial:.4g}, distributed {cost}, "
        f"centralized {summary.centralized_method} {summary.cost_centralized:.6g}"
    )
    accuracy = f"  ATE* poses {summary.ate_poses_m:.3g} m, ARE* poses {summary.are_poses_deg:.3g} deg"
    accuracy += " (vs centralized)"
    if summary.ate_vs_truth_m is not None and summary.ate_centralized_vs_truth_m is not None:
        accuracy += (
            f"; vs the world's truth {summary.ate_vs_truth_m:.3g} m "
            f"(centralized {summary.ate_centralized_vs_truth_m:.3g} m)"
        )
    lines.append(accuracy)
    for stage, v in summary.bytes_per_iteration.items():
        lines.append(
            f"  bytes per link per iteration, {stage}: measured {v['measured_bytes']:.0f} B, "
            f"model {v['model_bytes']:.0f} B ({v['floats']:.1f} floats x 8 B), x{v['ratio']:.3f}"
        )
    if summary.check is not None:
        c = summary.check
        verdict = "identical" if c.identical else "DIFFERENT: " + "; ".join(c.differences[:3])
        lines.append(f"  vs run_dgs in one process ({c.reference}), {c.messages_live} messages: {verdict}")
    return "\n".join(lines)
