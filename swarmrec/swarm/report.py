"""The swarm run's report: pair scores, accuracy, bytes and load, measured.

Bytes per query and the shard load come from the services' Prometheus
metrics as scraped at the end of the run, not from a formula: ``bytes`` sums
the payload bytes every service counted as sent between robots
(``swarmrec_message_bytes_sent_total{scope="swarm"}``). Output files are
described in docs/swarm-report.md.
"""

from __future__ import annotations

import csv
import json
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from swarmrec.core.presets import Preset
from swarmrec.core.types import ConstellationSequence, Trajectory
from swarmrec.evaluation.bandwidth import HolderLoad
from swarmrec.evaluation.scoring import ScoreMatrix, decentralized_marks
from swarmrec.services.config import ServiceSettings
from swarmrec.swarm.scrape import Scrape
from swarmrec.wire import messages as pb

if TYPE_CHECKING:
    from swarmrec.swarm.job import Replay, SwarmSettings

__all__ = ["pair_matrix", "write_report"]


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


def _compare_offline(
    matrix: ScoreMatrix,
    wire_seq: ConstellationSequence,
    robots: int,
    preset: Preset,
    bounds: npt.NDArray[np.int64],
) -> tuple[dict[str, Any], Any]:
    from swarmrec.evaluation.scoring import score_decentralized

    run = score_decentralized(wire_seq, robots, preset, bounds=bounds)
    ours, theirs = _positive(matrix), _positive(run.matrix)
    differ = sum(1 for k in ours.keys() & theirs.keys() if ours[k] != theirs[k])
    only_swarm, only_offline = len(ours.keys() - theirs.keys()), len(theirs.keys() - ours.keys())
    result = {
        "identical": differ == 0 and only_swarm == 0 and only_offline == 0,
        "positive_pairs_swarm": len(ours),
        "positive_pairs_offline": len(theirs),
        "scores_differ": differ,
        "only_in_swarm": only_swarm,
        "only_offline": only_offline,
    }
    return result, run


def _bytes(metrics: Scrape, n_queries: int, n_slots: int) -> dict[str, Any]:
    by_type = metrics.by_label("swarmrec_message_bytes_sent_total", "message", scope="swarm")
    msgs = metrics.by_label("swarmrec_messages_sent_total", "message", scope="swarm")
    total = sum(by_type.values())
    return {
        "between_robots_total": total,
        "per_query": total / n_queries if n_queries else 0.0,
        "per_frame": total / n_slots if n_slots else 0.0,
        "per_query_by_message": {k: v / n_queries for k, v in sorted(by_type.items())} if n_queries else {},
        "messages_per_query": {k: v / n_queries for k, v in sorted(msgs.items())} if n_queries else {},
        "within_robot_total": metrics.total("swarmrec_message_bytes_sent_total", scope="robot"),
        "to_clients_total": metrics.total("swarmrec_message_bytes_sent_total", scope="client"),
        "note": (
            "protobuf payload bytes sent between robots, summed from every service's "
            "swarmrec_message_bytes_sent_total{scope='swarm'}; per_query divides by the frames "
            "that queried, per_frame by every (robot, step) slot as the paper's byte model averages"
        ),
    }


def _detector_figures(metrics: Scrape) -> dict[str, Any]:
    """What the rgbd detectors counted: frames by outcome, skips, dropped boxes, objects, stage times."""
    by_outcome = metrics.by_label("swarmrec_detector_frames_total", "outcome")
    outcomes = {k: int(v) for k, v in sorted(by_outcome.items())}
    made = outcomes.get("detected", 0) + outcomes.get("no_objects", 0)
    objects = metrics.total("swarmrec_detector_objects_total")
    sums = metrics.by_label("swarmrec_detector_stage_seconds_sum", "stage")
    counts = metrics.by_label("swarmrec_detector_stage_seconds_count", "stage")
    return {
        "frames": sum(outcomes.values()),
        "frames_by_outcome": outcomes,
        "skipped": {k: v for k, v in outcomes.items() if k not in ("detected", "no_objects")},
        "boxes_dropped": {
            k: int(v) for k, v in metrics.by_label("swarmrec_detector_boxes_dropped_total", "reason").items()
        },
        "objects": int(objects),
        "objects_per_frame": objects / made if made else 0.0,
        "stage_ms_mean": {k: 1e3 * sums[k] / counts[k] for k in sorted(sums) if counts.get(k)},
        "note": "scraped from the detectors' swarmrec_detector_* metrics; objects_per_frame is over "
        "the frames a constellation was made of (detected or no_objects)",
    }


def write_report(
    settings: SwarmSettings,
    *,
    seq: ConstellationSequence,
    wire_seq: ConstellationSequence,
    trajectory: Trajectory | None,
    preset: Preset,
    bounds: npt.NDArray[np.int64],
    blocks: list[range],
    replay: Replay,
    metrics: Scrape,
    closures: list[pb.LoopClosure],
    exit_codes: dict[str, int],
    timings: dict[str, float],
    deployment: str = "local processes",
    detector: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Write the report files under ``settings.out`` and return the summary.

    ``detector`` (a run from pixels: the model, threshold, camera) is reported
    with the detectors' scraped figures under ``summary["detector"]``.
    """
    out = settings.out
    matrix, conflicts = pair_matrix(replay.reports, wire_seq, blocks, preset)
    queried = [r for r in replay.reports if r.queried]
    n_slots = settings.robots * max((len(b) for b in blocks), default=0)
    shard_load = metrics.per_service("swarmrec_shard_partial_queries_total", "index-shard")
    loads = [int(shard_load.get(r, 0)) for r in range(settings.robots)]
    mean_load = float(np.mean(loads)) if loads else 0.0
    missing_by_robot: dict[str, int] = {}
    for r, _t in replay.missing:
        missing_by_robot[str(r)] = missing_by_robot.get(str(r), 0) + 1
    summary: dict[str, Any] = {
        "dataset": {
            "name": seq.name,
            "source": settings.dataset,
            "frames": len(seq),
            "labels": seq.n_labels,
            "groundtruth": trajectory is not None,
        },
        "swarm": {
            "robots": settings.robots,
            "pace": settings.pace,
            "preset": asdict(preset),
            "label_bounds": [int(b) for b in bounds],
            "deployment": deployment,
            "processes": len(exit_codes),
        },
        "queries": {
            "frames_replayed": len(replay.reports),
            "queried": len(queried),
            "missing_slots": len(replay.missing),
            "missing_by_robot": missing_by_robot,
            "failed_shard_requests": sum(len(r.failed_shard_robot_ids) for r in replay.reports),
            "failed_verifier_requests": sum(len(r.failed_verifier_robot_ids) for r in replay.reports),
            "errors": replay.errors[:50],
            "latency_ms": {k: v / 1e3 for k, v in _pct([r.duration_us for r in queried]).items()},
            "step_latency_ms": {k: v * 1e3 for k, v in _pct(replay.step_seconds).items()},
        },
        "bytes": _bytes(metrics, len(queried), n_slots),
        "shard_load": {
            "partial_queries": loads,
            "balance_ratio": float(max(loads) / mean_load) if mean_load > 0 else 0.0,
            "note": "partial queries served per index shard (swarmrec_shard_partial_queries_total); "
            "balance_ratio is the busiest shard over the mean",
        },
        "rejected_requests": metrics.total("swarmrec_rejected_requests_total"),
        "peer_failures": metrics.by_label("swarmrec_peer_failures_total", "reason"),
        "loop_closures": {
            "count": len(closures),
            "scraped_total": metrics.total("swarmrec_loop_closures_total"),
            "min_score": ServiceSettings().loop_closure_min_score,
        },
        "pairs": {"checked_positive": int(np.count_nonzero(matrix.scores > 0)), "conflicting": conflicts},
        "scrape_failed": metrics.failed,
        "exit_codes": exit_codes,
        "timings": timings,
    }
    if detector is not None:
        summary["detector"] = detector | _detector_figures(metrics)
    offline_run = None
    if settings.check_offline and settings.lockstep and not replay.missing:
        summary["offline_check"], offline_run = _compare_offline(
            matrix, wire_seq, settings.robots, preset, bounds
        )
    dense = matrix.dense()
    curves = {}
    if trajectory is not None:
        from swarmrec.evaluation.groundtruth import ground_truth
        from swarmrec.evaluation.pr import precision_recall

        gt = ground_truth(wire_seq, trajectory, exclusion=preset.exclusion)
        curves[f"swarm x{settings.robots}"] = precision_recall(dense, gt.closures)
        summary["auc"] = curves[f"swarm x{settings.robots}"].auc
        truth = gt.closures
    else:
        truth = None
    _write_pairs(out / "pairs.csv", matrix, wire_seq)
    _write_closures(out / "loop_closures.csv", closures, blocks, seq, truth)
    if settings.plots:
        _plots(settings, summary, dense, curves, wire_seq, bounds, loads, offline_run)
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
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
            g = blocks[c.query_robot_id].start + c.query_frame_index
            h = blocks[c.match_robot_id].start + c.match_frame_index
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
    settings: SwarmSettings,
    summary: dict[str, Any],
    dense: Any,
    curves: dict[str, Any],
    seq: ConstellationSequence,
    bounds: Any,
    loads: list[int],
    offline_run: Any,
) -> None:
    from swarmrec.datasets.constellations import label_counts
    from swarmrec.evaluation.plots import plot_bytes, plot_holder_load, plot_pr, plot_similarity

    out = settings.out
    plot_similarity(dense, f"{seq.name}: swarm of {settings.robots} robots", out / "similarity.png")
    if curves:
        plot_pr(curves, out / "precision_recall.png")
    counts = label_counts(seq.constellations, seq.n_labels)
    holder = np.repeat(np.arange(len(loads)), np.diff(bounds))
    labels = np.bincount(holder, weights=(counts > 0), minlength=len(loads)).astype(int).tolist()
    objects = np.bincount(holder, weights=counts, minlength=len(loads)).astype(int).tolist()
    load = HolderLoad(bounds=[int(b) for b in bounds], partial_queries=loads, labels=labels, objects=objects)
    plot_holder_load(load, counts, seq.label_names, out / "shard_load.png")
    plot_bytes(summary["bytes"]["per_query_by_message"], out / "bytes_per_query.png")
