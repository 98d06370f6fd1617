"""Confidence threshold and class-aware non-maximum suppression.

The constellation paper ran its detector with a zero threshold to keep as
many objects as possible, so a threshold of 0.0 keeps every box, including
boxes whose confidence is exactly zero. OpenCV's NMS only keeps scores
strictly above its (non-negative) threshold, so it is handed score *ranks*
instead of scores: the order is the same, every rank is above zero, and
ties keep the model's box order.

Suppression runs class by class with ``cv2.dnn.NMSBoxes``: the same result as
``cv2.dnn.NMSBoxesBatched`` (boxes of different classes never suppress each
other), but each box is only compared with kept boxes of its own class,
which matters at threshold zero, where thousands of boxes survive.
"""

from __future__ import annotations

import cv2
import numpy as np
import numpy.typing as npt

from swarmrec.detection.decode import Candidates

__all__ = ["non_max_suppression"]

IntArray = npt.NDArray[np.int64]


def non_max_suppression(
    candidates: Candidates, conf_threshold: float, iou_threshold: float, max_detections: int
) -> IntArray:
    """Indices of the kept candidates, best score first.

    A box is kept when its confidence is at least ``conf_threshold``, its box
    is finite with positive width and height (a degenerate box covers no
    pixel, so it could never become an object point), and no better box of
    the same class overlaps it with an IoU above ``iou_threshold``. At most
    ``max_detections`` are returned.
    """
    boxes, scores = candidates.boxes, candidates.scores
    wh = boxes[:, 2:] - boxes[:, :2]
    valid = (
        np.isfinite(scores)
        & np.isfinite(boxes).all(axis=1)
        & (scores >= conf_threshold)
        & (wh > 0).all(axis=1)
    )
    index = np.flatnonzero(valid)
    if index.size == 0:
        return np.zeros(0, np.int64)
    by_score = index[np.argsort(-scores[index], kind="stable")]
    # float32 holds every integer up to 2**24, so ranks are exact for any real output size.
    rank = np.empty(boxes.shape[0], np.float32)
    rank[by_score] = np.arange(by_score.size, 0, -1, dtype=np.float32)
    xywh = np.concatenate([boxes[:, :2], wh], axis=1)
    # Group by class, best first inside each group; every group is then one NMS call.
    grouped = by_score[np.argsort(candidates.class_ids[by_score], kind="stable")]
    group_ids = candidates.class_ids[grouped]
    starts = np.flatnonzero(np.r_[True, group_ids[1:] != group_ids[:-1]])
    kept: list[IntArray] = []
    for members in np.split(grouped, starts[1:]):
        # The stubs say sequences; the binding takes the arrays as they are, with no Python objects made.
        picked = cv2.dnn.NMSBoxes(xywh[members], rank[members], 0.0, iou_threshold)  # type: ignore[arg-type]
        kept.append(members[np.asarray(picked, dtype=np.int64).reshape(-1)])
    result = np.concatenate(kept)
    result = result[np.argsort(-rank[result], kind="stable")]
    return result[:max_detections].astype(np.int64)
