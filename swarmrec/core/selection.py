"""Candidate selection by a range holder (n_ret) and robot selection by the
querying robot (n_fq), paper Sec. III-C/D.

Both follow the published scripts to the tie: candidates are the first
``n_ret`` entries of a descending ``numpy.argsort`` of the partial scores
(scores > 0 only), robots the first ``n_fq`` of a descending argsort of the
candidate counts per robot. numpy's default argsort is not stable, so which of
several equal scores wins is decided by that same sort on the same array; the
functions below call it whenever a tie straddles the cut and skip it otherwise
(the result does not depend on the order inside the kept set).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = ["select_candidates", "select_candidates_many", "select_robots"]

IntArray = npt.NDArray[np.int64]
FloatArray = npt.NDArray[np.float64]


def select_candidates(scores: FloatArray, n_ret: int) -> IntArray:
    """Indices of the (at most) ``n_ret`` best scores > 0, as the paper picks them."""
    scores = np.asarray(scores, dtype=np.float64)
    positive = np.flatnonzero(scores > 0.0)
    if positive.shape[0] <= n_ret:
        return positive.astype(np.int64)
    kth = np.partition(scores[positive], positive.shape[0] - n_ret)[positive.shape[0] - n_ret]
    above = positive[scores[positive] > kth]
    tied = positive[scores[positive] == kth]
    if above.shape[0] + tied.shape[0] == n_ret:
        return np.sort(np.concatenate([above, tied])).astype(np.int64)
    order = np.argsort(-scores)  # the published call: decides which tied scores are kept
    return np.sort(order[:n_ret]).astype(np.int64)


def select_candidates_many(scores: FloatArray, n_ret: int) -> list[IntArray]:
    """:func:`select_candidates` for each row of a 2-D array, vectorised for
    the common cases: few positive scores, or no tie straddling the cut."""
    scores = np.asarray(scores, dtype=np.float64)
    positive = scores > 0.0
    n_pos = np.count_nonzero(positive, axis=1)
    out: list[IntArray] = [np.flatnonzero(row).astype(np.int64) for row in positive]
    busy = np.flatnonzero(n_pos > n_ret)
    if busy.shape[0] == 0:
        return out
    sub = scores[busy]
    kth = -np.partition(-sub, n_ret - 1, axis=1)[:, n_ret - 1]
    n_ge = np.count_nonzero(sub >= kth[:, None], axis=1)
    for b, row, kth_b, n_ge_b in zip(busy.tolist(), sub, kth.tolist(), n_ge.tolist(), strict=True):
        if n_ge_b == n_ret:
            out[b] = np.flatnonzero(row >= kth_b).astype(np.int64)
        else:
            out[b] = np.sort(np.argsort(-row)[:n_ret]).astype(np.int64)
    return out


def select_robots(candidate_robots: npt.ArrayLike, n_fq: int, self_robot: int | None) -> IntArray:
    """Robots to send the full constellation to: the ``n_fq`` robots with the
    most candidates (ties as the published argsort orders them), plus the
    querying robot itself (None: the query comes from outside the swarm).
    Robots with no candidate may fill the list, as in the scripts; they have
    nothing to verify."""
    robots = np.asarray(candidate_robots, dtype=np.int64)
    chosen: list[int] = []
    if robots.shape[0]:
        order = np.argsort(-np.bincount(robots))
        chosen = [int(r) for r in order[:n_fq]]
    if self_robot is not None:
        chosen.append(int(self_robot))
    return np.unique(np.array(chosen, np.int64))
