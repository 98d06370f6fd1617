"""Assignment of label ranges to range holders (paper Sec. III-C, IV-B2).

The semantic descriptor is split into consecutive label ranges; range ``k`` is
held by one holder (a robot's index shard). A split is described by its
boundaries ``b`` (length n+1, ``b[0] = 0``, ``b[-1] = n_labels``): range ``k``
is ``[b[k], b[k+1])``.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import numpy.typing as npt

from swarmrec.errors import ConfigError

__all__ = [
    "RangeStrategy",
    "balanced_ranges",
    "even_ranges",
    "holder_of_labels",
    "label_bounds",
    "validate_bounds",
]

Bounds = npt.NDArray[np.int64]
RangeStrategy = Literal["even", "balanced"]


def label_bounds(
    strategy: RangeStrategy, n_labels: int, n_holders: int, label_load: npt.ArrayLike | None = None
) -> Bounds:
    """The label range boundaries of ``strategy``: the one place the policy lives.

    ``even`` is the paper's split (:func:`even_ranges`); ``balanced`` needs
    ``label_load`` (how often each label is expected, e.g. label frequencies) and
    minimises the busiest holder's load (:func:`balanced_ranges`).
    """
    if strategy == "even":
        return even_ranges(n_labels, n_holders)
    if strategy != "balanced":
        raise ConfigError(f"label range strategy must be even or balanced, got {strategy!r}")
    if label_load is None:
        raise ConfigError("balanced label ranges need a label load (label frequencies)")
    load = np.asarray(label_load, dtype=np.float64)
    if load.shape != (n_labels,):
        raise ConfigError(f"a label load has one value per label ({n_labels}), got shape {load.shape}")
    return validate_bounds(balanced_ranges(load, n_holders), n_labels)


def even_ranges(n_labels: int, n_holders: int) -> Bounds:
    """The paper's split: ``integer linspace(0, n_labels, n_holders + 1)``.

    ``linspace`` then truncation to int, exactly as the published scripts do,
    so 80 labels over 3 holders gives ``[0, 26, 53, 80]``.
    """
    if n_holders < 1:
        raise ConfigError(f"need at least one range holder, got {n_holders}")
    return np.linspace(0, n_labels, n_holders + 1, dtype=int).astype(np.int64)


def balanced_ranges(label_load: npt.ArrayLike, n_holders: int) -> Bounds:
    """Consecutive ranges whose summed ``label_load`` is as even as possible.

    ``label_load[l]`` is how often label ``l`` is expected in queries (e.g.
    label frequencies of a previous run or of a prior over the environment).
    Minimises the busiest holder's load with a linear-partition dynamic
    programme (exact optimum for consecutive ranges). The paper names load
    balancing with knowledge of the object distribution as future work.
    """
    load = np.asarray(label_load, dtype=np.float64)
    n = load.shape[0]
    if n_holders < 1:
        raise ConfigError(f"need at least one range holder, got {n_holders}")
    if n_holders > n:
        raise ConfigError(f"cannot split {n} labels into {n_holders} non-empty ranges")
    prefix = np.concatenate([[0.0], np.cumsum(load)])
    inf = float("inf")
    # best[k][i]: min over splits of labels [0, i) into k ranges of the max range load.
    best = np.full((n_holders + 1, n + 1), inf)
    cut = np.zeros((n_holders + 1, n + 1), np.int64)
    best[0][0] = 0.0
    for k in range(1, n_holders + 1):
        for i in range(k, n - (n_holders - k) + 1):
            j = np.arange(k - 1, i)
            cost = np.maximum(best[k - 1][j], prefix[i] - prefix[j])
            pick = int(np.argmin(cost))
            best[k][i] = cost[pick]
            cut[k][i] = j[pick]
    bounds = [n]
    i = n
    for k in range(n_holders, 0, -1):
        i = int(cut[k][i])
        bounds.append(i)
    return np.array(bounds[::-1], np.int64)


def validate_bounds(bounds: npt.ArrayLike, n_labels: int) -> Bounds:
    """Check a split given by the user; returns it as an int array."""
    b = np.asarray(bounds, dtype=np.int64)
    if b.ndim != 1 or b.shape[0] < 2:
        raise ConfigError("label range boundaries need at least two values")
    if b[0] != 0 or b[-1] != n_labels:
        raise ConfigError(f"label ranges must start at 0 and end at {n_labels}, got {b.tolist()}")
    if np.any(np.diff(b) < 0):
        raise ConfigError(f"label range boundaries must not decrease: {b.tolist()}")
    return b


def holder_of_labels(bounds: Bounds, labels: npt.ArrayLike) -> npt.NDArray[np.int64]:
    """The holder (range index) of each label."""
    return (np.searchsorted(bounds, np.asarray(labels), side="right") - 1).astype(np.int64)
