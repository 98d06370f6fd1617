"""Geometric data association (paper Eq. 2-4) and the final score (Eq. 5-7).

For two constellations A and B:

1. The common labels are the labels present in both. If the number of common
   objects ``sum_l min(a_l, b_l)`` is below ``min_common`` there is no match.
2. Every object of A whose label is common gets a *surroundings vector* with
   one entry per common label (label order): the distance to the nearest
   object of A with that label, itself included (so its own label's entry is
   0). Same for B.
3. Object k of A and object n of B match when each is the other's nearest
   vector (Euclidean) and their distance is strictly below ``d``. Ties go to
   the first index.
4. ``score = jaccard(A, B) * matches / common``.

The published scripts search the nearest vector over *all* common-label
objects of the other frame (Eq. 3 says "with the same label"); the paper
preset does what the scripts did (``same_label_only=False``), the improved
presets restrict the search to the same label.

The arithmetic follows the published evaluation operation by operation
(distances summed coordinate by coordinate from 0, then ``sqrt``; Jaccard as
``common / (sum a + sum b - common)``), so scores agree bit for bit.

The work happens in numba-compiled kernels over a :class:`FrameTable`, a
packed form of many constellations with every per-frame quantity computed
once; the small functions at the bottom are the convenient single-pair API.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numba
import numpy as np
import numpy.typing as npt

from swarmrec.core.descriptor import semantic_descriptors
from swarmrec.core.types import Constellation

__all__ = [
    "FrameTable",
    "PairScore",
    "associate",
    "build_table",
    "full_score",
    "score_pairs",
    "score_tables",
    "warm_up",
]

IntArray = npt.NDArray[np.int64]
FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class FrameTable:
    """Many constellations packed for the kernels.

    ``order[offsets[f]:offsets[f+1]]`` are frame f's objects (global indices)
    sorted by label, ties in detection order; ``near[o, l]`` is the distance
    from object o to the nearest object of label l in its own frame (inf when
    the frame has none); ``desc`` holds the semantic descriptors.
    """

    offsets: IntArray
    labels: IntArray
    order: IntArray
    near: FloatArray
    desc: IntArray
    max_objects: int

    @property
    def n_frames(self) -> int:
        return int(self.offsets.shape[0] - 1)

    def n_objects(self, frame: int) -> int:
        return int(self.offsets[frame + 1] - self.offsets[frame])


@numba.njit(cache=True)
def _near_table(offsets: IntArray, labels: IntArray, pos: FloatArray, n_labels: int) -> FloatArray:
    near = np.full((labels.shape[0], n_labels), np.inf)
    for f in range(offsets.shape[0] - 1):
        for a in range(offsets[f], offsets[f + 1]):
            for b in range(offsets[f], offsets[f + 1]):
                # Summed from zero in x, y, z order, then sqrt: scipy's pdist does the same.
                s = 0.0
                for c in range(3):
                    diff = pos[a, c] - pos[b, c]
                    s = s + diff * diff
                dist = np.sqrt(s)
                if dist < near[a, labels[b]]:
                    near[a, labels[b]] = dist
    return near


def build_table(constellations: Sequence[Constellation], n_labels: int) -> FrameTable:
    """Pack ``constellations`` (in order) into a :class:`FrameTable`."""
    sizes = np.array([len(c) for c in constellations], np.int64)
    offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    if offsets[-1]:
        labels = np.concatenate([c.labels for c in constellations if len(c)]).astype(np.int64)
        pos = np.concatenate([c.positions for c in constellations if len(c)]).astype(np.float64)
    else:
        labels = np.zeros(0, np.int64)
        pos = np.zeros((0, 3), np.float64)
    order = np.empty_like(labels)
    for f in range(len(constellations)):
        lo, hi = offsets[f], offsets[f + 1]
        order[lo:hi] = lo + np.argsort(labels[lo:hi], kind="stable")
    near = _near_table(offsets, labels, pos, n_labels)
    desc = semantic_descriptors(list(constellations), n_labels)
    return FrameTable(offsets, labels, order, near, desc, int(sizes.max(initial=0)))


@numba.njit(cache=True)
def _pair(
    i: int,
    j: int,
    ta_offsets: IntArray,
    ta_labels: IntArray,
    ta_order: IntArray,
    ta_near: FloatArray,
    ta_desc: IntArray,
    tb_offsets: IntArray,
    tb_labels: IntArray,
    tb_order: IntArray,
    tb_near: FloatArray,
    tb_desc: IntArray,
    d: float,
    min_common: int,
    same_label: bool,
    buf_a: IntArray,
    buf_b: IntArray,
    common: IntArray,
    dist: FloatArray,
    best_a: IntArray,
    best_b: IntArray,
    out_matches: IntArray,
) -> tuple[float, float, int]:
    """Score frame i of table A against frame j of table B.

    Returns (score, semantic score, number of matches); when ``out_matches``
    has rows, the matched (k, n) object indices (frame-local) are written there.
    """
    n_labels = ta_desc.shape[1]
    sa = 0
    sb = 0
    sm = 0
    m = 0
    for lab in range(n_labels):
        x = ta_desc[i, lab]
        y = tb_desc[j, lab]
        sa += x
        sb += y
        if x > 0 and y > 0:
            sm += min(x, y)
            common[m] = lab
            m += 1
    if sm == 0:
        return 0.0, 0.0, 0
    sem = sm / (sa + sb - sm)
    if sm < min_common:
        return 0.0, sem, 0
    ka = 0
    for p in range(ta_offsets[i], ta_offsets[i + 1]):
        o = ta_order[p]
        if tb_desc[j, ta_labels[o]] > 0:
            buf_a[ka] = o
            ka += 1
    kb = 0
    for p in range(tb_offsets[j], tb_offsets[j + 1]):
        o = tb_order[p]
        if ta_desc[i, tb_labels[o]] > 0:
            buf_b[kb] = o
            kb += 1
    for x in range(ka):
        for y in range(kb):
            s = 0.0
            for c in range(m):
                diff = ta_near[buf_a[x], common[c]] - tb_near[buf_b[y], common[c]]
                s = s + diff * diff
            dist[x, y] = np.sqrt(s)
    for x in range(ka):
        best = -1
        for y in range(kb):
            if same_label and ta_labels[buf_a[x]] != tb_labels[buf_b[y]]:
                continue
            if best < 0 or dist[x, y] < dist[x, best]:
                best = y
        best_a[x] = best
    for y in range(kb):
        best = -1
        for x in range(ka):
            if same_label and ta_labels[buf_a[x]] != tb_labels[buf_b[y]]:
                continue
            if best < 0 or dist[x, y] < dist[best, y]:
                best = x
        best_b[y] = best
    count = 0
    for x in range(ka):
        y = best_a[x]
        if y >= 0 and best_b[y] == x and dist[x, y] < d:
            if count < out_matches.shape[0]:
                out_matches[count, 0] = buf_a[x] - ta_offsets[i]
                out_matches[count, 1] = buf_b[y] - tb_offsets[j]
            count += 1
    return sem * (count / sm), sem, count


@numba.njit(cache=True)
def _score_pairs(
    pi: IntArray,
    pj: IntArray,
    ta_offsets: IntArray,
    ta_labels: IntArray,
    ta_order: IntArray,
    ta_near: FloatArray,
    ta_desc: IntArray,
    tb_offsets: IntArray,
    tb_labels: IntArray,
    tb_order: IntArray,
    tb_near: FloatArray,
    tb_desc: IntArray,
    max_objects: int,
    d: float,
    min_common: int,
    same_label: bool,
) -> FloatArray:
    k = max(max_objects, 1)
    buf_a = np.empty(k, np.int64)
    buf_b = np.empty(k, np.int64)
    common = np.empty(ta_desc.shape[1], np.int64)
    dist = np.empty((k, k))
    best_a = np.empty(k, np.int64)
    best_b = np.empty(k, np.int64)
    no_matches = np.empty((0, 2), np.int64)
    out = np.empty(pi.shape[0])
    for p in range(pi.shape[0]):
        out[p] = _pair(
            pi[p], pj[p],
            ta_offsets, ta_labels, ta_order, ta_near, ta_desc,
            tb_offsets, tb_labels, tb_order, tb_near, tb_desc,
            d, min_common, same_label, buf_a, buf_b, common, dist, best_a, best_b, no_matches,
        )[0]  # fmt: skip
    return out


def score_pairs(
    table: FrameTable,
    pairs_i: npt.ArrayLike,
    pairs_j: npt.ArrayLike,
    *,
    d: float,
    min_common: int,
    same_label_only: bool,
    other: FrameTable | None = None,
) -> FloatArray:
    """Full scores (Eq. 7) of frame ``pairs_i[p]`` of ``table`` against frame
    ``pairs_j[p]`` of ``other`` (``table`` itself by default)."""
    tb = table if other is None else other
    pi = np.ascontiguousarray(pairs_i, dtype=np.int64)
    pj = np.ascontiguousarray(pairs_j, dtype=np.int64)
    return _score_pairs(
        pi, pj,
        table.offsets, table.labels, table.order, table.near, table.desc,
        tb.offsets, tb.labels, tb.order, tb.near, tb.desc,
        max(table.max_objects, tb.max_objects), float(d), int(min_common), bool(same_label_only),
    )  # fmt: skip


@dataclass(frozen=True)
class PairScore:
    """The full comparison of two constellations."""

    score: float
    semantic: float
    matches: IntArray  # (m, 2): object index in A, object index in B

    @property
    def geometric(self) -> float:
        """g of Eq. 6: matched objects over common objects (0 when none are common)."""
        return self.score / self.semantic if self.semantic else 0.0


def full_score(
    a: Constellation,
    b: Constellation,
    n_labels: int,
    *,
    d: float = 0.25,
    min_common: int = 3,
    same_label_only: bool = False,
) -> PairScore:
    """Compare two constellations: Eq. 2-7 with the matched object pairs."""
    return score_tables(
        build_table([a], n_labels),
        build_table([b], n_labels),
        d=d,
        min_common=min_common,
        same_label_only=same_label_only,
    )


def score_tables(
    ta: FrameTable,
    tb: FrameTable,
    *,
    d: float = 0.25,
    min_common: int = 3,
    same_label_only: bool = False,
) -> PairScore:
    """:func:`full_score` of the first frame of ``ta`` against the first frame of ``tb``.

    A service that compares one frame with many keeps each frame's one-frame table
    (:func:`build_table` of it alone) instead of packing both frames again per pair."""
    n_labels = ta.desc.shape[1]
    k = max(ta.max_objects, tb.max_objects, 1)
    matches = np.zeros((k, 2), np.int64)
    score, sem, count = _pair(
        0, 0,
        ta.offsets, ta.labels, ta.order, ta.near, ta.desc,
        tb.offsets, tb.labels, tb.order, tb.near, tb.desc,
        float(d), int(min_common), bool(same_label_only),
        np.empty(k, np.int64), np.empty(k, np.int64), np.empty(n_labels, np.int64),
        np.empty((k, k)), np.empty(k, np.int64), np.empty(k, np.int64), matches,
    )  # fmt: skip
    return PairScore(float(score), float(sem), matches[:count].copy())


def associate(
    a: Constellation,
    b: Constellation,
    n_labels: int,
    *,
    d: float = 0.25,
    min_common: int = 3,
    same_label_only: bool = False,
) -> IntArray:
    """The matched (index in a, index in b) object pairs of Eq. 4."""
    return full_score(a, b, n_labels, d=d, min_common=min_common, same_label_only=same_label_only).matches


def warm_up() -> None:
    """Compile (or load from numba's cache) the kernels a verifier uses.

    Called where paying the compile once saves it many times over: the main job
    before it starts ten verifiers, the service image at build time.
    """
    probe = Constellation(np.array([0, 1, 2]), np.eye(3))
    full_score(probe, probe, 3)
