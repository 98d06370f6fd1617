"""Detection quality: average precision per class at one IoU threshold, and its mean (mAP).

The PASCAL VOC rule (the devkit of 2010 onwards), which COCO's mAP@0.5 follows
closely:

* A detection is compared with the ground-truth boxes of its own class in its own
  image; it goes to the one it overlaps most (intersection over union). Reaching
  ``iou_threshold`` (0.5) with a box not yet taken makes it a true positive and
  takes the box; reaching it with a box already taken by a better-scored detection
  makes it a false positive (a duplicate), and so does overlapping no box enough.
* A ground-truth box marked ``ignore`` (VOC's "difficult": too small or too hidden
  to demand) neither counts as an object to find nor makes a detection of it wrong:
  a detection whose best box is an ignored one is left out of the count.
* Per class, the detections of all images are ranked by score; precision and recall
  along the ranking give the precision-recall curve, precision is made
  non-increasing from the right and AP is the area under that curve at every
  recall step ("all-point interpolation", not VOC 2007's 11 points).
* mAP is the mean AP of the classes that have at least one ground-truth box that
  is not ignored. A class with boxes and no detection has AP 0; a class with
  detections and no boxes is not in the mean.

Boxes are ``x1 y1 x2 y2`` in continuous pixel coordinates (pixel ``u`` covers
``[u, u + 1)``, so a box's width is ``x2 - x1``), as the detector and the renderer
give them.

>>> truth = GroundTruth(np.array([[0.0, 0.0, 10.0, 10.0]]), np.array([3]))
>>> found = Predictions(np.array([[1.0, 0.0, 10.0, 10.0]]), np.array([0.9]), np.array([3]))
>>> evaluate_detections([found], [truth]).mean_ap
1.0
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from swarmrec.errors import ConfigError

__all__ = [
    "ClassAP",
    "DetectionEvaluation",
    "GroundTruth",
    "OperatingPoint",
    "Outcome",
    "Predictions",
    "average_precision",
    "box_iou",
    "evaluate_detections",
    "match_frame",
]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]


class Outcome:
    """What :func:`match_frame` makes of each detection."""

    FALSE_POSITIVE = 0
    TRUE_POSITIVE = 1
    #: Its best box is an ignored one: neither right nor wrong.
    IGNORED = -1


def _boxes(value: npt.ArrayLike, what: str) -> FloatArray:
    boxes = np.asarray(value, dtype=np.float64)
    if boxes.size == 0:
        return np.zeros((0, 4), np.float64)
    if boxes.ndim != 2 or boxes.shape[1] != 4:
        raise ValueError(f"{what} must be an (n, 4) array of x1 y1 x2 y2, got shape {boxes.shape}")
    return boxes


def _vector(value: npt.ArrayLike, n: int, dtype: type[np.generic], what: str) -> npt.NDArray[np.generic]:
    array = np.asarray(value, dtype=dtype).reshape(-1)
    if array.shape[0] != n:
        raise ValueError(f"{what} has {array.shape[0]} entries for {n} boxes")
    return array


@dataclass(frozen=True, eq=False)
class GroundTruth:
    """The true objects of one image: boxes, class ids, and which ones are ignored (all kept if None)."""

    boxes: FloatArray
    class_ids: IntArray
    ignore: BoolArray | None = None

    def __post_init__(self) -> None:
        boxes = _boxes(self.boxes, "ground-truth boxes")
        n = boxes.shape[0]
        ignore = np.zeros(n, np.bool_) if self.ignore is None else self.ignore
        object.__setattr__(self, "boxes", boxes)
        object.__setattr__(self, "class_ids", _vector(self.class_ids, n, np.int64, "class_ids"))
        object.__setattr__(self, "ignore", _vector(ignore, n, np.bool_, "ignore"))

    def __len__(self) -> int:
        return int(self.boxes.shape[0])

    @property
    def kept(self) -> BoolArray:
        """The boxes that count as objects to find."""
        assert self.ignore is not None  # set in __post_init__
        return ~self.ignore


@dataclass(frozen=True, eq=False)
class Predictions:
    """The detections of one image: boxes, scores and class ids, in any order."""

    boxes: FloatArray
    scores: FloatArray
    class_ids: IntArray

    def __post_init__(self) -> None:
        boxes = _boxes(self.boxes, "detected boxes")
        n = boxes.shape[0]
        object.__setattr__(self, "boxes", boxes)
        object.__setattr__(self, "scores", _vector(self.scores, n, np.float64, "scores"))
        object.__setattr__(self, "class_ids", _vector(self.class_ids, n, np.int64, "class_ids"))

    def __len__(self) -> int:
        return int(self.boxes.shape[0])

    @classmethod
    def empty(cls) -> Predictions:
        return cls(np.zeros((0, 4)), np.zeros(0), np.zeros(0, np.int64))


def box_iou(a: npt.ArrayLike, b: npt.ArrayLike) -> FloatArray:
    """Intersection over union of every box of ``a`` (``n x 4``) with every box of ``b`` (``m x 4``).

    A pair whose union is empty (two boxes without area) has IoU 0.
    """
    p, q = _boxes(a, "boxes"), _boxes(b, "boxes")
    lo = np.maximum(p[:, None, :2], q[None, :, :2])
    hi = np.minimum(p[:, None, 2:], q[None, :, 2:])
    inter = np.clip(hi - lo, 0.0, None).prod(axis=2)
    area_p = np.clip(p[:, 2:] - p[:, :2], 0.0, None).prod(axis=1)
    area_q = np.clip(q[:, 2:] - q[:, :2], 0.0, None).prod(axis=1)
    union = area_p[:, None] + area_q[None, :] - inter
    return np.asarray(np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0))


def match_frame(predictions: Predictions, truth: GroundTruth, iou_threshold: float = 0.5) -> IntArray:
    """The :class:`Outcome` of each detection of one image, in the order given.

    Detections are matched class by class, best score first (ties: the order given).
    """
    _check_threshold(iou_threshold)
    outcome = np.full(len(predictions), Outcome.FALSE_POSITIVE, np.int64)
    assert truth.ignore is not None
    for class_id in np.unique(predictions.class_ids):
        dets = np.flatnonzero(predictions.class_ids == class_id)
        gts = np.flatnonzero(truth.class_ids == class_id)
        if gts.size == 0:
            continue
        dets = dets[np.argsort(-predictions.scores[dets], kind="stable")]
        overlaps = box_iou(predictions.boxes[dets], truth.boxes[gts])
        taken = np.zeros(gts.size, np.bool_)
        for row, det in enumerate(dets):
            best = int(np.argmax(overlaps[row]))
            if overlaps[row, best] < iou_threshold:
                continue
            if truth.ignore[gts[best]]:
                outcome[det] = Outcome.IGNORED
            elif not taken[best]:
                taken[best] = True
                outcome[det] = Outcome.TRUE_POSITIVE
    return outcome


def average_precision(recall: npt.ArrayLike, precision: npt.ArrayLike) -> float:
    """Area under a precision-recall curve with all-point interpolation (VOC 2010+).

    ``recall`` and ``precision`` are the values after each detection, best score
    first (recall non-decreasing). Precision at recall ``r`` is taken as the best
    precision at any recall ``>= r``; an empty curve has AP 0.
    """
    rec = np.asarray(recall, dtype=np.float64).reshape(-1)
    prec = np.asarray(precision, dtype=np.float64).reshape(-1)
    if rec.shape != prec.shape:
        raise ValueError(f"recall and precision differ in length: {rec.shape[0]} and {prec.shape[0]}")
    if rec.size == 0:
        return 0.0
    mrec = np.concatenate(([0.0], rec, [1.0]))
    mpre = np.concatenate(([0.0], prec, [0.0]))
    mpre = np.maximum.accumulate(mpre[::-1])[::-1]
    steps = np.flatnonzero(mrec[1:] != mrec[:-1])
    return float(np.sum((mrec[steps + 1] - mrec[steps]) * mpre[steps + 1]))


@dataclass(frozen=True, eq=False)
class ClassAP:
    """One class's result: AP (None without ground truth), counts and its precision-recall curve.

    ``recall[i]`` and ``precision[i]`` hold after the ``i + 1`` best-scored detections
    that were not ignored, whose scores are ``scores[i]``.
    """

    class_id: int
    ap: float | None
    n_truth: int
    n_ignored_truth: int
    n_detections: int
    true_positives: int
    scores: FloatArray = field(repr=False)
    recall: FloatArray = field(repr=False)
    precision: FloatArray = field(repr=False)

    @property
    def max_recall(self) -> float:
        """The share of this class's objects found at any score (0 without ground truth)."""
        return float(self.recall[-1]) if self.recall.size else 0.0


@dataclass(frozen=True)
class OperatingPoint:
    """All classes together at one confidence threshold (detections scoring at least it)."""

    threshold: float
    precision: float
    recall: float
    f1: float
    true_positives: int
    false_positives: int
    ignored: int
    detections_per_frame: float


@dataclass(frozen=True, eq=False)
class DetectionEvaluation:
    """Per-class AP and the mean over the classes with ground truth, at ``iou_threshold``.

    ``scores`` and ``outcomes`` are every detection of every class and image (pooled,
    in no particular order), for operating points across classes.
    """

    iou_threshold: float
    per_class: dict[int, ClassAP]
    n_frames: int
    scores: FloatArray = field(repr=False)
    outcomes: IntArray = field(repr=False)

    @property
    def evaluated_classes(self) -> list[int]:
        """The classes with at least one ground-truth box that is not ignored, ascending."""
        return sorted(c for c, r in self.per_class.items() if r.ap is not None)

    @property
    def mean_ap(self) -> float:
        """The mean AP over :attr:`evaluated_classes` (0 when there are none)."""
        aps = [self.per_class[c].ap for c in self.evaluated_classes]
        return float(np.mean([ap for ap in aps if ap is not None])) if aps else 0.0

    @property
    def n_truth(self) -> int:
        return sum(r.n_truth for r in self.per_class.values())

    def at_threshold(self, threshold: float) -> OperatingPoint:
        """Precision, recall and detections per frame of the detections scoring ``>= threshold``."""
        chosen = self.scores >= threshold
        tp = int(np.sum(self.outcomes[chosen] == Outcome.TRUE_POSITIVE))
        fp = int(np.sum(self.outcomes[chosen] == Outcome.FALSE_POSITIVE))
        ignored = int(np.sum(self.outcomes[chosen] == Outcome.IGNORED))
        precision = tp / (tp + fp) if tp + fp else 1.0
        recall = tp / self.n_truth if self.n_truth else 0.0
        f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
        return OperatingPoint(
            threshold=float(threshold),
            precision=precision,
            recall=recall,
            f1=f1,
            true_positives=tp,
            false_positives=fp,
            ignored=ignored,
            detections_per_frame=(tp + fp + ignored) / max(self.n_frames, 1),
        )

    def best_f1(self, candidates: Iterable[float] | None = None) -> OperatingPoint:
        """The operating point of highest F1 among ``candidates`` (default: 0.01, 0.02, ..., 0.99)."""
        thresholds = np.round(np.arange(1, 100) / 100, 2) if candidates is None else candidates
        points = [self.at_threshold(float(t)) for t in thresholds]
        if not points:
            raise ValueError("no candidate thresholds")
        return max(points, key=lambda p: (p.f1, -p.threshold))


def evaluate_detections(
    predictions: Sequence[Predictions], truths: Sequence[GroundTruth], iou_threshold: float = 0.5
) -> DetectionEvaluation:
    """AP per class over images, ``predictions[i]`` being the detections in the image of ``truths[i]``."""
    _check_threshold(iou_threshold)
    if len(predictions) != len(truths):
        raise ValueError(f"{len(predictions)} images of detections for {len(truths)} of ground truth")
    outcomes = [match_frame(p, t, iou_threshold) for p, t in zip(predictions, truths, strict=True)]
    none = np.zeros(0, np.int64)  # so that no images concatenate to empty arrays
    all_scores = np.concatenate([*(p.scores for p in predictions), np.zeros(0)])
    all_classes = np.concatenate([*(p.class_ids for p in predictions), none])
    all_outcomes = np.concatenate([*outcomes, none])
    truth_classes = np.concatenate([*(t.class_ids[t.kept] for t in truths), none])
    ignored_classes = np.concatenate([*(t.class_ids[~t.kept] for t in truths), none])
    per_class: dict[int, ClassAP] = {}
    for class_id in np.union1d(np.union1d(all_classes, truth_classes), ignored_classes).tolist():
        mine = all_classes == class_id
        n_detections = int(mine.sum())
        counted = mine & (all_outcomes != Outcome.IGNORED)
        scores = all_scores[counted]
        order = np.argsort(-scores, kind="stable")
        hits = (all_outcomes[counted][order] == Outcome.TRUE_POSITIVE).astype(np.float64)
        n_truth = int(np.sum(truth_classes == class_id))
        cum_tp = np.cumsum(hits)
        precision = cum_tp / np.arange(1, hits.size + 1)
        recall = cum_tp / n_truth if n_truth else np.zeros_like(cum_tp)
        per_class[int(class_id)] = ClassAP(
            class_id=int(class_id),
            ap=average_precision(recall, precision) if n_truth else None,
            n_truth=n_truth,
            n_ignored_truth=int(np.sum(ignored_classes == class_id)),
            n_detections=n_detections,
            true_positives=int(hits.sum()),
            scores=scores[order],
            recall=recall,
            precision=precision,
        )
    return DetectionEvaluation(iou_threshold, per_class, len(truths), all_scores, all_outcomes)


def _check_threshold(iou_threshold: float) -> None:
    if not 0.0 < iou_threshold <= 1.0:
        raise ConfigError(f"iou_threshold must be in (0, 1], got {iou_threshold}")
