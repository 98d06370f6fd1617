"""The offline evaluation: score a dataset the way the constellation paper
did, centralized and/or decentralized with N robots, and report PR/AUC
against ground truth, the byte model and the load per range holder.

``main(settings)`` does the work and returns the summary; the CLI only parses
arguments into :class:`EvaluationSettings`. Output files are described in
docs/output-format.md.
"""

from __future__ import annotations

import csv
import json
import logging
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from tqdm import tqdm

from swarmrec.core.association import build_table
from swarmrec.core.presets import get_preset
from swarmrec.core.types import ConstellationSequence
from swarmrec.datasets.constellations import label_counts
from swarmrec.errors import ConfigError
from swarmrec.evaluation.bandwidth import holder_load, paper_byte_model
from swarmrec.evaluation.groundtruth import Rules, ground_truth
from swarmrec.evaluation.plots import plot_holder_load, plot_pr, plot_similarity
from swarmrec.evaluation.pr import PRCurve, precision_recall
from swarmrec.evaluation.scoring import (
    ScoreMatrix,
    label_frequency_prior,
    score_centralized,
    score_decentralized,
    split_frames,
)
from swarmrec.evaluation.source import DatasetSource, load_dataset

__all__ = ["EvaluationSettings", "EvaluationSummary", "ModeResult", "main"]

log = logging.getLogger(__name__)

Mode = Literal["centralized", "decentralized", "both"]

#: Above this many frames the dense N x N protocol would need several GB.
MAX_DENSE_FRAMES = 12_000


@dataclass(frozen=True)
class EvaluationSettings:
    """Everything one evaluation needs; validated on construction."""

    dataset: str = "synthetic"
    seed: int = 0
    frames: int | None = None
    labels: Path | None = None
    groundtruth: Path | None = None
    gt_rules: Rules = "none"
    mode: Mode = "both"
    robots: int = 10
    preset: str = "paper"
    out: Path = Path("runs/evaluate")
    plots: bool = True
    progress: bool = True
    preset_overrides: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.mode not in ("centralized", "decentralized", "both"):
            raise ConfigError(f"mode must be centralized, decentralized or both, got {self.mode!r}")
        if self.robots < 1:
            raise ConfigError(f"robots must be >= 1, got {self.robots}")
        if self.frames is not None and self.frames < 1:
            raise ConfigError(f"frames must be >= 1, got {self.frames}")
        if self.gt_rules not in ("none", "tum-fr3-office"):
            raise ConfigError(f"gt_rules must be none or tum-fr3-office, got {self.gt_rules!r}")
        get_preset(self.preset)  # fails early with the list of known presets

    @property
    def source(self) -> DatasetSource:
        return DatasetSource(self.dataset, self.seed, self.frames, self.labels, self.groundtruth)


@contextmanager
def _bar(enabled: bool, total: int, desc: str) -> Iterator[Any]:
    with tqdm(total=total, desc=desc, unit="frame", disable=not enabled, leave=False) as bar:
        yield bar


def _write_scores(path: Path, matrix: ScoreMatrix, seq: ConstellationSequence, robots: int) -> None:
    owner = np.zeros(len(seq), np.int64)
    for r, block in enumerate(split_frames(len(seq), robots)):
        owner[block.start : block.stop] = r
    keep = matrix.outside_exclusion()
    np.savez_compressed(
        path,
        frame_i=matrix.pairs_i[keep].astype(np.uint32),
        frame_j=matrix.pairs_j[keep].astype(np.uint32),
        score=matrix.scores[keep],
        frame_ids=np.array(seq.frame_ids),
        robot=owner,
        ignored=matrix.ignored,
        exclusion=np.array(matrix.exclusion),
    )


def _write_best(path: Path, seq: ConstellationSequence, dense: np.ndarray, curve: PRCurve | None) -> None:
    best = np.argmax(dense, axis=1)
    with path.open("w", newline="", encoding="utf-8") as f:
        out = csv.writer(f)
        out.writerow(["frame", "frame_id", "best_frame", "best_frame_id", "score", "true_closure"])
        for i, j in enumerate(best.tolist()):
            truth = "" if curve is None else int(curve.true_positive[i])
            out.writerow([i, seq.frame_ids[i], j, seq.frame_ids[j], f"{dense[i, j]:.6f}", truth])


@dataclass
class EvaluatedDataset:
    name: str
    source: str
    frames: int
    labels: int
    ignored_frames: int
    skipped: dict[str, int]
    groundtruth: bool
    frames_far_from_a_pose: int | None = None
    pose_note: str | None = None
    groundtruth_note: str | None = None


@dataclass
class ModeResult:
    """One mode's scores (centralized, or decentralized with N robots)."""

    checked_pairs: int
    positive_pairs: int
    auc: float | None = None
    frames_with_true_closure: int | None = None


@dataclass
class Bandwidth:
    paper_byte_model_per_query: dict[str, Any]
    holder_load: dict[str, Any]


@dataclass
class EvaluationSummary:
    """What an evaluation reports; ``summary.json`` holds :meth:`to_dict`."""

    dataset: EvaluatedDataset
    preset: dict[str, Any]
    results: dict[str, ModeResult] = field(default_factory=dict)
    bandwidth: Bandwidth | None = None
    timings: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready, optional parts absent from the run left out."""
        out: dict[str, Any] = _drop_none(asdict(self))
        return out


def _drop_none(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _drop_none(v) for k, v in value.items() if v is not None}
    return value


def main(settings: EvaluationSettings) -> EvaluationSummary:
    """Run the evaluation, write its files under ``settings.out``, return the summary."""
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    data = load_dataset(settings.source)
    seq, trajectory = data.sequence, data.trajectory
    timings["load_s"] = time.perf_counter() - t0
    if len(seq) > MAX_DENSE_FRAMES:
        raise ConfigError(
            f"{len(seq)} frames: the paper's protocol keeps an N x N matrix; use --frames to "
            f"evaluate at most {MAX_DENSE_FRAMES}"
        )
    preset = get_preset(settings.preset).with_(**settings.preset_overrides)
    out = settings.out
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    table = build_table(seq.constellations, seq.n_labels)
    timings["prepare_s"] = time.perf_counter() - t0
    counts = label_counts(seq.constellations, seq.n_labels)
    summary = EvaluationSummary(
        dataset=EvaluatedDataset(
            name=seq.name,
            source=settings.dataset,
            frames=len(seq),
            labels=seq.n_labels,
            ignored_frames=int(np.count_nonzero(np.diff(table.offsets) < preset.min_objects)),
            skipped=dict(seq.skipped),
            groundtruth=trajectory is not None,
        ),
        preset=asdict(preset),
    )
    gt = None
    if trajectory is not None:
        t0 = time.perf_counter()
        gt = ground_truth(seq, trajectory, exclusion=preset.exclusion, rules=settings.gt_rules)
        timings["groundtruth_s"] = time.perf_counter() - t0
        summary.dataset.frames_far_from_a_pose = int(gt.poses.far.size)
        if gt.poses.far.size:
            note = gt.poses.describe()
            summary.dataset.pose_note = note
            log.warning("ground truth: %s", note)
    else:
        summary.dataset.groundtruth_note = (
            "no trajectory: pair scores are written but precision-recall needs --groundtruth"
        )
    curves: dict[str, PRCurve] = {}
    runs: list[tuple[str, ScoreMatrix, int]] = []
    if settings.mode in ("centralized", "both"):
        t0 = time.perf_counter()
        with _bar(settings.progress, len(seq), "centralized") as bar:
            matrix = score_centralized(seq, preset, table=table, progress=bar.update)
        timings["centralized_s"] = time.perf_counter() - t0
        runs.append(("centralized", matrix, 1))
    if settings.mode in ("decentralized", "both"):
        load_prior = None
        if preset.ranges == "balanced":
            load_prior = label_frequency_prior(table)
        t0 = time.perf_counter()
        steps = max(len(split_frames(len(seq), settings.robots)[0]) - 1, 0)
        with _bar(settings.progress, steps, f"decentralized x{settings.robots}") as bar:
            run = score_decentralized(
                seq,
                settings.robots,
                preset,
                table=table,
                label_load=load_prior,
                progress=bar.update,
            )
        timings["decentralized_s"] = time.perf_counter() - t0
        runs.append((f"decentralized_{settings.robots}", run.matrix, settings.robots))
        load = holder_load(run)
        summary.bandwidth = Bandwidth(paper_byte_model(run, preset.n_fq).to_dict(), load.to_dict())
        if settings.plots:
            plot_holder_load(load, counts, seq.label_names, out / "holder_load.png")
    for name, matrix, robots in runs:
        dense = matrix.dense()
        keep = matrix.outside_exclusion()
        result = ModeResult(
            checked_pairs=int(np.count_nonzero(keep)),
            positive_pairs=int(np.count_nonzero(matrix.scores[keep] > 0)),
        )
        curve = None
        if gt is not None:
            curve = precision_recall(dense, gt.closures)
            curves[name] = curve
            result.auc, result.frames_with_true_closure = curve.auc, curve.relevant
        summary.results[name] = result
        _write_scores(out / f"scores_{name}.npz", matrix, seq, robots)
        _write_best(out / f"best_matches_{name}.csv", seq, dense, curve)
        if settings.plots:
            starts = [b.start for b in split_frames(len(seq), robots)] if robots > 1 else []
            plot_similarity(
                dense,
                f"{seq.name}: {name.replace('_', ' ')} robots",
                out / f"similarity_{name}.png",
                robot_starts=starts,
            )
    if settings.plots and curves:
        plot_pr(curves, out / "precision_recall.png")
    summary.timings = timings
    (out / "summary.json").write_text(json.dumps(summary.to_dict(), indent=2, default=_json_default) + "\n")
    return summary


def _json_default(value: object) -> object:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
