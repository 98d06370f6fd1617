"""The paper's precision-recall protocol and its AUC.

For each frame take its single best-scoring other frame (first on ties);
sort frames by that best score, descending; walk the list accumulating true
and false positives. Recall is over the number of frames that have at least
one true closure. A true closure only counts where the detector could have
found it: pairs involving a frame with too few objects (score < 0 in the
published convention) are not missed closures. AUC is the trapezoid area
under precision(recall).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

__all__ = ["PRCurve", "precision_recall"]

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class PRCurve:
    precision: FloatArray
    recall: FloatArray
    thresholds: FloatArray  # the best score at each step of the walk
    best_match: npt.NDArray[np.int64]  # per frame: index of its best-scoring frame
    best_score: FloatArray
    true_positive: npt.NDArray[np.bool_]  # per frame: is its best match a true closure
    relevant: int  # frames with at least one true closure

    @property
    def auc(self) -> float:
        """Trapezoid area under precision over recall (recall never decreases)."""
        return float(np.trapezoid(self.precision, self.recall))


def precision_recall(dense_scores: FloatArray, closures: npt.NDArray[np.bool_]) -> PRCurve:
    """The protocol above on a dense score matrix in the published convention."""
    truth = closures & (dense_scores >= 0.0)
    best = np.argmax(dense_scores, axis=1)
    best_score = dense_scores[np.arange(dense_scores.shape[0]), best]
    # The published default (unstable) argsort: its order of equal best scores shapes the curve.
    walk = np.argsort(-best_score)
    hit = truth[walk, best[walk]]
    tp = np.cumsum(hit)
    fp = np.cumsum(~hit)
    relevant = int(truth.any(axis=1).sum())
    fn = relevant - tp
    precision = tp / (tp + fp + 1e-12)
    recall = tp / (tp + fn + 1e-12)
    return PRCurve(
        precision=precision,
        recall=recall,
        thresholds=best_score[walk],
        best_match=best.astype(np.int64),
        best_score=best_score,
        true_positive=truth[np.arange(truth.shape[0]), best],
        relevant=relevant,
    )
