"""A straightforward per-pair implementation of Eq. 2-7, the way a first
version (and the published scripts) would write it: Python loops over objects,
numpy for the small vector maths. It is the same-run baseline of the offline
benchmark; results equal the kernel's (checked in the benchmark)."""

from __future__ import annotations

import numpy as np

from swarmrec.core.types import Constellation


def naive_score(
    a: Constellation, b: Constellation, n_labels: int, d: float = 0.25, min_common: int = 3
) -> float:
    ha = np.bincount(a.labels, minlength=n_labels)
    hb = np.bincount(b.labels, minlength=n_labels)
    common = float(np.minimum(ha, hb).sum())
    sem = common / (ha.sum() + hb.sum() - common)
    if sem <= 0 or common < min_common:
        return 0.0
    labels = [lab for lab in range(n_labels) if ha[lab] and hb[lab]]

    def vectors(c: Constellation) -> np.ndarray:
        dist = np.sqrt(((c.positions[:, None, :] - c.positions[None, :, :]) ** 2).sum(-1))
        rows = []
        for lab in labels:
            for k in np.flatnonzero(c.labels == lab):
                rows.append([dist[k, c.labels == other].min() for other in labels])
        return np.array(rows)

    va, vb = vectors(a), vectors(b)
    dist = np.sqrt(((va[:, None, :] - vb[None, :, :]) ** 2).sum(-1))
    best_a, best_b = dist.argmin(1), dist.argmin(0)
    matches = sum(1 for k, n in enumerate(best_a) if best_b[n] == k and dist[k, n] < d)
    return sem * (matches / common)
