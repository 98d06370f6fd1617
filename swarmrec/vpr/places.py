"""What counts as the same place, and the centralized retrieval metrics.

A *place* is a camera position and viewing direction (the camera's z axis in
the world, TUM convention). Two frames show the same place when

* their cameras are at most ``max_distance_m`` (0.5 m) apart, and
* their viewing directions differ by at most ``max_angle_deg`` (30 deg), and
* they are more than ``exclusion_frames`` (100) frames apart in their sequence
  (frames of the same moment are not a loop closure; the constellation
  protocol of :mod:`swarmrec.evaluation.groundtruth` excludes the same window).

Training uses the first two conditions for positives and a wider margin for
negatives (:data:`TRAIN_NEGATIVE`): a pair between the two is neither.

Retrieval metrics on a set of frames with descriptors (squared L2 distance,
smaller is closer), each frame queried against every *eligible* other frame:

* recall@k: over the queries with at least one true match among their eligible
  frames, the share whose k nearest eligible frames hold a true match;
* AUC: the project's precision-recall protocol
  (:func:`swarmrec.evaluation.pr.precision_recall`): each query's single nearest
  eligible frame, queries walked from the smallest distance up, recall over the
  queries with a true match; the score handed to it is ``4 - d^2`` (unit
  vectors are at most 2 apart, so every eligible pair scores >= 0) and
  ineligible pairs score -1, which that protocol reads as "never a closure".

This module needs only numpy, so ``models/descriptor/train.py`` (torch, no
faiss) measures its model with the same definitions as the runtime.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from swarmrec.core.geometry import quaternion_to_matrix
from swarmrec.errors import ConfigError
from swarmrec.evaluation.pr import PRCurve, precision_recall

__all__ = [
    "TRAIN_NEGATIVE",
    "TRAIN_POSITIVE",
    "PlaceThresholds",
    "RetrievalMetrics",
    "eligible_pairs",
    "pair_distances",
    "retrieval_metrics",
    "same_place",
    "view_directions",
]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.int64]

#: Largest squared L2 distance between unit vectors; ``4 - d^2`` is then a score >= 0.
MAX_SQUARED_DISTANCE = 4.0


@dataclass(frozen=True)
class PlaceThresholds:
    """When two frames show the same place (see the module docstring)."""

    max_distance_m: float = 0.5
    max_angle_deg: float = 30.0
    exclusion_frames: int = 100

    def __post_init__(self) -> None:
        if not (math.isfinite(self.max_distance_m) and self.max_distance_m > 0):
            raise ConfigError(f"max_distance_m must be > 0, got {self.max_distance_m}")
        if not 0 < self.max_angle_deg <= 180:
            raise ConfigError(f"max_angle_deg must be in (0, 180], got {self.max_angle_deg}")
        if self.exclusion_frames < 0:
            raise ConfigError(f"exclusion_frames must be >= 0, got {self.exclusion_frames}")


#: Training positives: the evaluation's own definition of the same place.
TRAIN_POSITIVE = PlaceThresholds(0.5, 30.0, 0)
#: Training negatives: cameras more than 1 m apart or looking more than 60 deg apart. The band
#: between (0.5-1 m, 30-60 deg) is ignored: such views share much of the scene, and pushing them
#: apart would fight the positives.
TRAIN_NEGATIVE = PlaceThresholds(1.0, 60.0, 0)


def view_directions(quaternions: npt.ArrayLike) -> FloatArray:
    """Unit viewing directions (the camera's z axis in the world) of TUM quaternions ``(N, 4)``."""
    directions: FloatArray = quaternion_to_matrix(quaternions)[..., :, 2]
    return directions


def pair_distances(positions: FloatArray, directions: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Camera distances (m) and viewing-direction angles (deg) between every two frames."""
    diff = positions[:, None, :] - positions[None, :, :]
    distance = np.sqrt((diff * diff).sum(-1))
    cosine = np.clip(directions @ directions.T, -1.0, 1.0)
    return distance, np.degrees(np.arccos(cosine))


def same_place(
    positions: FloatArray,
    directions: FloatArray,
    frames: IntArray,
    thresholds: PlaceThresholds = PlaceThresholds(),  # frozen, so one shared default is safe
) -> BoolArray:
    """``(N, N)`` true loop closures of N frames of ONE sequence (``frames``: their indices in it)."""
    distance, angle = pair_distances(positions, directions)
    apart = np.abs(frames[:, None] - frames[None, :]) > thresholds.exclusion_frames
    closures: BoolArray = (
        (distance <= thresholds.max_distance_m) & (angle <= thresholds.max_angle_deg) & apart
    )
    return closures


def eligible_pairs(frames: IntArray, exclusion_frames: int) -> BoolArray:
    """``(N, N)``: the pairs of one sequence more than ``exclusion_frames`` apart (never i with i)."""
    eligible: BoolArray = np.abs(frames[:, None] - frames[None, :]) > exclusion_frames
    return eligible


@dataclass(frozen=True)
class RetrievalMetrics:
    """Recall@1, recall@5 and AUC of one set of descriptors (see the module docstring)."""

    recall_at_1: float
    recall_at_5: float
    auc: float
    queries: int
    queries_with_match: int


def _squared_distances(descriptors: npt.NDArray[np.floating]) -> FloatArray:
    x = np.asarray(descriptors, np.float64)
    norms = (x * x).sum(1)
    squared: FloatArray = np.maximum(norms[:, None] + norms[None, :] - 2.0 * (x @ x.T), 0.0)
    return squared


def retrieval_metrics(
    descriptors: npt.NDArray[np.floating], closures: BoolArray, eligible: BoolArray
) -> tuple[RetrievalMetrics, PRCurve]:
    """Recall@1/5 and the AUC of unit ``descriptors (N, d)`` given the true closures and the
    eligible pairs (both ``(N, N)``; a closure outside ``eligible`` does not count)."""
    n = len(descriptors)
    if closures.shape != (n, n) or eligible.shape != (n, n):
        raise ConfigError(f"closures and eligible must be ({n}, {n}), got {closures.shape}, {eligible.shape}")
    squared = _squared_distances(descriptors)
    truth = closures & eligible
    ranked = np.where(eligible, squared, np.inf)
    order = np.argsort(ranked, axis=1, kind="stable")[:, :5]
    rows = np.arange(n)[:, None]
    # A neighbour past the eligible ones (distance inf) is never a hit: truth is False there.
    hits = truth[rows, order] & np.isfinite(ranked[rows, order])
    has_match = truth.any(axis=1)
    count = int(has_match.sum())
    recall_1 = float(hits[has_match, :1].any(axis=1).mean()) if count else 0.0
    recall_5 = float(hits[has_match, :5].any(axis=1).mean()) if count else 0.0
    scores = np.where(eligible, MAX_SQUARED_DISTANCE - squared, -1.0)
    curve = precision_recall(scores, truth)
    return RetrievalMetrics(recall_1, recall_5, curve.auc, n, count), curve
