"""How even the index's load can be, whatever the placement: lower bounds on the busiest
shard's partial queries for a number of complete copies of each label group.

A group ``g`` queried ``q_g`` times (one partial query per queried frame with labels in
it) and held in ``k_g`` complete copies puts ``q_g / k_g`` partial queries on its owners
on average, however its slices are cut among them: a partial query is answered from one
complete copy, so cutting a group by stored frame into sub-groups (each with its own
owners) divides the rows an owner stores and searches, not the partial queries it
receives. The mean over ``n`` shards is ``Q / n`` (``Q = sum q_g``, the same for every
placement), so

* busiest / mean >= ``max_g q_g n / (k_g Q)`` (:func:`share_bound`), and
* every copy beyond the first costs ``q_g`` replica ShardStores (:func:`replica_stores`):
  each slice of ``g`` is stored by the owner that answered it and sent to the other
  ``k_g - 1``.

So the least replica stores for busiest / mean <= ``ratio`` is a per-group minimum
(:func:`copies_for_ratio`, :func:`share_frontier` for every ratio), and for given copies
no packing onto ``n`` shards beats :func:`packing_bound` (pigeonhole bounds of scheduling
on identical machines). Nothing here reads :mod:`swarmrec.core.rebalance`: these are the
yardsticks its plans are measured against (``bench/bench_balance_bound.py``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from fractions import Fraction

import numpy as np
import numpy.typing as npt

from swarmrec.errors import ConfigError

__all__ = [
    "FrontierPoint",
    "copies_for_ratio",
    "group_partial_queries",
    "packing_bound",
    "replica_stores",
    "share_bound",
    "share_frontier",
    "tie_straddles_cut",
]


@dataclass(frozen=True)
class FrontierPoint:
    """The least replica stores (``replica_stores``, ShardStores in all) with which the
    busiest owner's share of partial queries is at most ``ratio`` times the mean, and the
    copies per group that achieve it."""

    ratio: float
    replica_stores: int
    copies: tuple[int, ...]


def group_partial_queries(
    descriptors: npt.ArrayLike,
    groups: Sequence[tuple[int, int]],
    queried: npt.ArrayLike | None = None,
) -> npt.NDArray[np.int64]:
    """Partial queries per group: the frames (rows of ``descriptors``, those ``queried``
    when given) with a positive count in the group's label range ``[lo, hi)``. Each such
    frame also stores one slice in the group, so this is its stored slices as well."""
    desc = np.asarray(descriptors)
    if desc.ndim != 2:
        raise ConfigError(f"descriptors are one row per frame, got shape {desc.shape}")
    rows = desc if queried is None else desc[np.asarray(queried, dtype=bool)]
    return np.array([int(np.count_nonzero(rows[:, lo:hi].sum(axis=1) > 0)) for lo, hi in groups], np.int64)


def _check(loads: Sequence[int], n_shards: int) -> int:
    if n_shards < 1:
        raise ConfigError(f"need at least one shard, got {n_shards}")
    if any(q < 0 for q in loads):
        raise ConfigError("a group's partial queries cannot be negative")
    return sum(loads)


def _check_copies(copies: Sequence[int], loads: Sequence[int], n_shards: int) -> None:
    if len(copies) != len(loads):
        raise ConfigError(f"{len(loads)} groups but {len(copies)} copy counts")
    if any(not 1 <= k <= n_shards for k in copies):
        raise ConfigError(f"a group has 1 to {n_shards} copies (one per shard at most)")


def share_bound(loads: Sequence[int], copies: Sequence[int], n_shards: int) -> float:
    """``max_g q_g / k_g`` over the mean ``Q / n``: no placement of these copies has a busiest
    shard below it (0 when nothing is queried)."""
    total = _check(loads, n_shards)
    _check_copies(copies, loads, n_shards)
    if total == 0:
        return 0.0
    return float(max(Fraction(q, k) for q, k in zip(loads, copies, strict=True)) * n_shards / total)


def replica_stores(loads: Sequence[int], copies: Sequence[int]) -> int:
    """ShardStores beyond the answering owner's own store: ``sum_g q_g (k_g - 1)``."""
    if len(copies) != len(loads):
        raise ConfigError(f"{len(loads)} groups but {len(copies)} copy counts")
    return sum(q * (k - 1) for q, k in zip(loads, copies, strict=True))


def copies_for_ratio(loads: Sequence[int], n_shards: int, ratio: float, *, floor: int = 1) -> list[int]:
    """The fewest copies of each group (at least ``floor``) with ``q_g / k_g <= ratio * Q / n``:
    ``k_g = ceil(q_g n / (ratio Q))``. Each group's count is its own minimum, so their replica
    stores are the least any placement with busiest / mean <= ``ratio`` needs. ``ratio`` below
    the largest ``q_g / Q`` (the share with a copy on every shard) cannot be reached."""
    total = _check(loads, n_shards)
    if not 1 <= floor <= n_shards:
        raise ConfigError(f"the floor of copies must be 1 to {n_shards}, got {floor}")
    if not (math.isfinite(ratio) and ratio > 0):
        raise ConfigError(f"a ratio must be finite and > 0, got {ratio}")
    if total == 0:
        return [floor] * len(loads)
    r = Fraction(ratio)  # the float's exact value: no rounding at a breakpoint
    out = []
    for q in loads:
        k = max(floor, math.ceil(Fraction(q * n_shards) / (r * total)))
        if k > n_shards:
            raise ConfigError(
                f"busiest/mean {ratio} is out of reach: a group of {q} of {total} partial queries "
                f"is at least {q / total:.3f} x the mean with a copy on every shard"
            )
        out.append(k)
    return out


def share_frontier(loads: Sequence[int], n_shards: int, *, floor: int = 1) -> list[FrontierPoint]:
    """Every corner of the trade-off between replica stores and :func:`share_bound`, from
    ``floor`` copies of each group to the best reachable: each point's copies are the least
    for its ratio (:func:`copies_for_ratio`), so any placement whose busiest / mean is at most
    a point's ratio makes at least its replica stores. Each step gives one more copy to every
    group whose share is the largest."""
    total = _check(loads, n_shards)
    if not 1 <= floor <= n_shards:
        raise ConfigError(f"the floor of copies must be 1 to {n_shards}, got {floor}")
    copies = [floor] * len(loads)
    points: list[FrontierPoint] = []
    if total == 0 or not loads:
        return [FrontierPoint(0.0, replica_stores(loads, copies), tuple(copies))]
    while True:
        shares = [Fraction(q, k) for q, k in zip(loads, copies, strict=True)]
        top = max(shares)
        points.append(
            FrontierPoint(float(top * n_shards / total), replica_stores(loads, copies), tuple(copies))
        )
        hot = [g for g, s in enumerate(shares) if s == top]
        if any(copies[g] >= n_shards for g in hot) or top == 0:
            return points
        for g in hot:
            copies[g] += 1


def packing_bound(loads: Sequence[int], copies: Sequence[int], n_shards: int) -> float:
    """A lower bound on busiest / mean for ``k_g`` copies of each group, each copy bearing
    ``q_g / k_g``, on ``n`` shards (a copy of a group on each of ``k_g`` distinct shards):

    * the mean itself (1.0), and the largest share (:func:`share_bound`);
    * for ``j >= 1``, of the ``j n + 1`` largest copies some shard holds ``j + 1`` (pigeonhole),
      so the busiest bears at least the ``j + 1`` smallest of them.
    """
    total = _check(loads, n_shards)
    _check_copies(copies, loads, n_shards)
    if total == 0:
        return 0.0
    items = sorted(
        (Fraction(q, k) for q, k in zip(loads, copies, strict=True) for _ in range(k)), reverse=True
    )
    best = max(Fraction(total, n_shards), items[0])
    j = 1
    while j * n_shards + 1 <= len(items):
        top = j * n_shards + 1
        best = max(best, sum(items[top - j - 1 : top], Fraction(0)))
        j += 1
    return float(best * n_shards / total)


def tie_straddles_cut(values: npt.ArrayLike, n_ret: int) -> bool:
    """Whether more than ``n_ret`` positive scores are >= the ``n_ret``-th best positive one:
    then which of the equal scores are kept is the published unstable argsort's choice over
    the whole score vector (:func:`swarmrec.core.selection.select_candidates`)."""
    if n_ret < 1:
        raise ConfigError(f"n_ret must be >= 1, got {n_ret}")
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    positive = v[v > 0.0]
    if positive.shape[0] <= n_ret:
        return False
    kth = -np.partition(-positive, n_ret - 1)[n_ret - 1]
    return bool(np.count_nonzero(positive >= kth) > n_ret)
