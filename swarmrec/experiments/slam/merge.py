"""One merged map from a finished place-recognition run: the pipeline behind ``swarmrec slam merge``.

Issue 14's one pipeline, on the place-recognition swarm's own office world::

    pixels / constellations   the run's frames (its dataset, or the detections made from pixels)
    loop closures             the run's verified loop closures (loop_closures.csv)
    inter-robot constraints   for each closure between two robots: the verifier's association
                              of the two constellations (the same core function, on the
                              millimetres the swarm carried; its match count must be the run's)
                              gives matched object pairs; RANSAC rigid alignment of their 3D
                              points gives the relative pose of the two cameras
    robot graphs              each robot's keyframes (every ``keyframe_every``-th frame of its
                              share, and every frame of a kept closure) chained by odometry
    outliers                  PCM per pair of robots (:func:`~swarmrec.slam.robust.pcm`), then gtsam's
                              GNC on the team's graph (:func:`~swarmrec.slam.robust.gnc`): the
                              world's look-alike desks give wrong closures that agree with each
                              other, which PCM alone keeps
    merged map                the distributed two-stage Gauss-Seidel: live, one slam service
                              per robot (:mod:`.pipeline`), or in one process (``live=False``)
    error                     against the synthetic world's camera poses: ATE of the merged
                              trajectories and the error of every object point placed by them

The run holds no odometry: the robots of the place-recognition swarm only send
constellations. Each robot's odometry is therefore simulated from the world's
camera poses (relative poses of consecutive keyframes, seeded Gaussian noise of
``odometry_sigma_deg`` / ``odometry_sigma_m``, information to match). Robot 0's
first keyframe is the anchor, at its true pose, so the estimate is in the
world's frame and compared without alignment; every other robot starts
knowing nothing of where it is (dead reckoning from the identity).
"""

from __future__ import annotations

import csv
import json
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np

from swarmrec.core.presets import Preset
from swarmrec.core.split import split_frames
from swarmrec.core.types import Constellation, ConstellationSequence, Trajectory
from swarmrec.core.verification import verify
from swarmrec.datasets.constellations import read_constellations
from swarmrec.datasets.labels import label_names
from swarmrec.datasets.tum import read_trajectory
from swarmrec.deployments.base import Deployment
from swarmrec.errors import ConfigError, DatasetError
from swarmrec.experiments.slam.pipeline import main as live_main
from swarmrec.experiments.slam.report import LiveSlamSummary, plot_maps
from swarmrec.experiments.slam.settings import SUMMARY_NAME, LiveSlamSettings
from swarmrec.slam.alignment import ransac_rigid
from swarmrec.slam.centralized import METHODS, Method, solve_centralized
from swarmrec.slam.dgs import DgsSettings, run_dgs
from swarmrec.slam.errors import AlignmentError, GraphError
from swarmrec.slam.g2o import parse_g2o, read_g2o, read_robot_folder, robot_file_name, write_g2o
from swarmrec.slam.graph import Edge, PoseGraph
from swarmrec.slam.keys import pose_key
from swarmrec.slam.lie import Pose, so3_exp, so3_log
from swarmrec.slam.offline import finite_json
from swarmrec.slam.robust import gnc, pcm
from swarmrec.wire.codec import constellation_from_proto, constellation_to_proto

__all__ = ["ClosureRecord", "MergeSettings", "MergeSummary", "build_team_graph", "format_merge", "merge_run"]

Reject = Literal["none", "pcm", "pcm+gnc"]
REJECTIONS: tuple[Reject, ...] = ("none", "pcm", "pcm+gnc")
#: A closure's relative pose is right when it is within these of the truth (for the report only).
RIGHT_ROTATION_DEG = 10.0
RIGHT_TRANSLATION_M = 0.3


@dataclass(frozen=True)
class MergeSettings:
    """What ``swarmrec slam merge`` does (defaults: keyframe every 5 frames, odometry 0.5 deg / 2 cm).

    - ``run``: a finished ``swarmrec run`` folder of the synthetic world (summary.json,
      loop_closures.csv, dataset/ or detections/, and the world's groundtruth.txt).
    - ``keyframe_every``: a robot pose every K frames of its share (plus closure frames).
    - ``odometry_sigma_deg``, ``odometry_sigma_m``, ``noise_seed``: the simulated odometry (noise
      per step between consecutive keyframes, whatever its length).
    - ``ransac_threshold_m``, ``min_inliers``: the rigid alignment of matched objects.
    - ``reject``: how wrong inter-robot constraints are rejected before the solve: ``pcm`` (per
      pair of robots), ``pcm+gnc`` (then gtsam's GNC on the team's graph, the odometry known
      inliers), or ``none``. Both are centralized checks of the front end's output, done here
      before the robots' graphs are written. ``pair_support``: keep a pair of robots'
      constraints only when at least this many survive (a lone one is never contradicted).
    - ``live``: solve as slam services (else :func:`~swarmrec.slam.dgs.run_dgs` in one process).
    - ``solver``: the distributed solver's settings (:class:`~swarmrec.slam.dgs.DgsSettings`).
    """

    run: Path
    out: Path
    keyframe_every: int = 5
    odometry_sigma_deg: float = 0.5
    odometry_sigma_m: float = 0.02
    noise_seed: int = 0
    ransac_threshold_m: float = 0.15
    min_inliers: int = 4
    reject: Reject = "pcm+gnc"
    pair_support: int = 1
    live: bool = True
    solver: DgsSettings = field(default_factory=DgsSettings)
    centralized: Method = "gauss-newton"
    progress: bool = True
    overwrite: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "run", Path(self.run))
        object.__setattr__(self, "out", Path(self.out))
        if not (self.run / "summary.json").is_file() or not (self.run / "loop_closures.csv").is_file():
            raise ConfigError(
                f"{self.run} is not a finished `swarmrec run` folder (summary.json, loop_closures.csv)"
            )
        if (self.out / SUMMARY_NAME).exists() and not self.overwrite:
            raise ConfigError(
                f"{self.out / SUMMARY_NAME} exists: add --overwrite to replace it (Python: overwrite=True)"
            )
        if self.keyframe_every < 1 or self.min_inliers < 3 or self.pair_support < 1:
            raise ConfigError("keyframe_every and pair_support must be >= 1, min_inliers >= 3")
        for name in ("odometry_sigma_deg", "odometry_sigma_m", "ransac_threshold_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"{name} must be > 0, got {value}")
        if self.centralized not in METHODS:
            raise ConfigError(f"centralized must be one of {METHODS}, got {self.centralized!r}")
        if self.reject not in REJECTIONS:
            raise ConfigError(f"reject must be one of {REJECTIONS}, got {self.reject!r}")


@dataclass(frozen=True)
class ClosureRecord:
    """One verified loop closure between two robots and what became of it."""

    query_robot: int
    query_frame: int
    match_robot: int
    match_frame: int
    n_matched: int
    #: aligned | too_few_pairs | alignment_failed | not_verified (the association disagrees with the run)
    status: str
    inliers: int = 0
    rms_m: float = math.nan
    #: Error of the measured relative pose against the world's truth (degrees, metres).
    rotation_error_deg: float = math.nan
    translation_error_m: float = math.nan
    kept: bool = False

    @property
    def right(self) -> bool:
        return self.rotation_error_deg < RIGHT_ROTATION_DEG and self.translation_error_m < RIGHT_TRANSLATION_M


@dataclass
class MergeSummary:
    """Everything the merge's ``summary.json`` holds."""

    run: str
    robots: int
    frames: int
    keyframes: int
    closures_inter_robot: int
    constraints_aligned: int
    constraints_right: int
    reject: str
    constraints_kept: int
    constraints_kept_right: int
    separators: int
    solver: str
    outcome: str
    #: ATE of the robots' keyframe poses against the world's camera poses (m, no alignment).
    ate_distributed_m: float
    ate_centralized_m: float
    ate_per_robot_m: dict[int, float]
    are_distributed_deg: float
    #: Robot 0's dead reckoning from its true first pose, for scale (m).
    ate_robot0_odometry_m: float
    #: Every observed object point placed by the merged map against placed by the true poses (RMS, m).
    object_points_rms_m: float
    object_points: int
    live: dict[str, Any] | None
    closures: list[ClosureRecord]
    timings: dict[str, float]
    files: list[str]

    @property
    def solved(self) -> bool:
        return self.outcome in ("converged", "unconverged")

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = finite_json(asdict(self))
        return out


# --- reading the run ------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class RunData:
    """What the merge reads from a finished run."""

    sequence: ConstellationSequence
    #: Each frame's camera pose (camera to world), by frame index.
    poses: tuple[Pose, ...]
    blocks: list[range]
    preset: Preset
    wire_mm: bool
    closures: list[tuple[int, int, int, int, int]]  # query robot, frame, match robot, frame, n_matched


def _camera_poses(seq: ConstellationSequence, trajectory: Trajectory, path: Path) -> tuple[Pose, ...]:
    out = []
    for t in seq.timestamps:
        i = int(np.argmin(np.abs(trajectory.timestamps - t)))
        if abs(trajectory.timestamps[i] - t) > 1e-3:
            raise DatasetError(path, f"no ground-truth pose within 1 ms of frame time {t:.6f}")
        out.append(Pose.from_quaternion(trajectory.positions[i], trajectory.quaternions[i]))
    return tuple(out)


def read_run(run: Path) -> RunData:
    """The run's frames, their true camera poses, the robots' shares, the preset and closures."""
    summary = json.loads((run / "summary.json").read_text(encoding="utf-8"))
    robots = int(summary["swarm"]["robots"])
    preset = Preset(**summary["swarm"]["preset"])
    folder = run / "detections" if (run / "detections").is_dir() else run / "dataset" / "constellations"
    seq = read_constellations(folder, label_names())
    truth = run / "dataset" / "groundtruth.txt"
    detector = summary.get("detector") or {}
    if not truth.is_file() and detector.get("folder"):
        truth = Path(detector["folder"]) / "groundtruth.txt"
    if not truth.is_file():
        raise ConfigError(
            f"{run} has no ground truth (groundtruth.txt): merge needs the synthetic world's poses"
        )
    index = {f: i for i, f in enumerate(seq.frame_ids)}
    blocks = split_frames(len(seq), robots)
    closures = []
    with (run / "loop_closures.csv").open(encoding="utf-8") as f:
        for row in csv.DictReader(f):
            q, m = index[row["query_frame_id"]], index[row["match_frame_id"]]
            qr, mr = int(row["query_robot"]), int(row["match_robot"])
            if q not in blocks[qr] or m not in blocks[mr]:
                raise DatasetError(run / "loop_closures.csv", f"frames of {row} are not the robots' shares")
            closures.append((qr, q, mr, m, int(row["n_matched"])))
    wire_mm = summary["swarm"].get("wire_positions", "mm") == "mm"
    return RunData(seq, _camera_poses(seq, read_trajectory(truth), truth), blocks, preset, wire_mm, closures)


def _on_the_wire(c: Constellation, n_labels: int) -> Constellation:
    return constellation_from_proto(constellation_to_proto(c, 0, 0), n_labels)


# --- the team's graph -------------------------------------------------------------------


def _information(sigma_rotation_rad: float, sigma_translation_m: float) -> np.ndarray:
    return np.diag([sigma_rotation_rad**-2] * 3 + [sigma_translation_m**-2] * 3)


def _relative_error(measured: Pose, truth: Pose) -> tuple[float, float]:
    delta = truth.inverse().compose(measured)
    return math.degrees(float(np.linalg.norm(so3_log(delta.rotation)))), float(
        np.linalg.norm(delta.translation)
    )


def align_closures(data: RunData, settings: MergeSettings) -> list[tuple[ClosureRecord, Edge | None]]:
    """Each inter-robot closure's relative pose from its matched objects, and its edge when aligned."""
    seq, n_labels = data.sequence, data.sequence.n_labels
    records: list[tuple[ClosureRecord, Edge | None]] = []
    seen: set[tuple[int, int]] = set()
    for qr, q, mr, m, n_matched in data.closures:
        if qr == mr or (min(q, m), max(q, m)) in seen:
            continue
        seen.add((min(q, m), max(q, m)))
        qf, mf = q - data.blocks[qr].start, m - data.blocks[mr].start
        query, match = seq.constellations[q], seq.constellations[m]
        if data.wire_mm:
            query, match = _on_the_wire(query, n_labels), _on_the_wire(match, n_labels)
        found = verify(query, (qr, qf), mr, [(mf, match)], n_labels, data.preset)
        base = ClosureRecord(qr, qf, mr, mf, n_matched, "not_verified")
        if not found or len(found[0].pairs) != n_matched:
            records.append((base, None))
            continue
        pairs = found[0].pairs
        if len(pairs) < settings.min_inliers:
            records.append((replace(base, status="too_few_pairs"), None))
            continue
        try:
            fit = ransac_rigid(
                query.positions[pairs[:, 0]],
                match.positions[pairs[:, 1]],
                threshold=settings.ransac_threshold_m,
                min_inliers=settings.min_inliers,
            )
        except AlignmentError:
            records.append((replace(base, status="alignment_failed"), None))
            continue
        inliers = query.positions[pairs[fit.inliers, 0]]
        spread = float(np.sqrt(np.mean(np.sum((inliers - inliers.mean(axis=0)) ** 2, axis=1))))
        # The fit's own residual underestimates the noise (6 parameters fitted to 3n coordinates).
        n = fit.inlier_count
        sigma_t = max(fit.rms * math.sqrt(3 * n / (3 * n - 6)), 0.05)
        sigma_r = min(max(sigma_t / max(spread, 1e-3), math.radians(0.5)), math.radians(20.0))
        truth = data.poses[m].inverse().compose(data.poses[q])
        rot_err, trans_err = _relative_error(fit.pose, truth)
        edge = fit.edge(pose_key(qr, qf), pose_key(mr, mf), _information(sigma_r, sigma_t))
        record = replace(
            base,
            status="aligned",
            inliers=fit.inlier_count,
            rms_m=fit.rms,
            rotation_error_deg=rot_err,
            translation_error_m=trans_err,
        )
        records.append((record, edge))
    return records


def build_team_graph(
    data: RunData, settings: MergeSettings, constraints: Sequence[Edge]
) -> tuple[PoseGraph, dict[int, Pose], dict[int, int]]:
    """Keyframe chains with simulated odometry, and the inter-robot ``constraints``; the graph,
    each key's true pose and each key's frame index."""
    rng = np.random.default_rng(settings.noise_seed)
    sigma_r, sigma_t = math.radians(settings.odometry_sigma_deg), settings.odometry_sigma_m
    info = _information(sigma_r, sigma_t)
    used = {k for e in constraints for k in e.keys}
    poses: dict[int, Pose] = {}
    truth: dict[int, Pose] = {}
    frames: dict[int, int] = {}
    edges: list[Edge] = []
    for robot, block in enumerate(data.blocks):
        local = [
            i for i in range(len(block)) if i % settings.keyframe_every == 0 or pose_key(robot, i) in used
        ]
        previous: tuple[int, Pose] | None = None
        for i in local:
            key, frame = pose_key(robot, i), block.start + i
            truth[key], frames[key] = data.poses[frame], frame
            if previous is None:
                poses[key] = data.poses[frame] if robot == 0 else Pose.identity()
            else:
                k0, estimate = previous
                exact = data.poses[frames[k0]].inverse().compose(data.poses[frame])
                noisy = Pose(
                    exact.rotation @ so3_exp(rng.normal(0.0, sigma_r, 3)),
                    exact.translation + rng.normal(0.0, sigma_t, 3),
                )
                edges.append(Edge(k0, key, noisy, info))
                poses[key] = estimate.compose(noisy)
            previous = (key, poses[key])
    return PoseGraph(poses, (*edges, *constraints)), truth, frames


def _object_points(
    data: RunData, frames: Mapping[int, int], estimate: Mapping[int, Pose], truth: Mapping[int, Pose]
) -> tuple[float, int]:
    squared, n = 0.0, 0
    for key, frame in frames.items():
        points = data.sequence.constellations[frame].positions
        if key in estimate and len(points):
            d = estimate[key].transform(points) - truth[key].transform(points)
            squared += float(np.sum(d**2))
            n += len(points)
    return (math.sqrt(squared / n) if n else math.nan), n


def _ate(estimate: Mapping[int, Pose], truth: Mapping[int, Pose], keys: Sequence[int]) -> float:
    keys = [k for k in keys if k in estimate]
    if not keys:
        return math.nan
    return math.sqrt(
        float(np.mean([np.sum((estimate[k].translation - truth[k].translation) ** 2) for k in keys]))
    )


def _are(estimate: Mapping[int, Pose], truth: Mapping[int, Pose], keys: Sequence[int]) -> float:
    keys = [k for k in keys if k in estimate]
    angles = [float(np.sum(so3_log(truth[k].rotation.T @ estimate[k].rotation) ** 2)) for k in keys]
    return math.degrees(math.sqrt(float(np.mean(angles)))) if angles else math.nan


def merge_run(settings: MergeSettings, swarm_at: Callable[[Path], Deployment] | None = None) -> MergeSummary:
    """Build the robots' graphs from the run, solve, compare with the world; writes under
    ``settings.out``. A live solve runs its team on ``swarm_at(folder)``, the deployment of
    the swarm whose report goes to ``folder``."""
    if settings.live and swarm_at is None:
        raise ConfigError("a live merge solves with a team of slam services: give it a deployment (swarm_at)")
    t_start = time.perf_counter()
    out = settings.out
    out.mkdir(parents=True, exist_ok=True)
    data = read_run(settings.run)
    aligned = align_closures(data, settings)
    constraints = [e for _, e in aligned if e is not None]
    graph, truth, frames = build_team_graph(data, settings, constraints)
    timings = {"prepare_s": time.perf_counter() - t_start}
    kept_ids = {id(e) for e in constraints}
    if settings.reject != "none" and constraints:
        t0 = time.perf_counter()
        kept_ids = {id(e) for e in pcm(graph).kept}
        timings["pcm_s"] = time.perf_counter() - t0
        if settings.reject == "pcm+gnc":
            t0 = time.perf_counter()
            kept_graph = graph.with_edges(
                e for e in graph.edges if not graph.is_separator(e) or id(e) in kept_ids
            )
            kept_ids -= {id(e) for e in gnc(kept_graph).rejected}
            timings["gnc_s"] = time.perf_counter() - t0
    by_pair: dict[tuple[int, int], list[int]] = {}
    for e in constraints:
        if id(e) in kept_ids:
            pair = tuple(sorted(graph.robot_of(k) for k in e.keys))
            by_pair.setdefault((pair[0], pair[1]), []).append(id(e))
    kept_ids = {i for ids in by_pair.values() if len(ids) >= settings.pair_support for i in ids}
    kept = [e for e in constraints if id(e) in kept_ids]
    records = [replace(r, kept=e is not None and id(e) in kept_ids) for r, e in aligned]
    graph, truth, frames = build_team_graph(data, settings, kept)
    apart = _unlinked(graph)
    if apart:
        raise GraphError(
            f"robots {apart} have no kept constraint linking them to robot 0's map "
            f"({len(constraints)} aligned, {len(kept)} kept); a longer run finds more loop closures"
        )
    folder = out / "graph"
    folder.mkdir(parents=True, exist_ok=True)
    for old in folder.glob("*.g2o"):
        old.unlink()
    for robot in graph.robots:
        write_g2o(
            folder / robot_file_name(robot),
            graph,
            keys=graph.robot_keys(robot),
            edges=graph.robot_edges(robot),
        )
    files = [str(folder)]
    live: LiveSlamSummary | None = None
    t0 = time.perf_counter()
    if settings.live:
        assert swarm_at is not None  # checked above
        live = live_main(
            LiveSlamSettings(
                out=out / "live",
                folder=folder,
                centralized=settings.centralized,
                progress=settings.progress,
                overwrite=True,
                solver=settings.solver,
            ),
            swarm_at(out / "live"),
        )
        outcome = live.outcome
        estimate = _read_estimate(out / "live", graph)
        files.append(str(out / "live"))
    else:
        result = run_dgs(read_robots(folder), settings.solver)
        outcome = "converged" if result.converged else "unconverged"
        estimate = result.poses
    timings["solve_s"] = time.perf_counter() - t0
    solved_graph = read_robots(folder)
    centralized = solve_centralized(
        solved_graph, method=settings.centralized, anchor=solved_graph.anchor_key()
    ).poses
    keys = list(solved_graph.keys)
    odometry0 = list(graph.robot_keys(0))
    rms, n_points = _object_points(data, frames, estimate, truth)
    figure = out / "merged.png"
    plot_maps(
        figure,
        solved_graph,
        {"the world's camera poses": truth, f"merged ({summary_solver(settings)})": estimate},
    )
    files.append(str(figure))
    summary = MergeSummary(
        run=str(settings.run),
        robots=len(data.blocks),
        frames=len(data.sequence),
        keyframes=len(graph.poses),
        closures_inter_robot=sum(1 for c in data.closures if c[0] != c[2]),
        constraints_aligned=len(constraints),
        constraints_right=sum(r.right for r in records if r.status == "aligned"),
        reject=settings.reject,
        constraints_kept=len(kept),
        constraints_kept_right=sum(r.right for r in records if r.kept),
        separators=len(solved_graph.separators()),
        solver=summary_solver(settings),
        outcome=outcome,
        ate_distributed_m=_ate(estimate, truth, keys),
        ate_centralized_m=_ate(centralized, truth, keys),
        ate_per_robot_m={r: _ate(estimate, truth, solved_graph.robot_keys(r)) for r in solved_graph.robots},
        are_distributed_deg=_are(estimate, truth, keys),
        ate_robot0_odometry_m=_ate(graph.poses, truth, odometry0),
        object_points_rms_m=rms,
        object_points=n_points,
        live=live.to_dict() if live is not None else None,
        closures=records,
        timings=timings | {"total_s": time.perf_counter() - t_start},
        files=files,
    )
    (out / SUMMARY_NAME).write_text(json.dumps(summary.to_dict(), indent=2) + "\n", encoding="utf-8")
    return summary


def summary_solver(settings: MergeSettings) -> str:
    return "live slam services" if settings.live else "run_dgs in one process"


def _unlinked(graph: PoseGraph) -> list[int]:
    """Robots no chain of separators links to robot 0."""
    links: dict[int, set[int]] = {r: set() for r in graph.robots}
    for edge in graph.separators():
        a, b = graph.robot_of(edge.source), graph.robot_of(edge.target)
        links[a].add(b)
        links[b].add(a)
    reached, frontier = {0}, [0]
    while frontier:
        for other in links[frontier.pop()] - reached:
            reached.add(other)
            frontier.append(other)
    return sorted(set(graph.robots) - reached)


def read_robots(folder: Path) -> PoseGraph:
    return read_robot_folder(folder).graph


def _read_estimate(live_out: Path, graph: PoseGraph) -> dict[int, Pose]:
    merged = live_out / "merged.g2o"
    if merged.is_file():
        return dict(read_g2o(merged).poses)
    estimate: dict[int, Pose] = {}
    for robot in graph.robots:
        path = live_out / robot_file_name(robot)
        if path.is_file():
            estimate.update({k: p for k, p in read_g2o_vertices(path).items() if k in graph.poses})
    return estimate


def read_g2o_vertices(path: Path) -> dict[int, Pose]:
    return dict(parse_g2o(path).poses)


def format_merge(summary: MergeSummary) -> str:
    """A few lines for a terminal."""
    s = summary
    constraints = (
        f"  {s.closures_inter_robot} verified loop closures between robots -> "
        f"{s.constraints_aligned} aligned ({s.constraints_right} right) -> "
        f"{s.constraints_kept} kept by {s.reject} ({s.constraints_kept_right} right)"
    )
    truth = (
        f"  against the world's truth: ATE {s.ate_distributed_m:.3g} m, ARE {s.are_distributed_deg:.3g} deg"
    )
    baselines = (
        f"    (centralized Gauss-Newton {s.ate_centralized_m:.3g} m; "
        f"robot 0's odometry alone {s.ate_robot0_odometry_m:.3g} m)"
    )
    return "\n".join(
        [
            f"merged map of {s.robots} robots from {s.run}: {s.frames} frames, {s.keyframes} keyframes",
            constraints,
            f"  solved by {s.solver}: {s.outcome}",
            truth,
            baselines,
            f"  object points placed by the merged map: RMS error {s.object_points_rms_m:.3g} m "
            f"({s.object_points} points)",
        ]
    )
