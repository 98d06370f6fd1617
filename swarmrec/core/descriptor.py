"""Semantic descriptors (paper Sec. III-B/C) and their Jaccard scores (Eq. 1, 5).

A semantic descriptor is a label histogram: bin ``l`` counts the objects of
label ``l`` in a constellation. Two descriptors compare by the Jaccard index
``sum min / sum max``; a *partial* score uses the bins of one label range only.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from swarmrec.core.types import Constellation

__all__ = ["jaccard", "partial_jaccard", "semantic_descriptor", "semantic_descriptors"]

Counts = npt.NDArray[np.int64]


def semantic_descriptor(c: Constellation, n_labels: int) -> Counts:
    """Histogram of ``c``'s labels over ``n_labels`` bins."""
    return np.bincount(c.labels, minlength=n_labels).astype(np.int64)[:n_labels]


def semantic_descriptors(
    constellations: tuple[Constellation, ...] | list[Constellation], n_labels: int
) -> Counts:
    """One descriptor per constellation, stacked as an (N, n_labels) array."""
    out = np.zeros((len(constellations), n_labels), np.int64)
    for i, c in enumerate(constellations):
        if len(c):
            np.add.at(out[i], c.labels, 1)
    return out


def jaccard(a: Counts, b: Counts) -> float:
    """Eq. 1/5: ``sum_l min(a_l, b_l) / sum_l max(a_l, b_l)``; 0 when both are empty.

    Written as ``common / (sum a + sum b - common)``, which is the same number
    and the form the published evaluation computes.
    """
    common = int(np.minimum(a, b).sum())
    union = int(a.sum()) + int(b.sum()) - common
    return common / union if union else 0.0


def partial_jaccard(a: Counts, b: Counts, lo: int, hi: int) -> float:
    """Eq. 1 restricted to the label range ``[lo, hi)``."""
    return jaccard(a[lo:hi], b[lo:hi])
