"""Offline scoring of a sequence, centralized and decentralized (N robots).

Both produce a :class:`ScoreMatrix`: every pair that was fully checked with
its score, in the dense convention of the published evaluation so results
compare entry by entry:

* ``-1`` for pairs within the exclusion window (``|i - j| <= exclusion``),
* ``-2`` for pairs involving an ignored frame (fewer than ``min_objects``
  objects) — in the decentralized case only for ignored frames that queried,
  i.e. not a robot's first frame, as in the scripts,
* the full score for checked pairs, ``0`` for pairs never checked.

The decentralized mode simulates the two-step query in lock-step, exactly as
REFERENCE_NOTES.md describes: the sequence is cut into ``n`` consecutive
sub-trajectories of ``ceil(N / n)`` frames; at step ``t`` every robot queries
with its ``t``-th frame against the frames ``t' < t`` of every robot; each
range holder returns up to ``n_ret`` candidates; the querying robot verifies
the candidates of the ``n_fq`` robots that returned most, plus its own.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from swarmrec.core.association import FrameTable, build_table, score_pairs
from swarmrec.core.index import PARTIAL_EPSILON
from swarmrec.core.placement import groups_from_bounds
from swarmrec.core.presets import Preset
from swarmrec.core.ranges import label_bounds, validate_bounds
from swarmrec.core.selection import select_candidates_many, select_robots
from swarmrec.core.split import split_frames
from swarmrec.core.types import ConstellationSequence
from swarmrec.evaluation.band import fill_band
from swarmrec.evaluation.partition import Holdings, Reach

__all__ = [
    "DecentralizedRun",
    "ScoreMatrix",
    "decentralized_marks",
    "label_frequency_prior",
    "same_objects",
    "score_centralized",
    "score_decentralized",
    "split_frames",
]

IntArray = npt.NDArray[np.int64]
FloatArray = npt.NDArray[np.float64]
Progress = Callable[[int], None]


@dataclass(frozen=True, eq=False)
class ScoreMatrix:
    """Scores of every checked pair of an N-frame sequence."""

    pairs_i: IntArray  # i < j
    pairs_j: IntArray
    scores: FloatArray
    n_frames: int
    exclusion: int
    ignored: npt.NDArray[np.bool_]  # frames with too few objects
    #: Ignored frames whose pairs the scripts mark -2 (all ignored frames when centralized).
    ignored_marked: npt.NDArray[np.bool_]

    def outside_exclusion(self) -> npt.NDArray[np.bool_]:
        """Mask of the checked pairs that are loop-closure candidates: a robot may
        verify its own recent frames, but pairs within the exclusion window never count."""
        return np.asarray(self.pairs_j - self.pairs_i > self.exclusion)

    def dense(self) -> FloatArray:
        """The (N, N) matrix in the published convention (see module doc)."""
        n = self.n_frames
        m = np.zeros((n, n))
        m[self.pairs_i, self.pairs_j] = self.scores
        m[self.pairs_j, self.pairs_i] = self.scores
        marked = np.flatnonzero(self.ignored_marked)
        m[marked, :] = -2.0
        m[:, marked] = -2.0
        fill_band(m, self.exclusion, -1.0)  # the exclusion wins over "ignored"
        return m

    def rescored(self, table: FrameTable, preset: Preset) -> ScoreMatrix:
        """The same checked pairs with their full scores (Eq. 7) computed on ``table``:
        what the evaluation gives a sequence of the same frames and objects at other
        positions (the millimetres the wire carries, or exact ones). Which pairs are
        checked depends on labels alone (the semantic descriptors and which frames have
        enough objects), so it is not computed again; ``table`` must hold the same objects."""
        if not (
            self.n_frames == table.n_frames
            and np.array_equal(np.diff(table.offsets) >= preset.min_objects, ~self.ignored)
        ):
            raise ValueError("rescored: the table's frames are not this matrix's")
        scores = score_pairs(
            table, self.pairs_i, self.pairs_j, d=preset.d, min_common=preset.min_common,
            same_label_only=preset.same_label_only,
        )  # fmt: skip
        return ScoreMatrix(
            self.pairs_i,
            self.pairs_j,
            scores,
            self.n_frames,
            self.exclusion,
            self.ignored,
            self.ignored_marked,
        )


def same_objects(a: FrameTable, b: FrameTable) -> bool:
    """Whether two tables hold the same frames of the same labelled objects, in the same
    order (their positions may differ): a decentralized run checks the same pairs of both."""
    return bool(np.array_equal(a.offsets, b.offsets) and np.array_equal(a.labels, b.labels)) and (
        a.desc.shape == b.desc.shape
    )


def _valid_frames(table: FrameTable, preset: Preset) -> npt.NDArray[np.bool_]:
    sizes = np.diff(table.offsets)
    return np.asarray(sizes >= preset.min_objects)


def score_centralized(
    seq: ConstellationSequence,
    preset: Preset,
    *,
    table: FrameTable | None = None,
    progress: Progress | None = None,
) -> ScoreMatrix:
    """Score every pair of valid frames more than ``exclusion`` frames apart."""
    table = table or build_table(seq.constellations, seq.n_labels)
    valid = _valid_frames(table, preset)
    n = len(seq)
    chunks_i: list[IntArray] = []
    chunks_j: list[IntArray] = []
    chunks_s: list[FloatArray] = []
    # Row by row keeps memory at O(N) per step and lets the bar move.
    valid_idx = np.flatnonzero(valid)
    for i in valid_idx:
        j = valid_idx[valid_idx > i + preset.exclusion]
        if j.shape[0]:
            ii = np.full(j.shape[0], i, np.int64)
            chunks_i.append(ii)
            chunks_j.append(j.astype(np.int64))
            chunks_s.append(
                score_pairs(
                    table,
                    ii,
                    j,
                    d=preset.d,
                    min_common=preset.min_common,
                    same_label_only=preset.same_label_only,
                )
            )
        if progress:
            progress(1)
    if progress:
        progress(n - valid_idx.shape[0])
    return ScoreMatrix(
        pairs_i=np.concatenate(chunks_i) if chunks_i else np.zeros(0, np.int64),
        pairs_j=np.concatenate(chunks_j) if chunks_j else np.zeros(0, np.int64),
        scores=np.concatenate(chunks_s) if chunks_s else np.zeros(0),
        n_frames=n,
        exclusion=preset.exclusion,
        ignored=~valid,
        ignored_marked=~valid,
    )


def decentralized_marks(valid: npt.NDArray[np.bool_], blocks: list[range]) -> npt.NDArray[np.bool_]:
    """The ignored frames a decentralized run marks -2: those that queried,
    i.e. every invalid frame but a robot's first (as the scripts do)."""
    marked = ~valid
    for block in blocks:
        if len(block):
            marked[block.start] = False
    return marked


def label_frequency_prior(table: FrameTable) -> FloatArray:
    """How many frames hold each label: the oracle prior the ``balanced``
    preset balances label ranges on (the dataset's own frequencies)."""
    prior: FloatArray = np.count_nonzero(table.desc, axis=0).astype(np.float64)
    return prior


@dataclass(frozen=True, eq=False)
class DecentralizedRun:
    """A decentralized evaluation: its scores and what was sent."""

    matrix: ScoreMatrix
    n_robots: int
    frames_per_robot: int
    bounds: IntArray
    #: (n_robots, frames_per_robot, n_labels) descriptors as the robots share them
    #: (zeros for ignored frames and for the padding of the last robot).
    descriptors: FloatArray
    #: Candidates returned to each query (robot, step), over all ranges.
    candidate_counts: IntArray
    checked_robots: dict[tuple[int, int], IntArray] = field(repr=False)
    partial_descriptors_per_holder: IntArray = field(repr=False)  # (R,)
    labels_per_holder: IntArray = field(repr=False)  # (R,) non-zero bins received
    objects_per_holder: IntArray = field(repr=False)  # (R,) objects of the holder's labels
    #: With a ``reach``: what each owner held, the queries that found no owner, the
    #: verifications that could not reach their robot.
    holdings: Holdings | None = field(default=None, repr=False)


def score_decentralized(
    seq: ConstellationSequence,
    n_robots: int,
    preset: Preset,
    *,
    table: FrameTable | None = None,
    label_load: FloatArray | None = None,
    bounds: IntArray | None = None,
    progress: Progress | None = None,
    reach: Reach | None = None,
) -> DecentralizedRun:
    """Simulate the two-step decentralized query with ``n_robots`` robots; with ``reach``,
    on a team that splits and heals as it says (:mod:`swarmrec.evaluation.partition`)."""
    table = table or build_table(seq.constellations, seq.n_labels)
    valid = _valid_frames(table, preset)
    n, n_labels = len(seq), seq.n_labels
    blocks = split_frames(n, n_robots)
    per = math.ceil(n / n_robots)
    if bounds is None:
        bounds = label_bounds(preset.ranges, n_labels, n_robots, label_load)
    bounds = validate_bounds(bounds, n_labels)
    n_ranges = bounds.shape[0] - 1
    # Shared descriptors, float64 as in the scripts (their sums are exact integers).
    sem = np.zeros((n_robots, per, n_labels))
    for r, block in enumerate(blocks):
        for t, g in enumerate(block):
            if valid[g]:
                sem[r, t] = table.desc[g]
    # Range membership as a matrix: a product with it sums each range's bins.
    member = np.zeros((n_labels, n_ranges))
    for k in range(n_ranges):
        member[bounds[k] : bounds[k + 1], k] = 1.0
    sem_part = sem @ member  # (n_robots, per, R)
    holdings = None
    if reach is not None:
        groups = groups_from_bounds(bounds.tolist())
        range_groups = [
            groups.index((lo, hi)) if hi > lo else None
            for lo, hi in zip(bounds[:-1].tolist(), bounds[1:].tolist(), strict=True)
        ]
        holdings = Holdings(reach, sem_part > 0, range_groups)
        holdings.store(0)

    cand_count = np.zeros((n_robots, per), np.int64)
    checked: dict[tuple[int, int], IntArray] = {}
    pair_i: list[int] = []
    pair_j: list[int] = []
    for t in range(1, per):
        if holdings is not None:
            holdings.deliver(t)
        query_part = sem_part[:, t]  # (n, R)
        act_q, act_k = np.nonzero(query_part > 0)
        selected: dict[tuple[int, int], IntArray] = {}
        if act_q.shape[0]:
            # Only the bins the query holds in the range can have a non-zero minimum: one
            # (active pair, bin) per such bin, the pairs in order (nonzero is row-major),
            # each pair's minima summed. The counts are integers, so every sum is exact
            # whatever its order: the same doubles as summing over every bin.
            qvals = sem[act_q, t]  # (A, n_labels)
            pa, pb = np.nonzero((qvals > 0) & (member[:, act_k].T > 0))
            minima = np.minimum(sem[:, :t, pb], qvals[pa, pb])  # (n, t, P)
            starts = np.flatnonzero(np.r_[True, pa[1:] != pa[:-1]])
            common = np.moveaxis(np.add.reduceat(minima, starts, axis=2), 2, 0)  # (A, n, t)
            stored_part = np.moveaxis(sem_part[:, :t, act_k], 2, 0)  # (A, n, t)
            total = stored_part + query_part[act_q, act_k][:, None, None] - common
            values = (common / (total + PARTIAL_EPSILON)).reshape(act_q.shape[0], n_robots * t)
            unreached: set[int] = set()
            if holdings is not None:
                # A split team: each query sees what its serving owner holds (unheld slots
                # score 0, as a shard's own dense vector has them), or nothing.
                for a, (q, k) in enumerate(zip(act_q.tolist(), act_k.tolist(), strict=True)):
                    seen = holdings.visible(q, k, t)
                    if seen is None:
                        unreached.add(a)
                        values[a] = 0.0
                    else:
                        values[a] = np.where(seen, values[a], 0.0)
            for a, (q, k, cols) in enumerate(
                zip(
                    act_q.tolist(),
                    act_k.tolist(),
                    select_candidates_many(values, preset.n_ret),
                    strict=True,
                )
            ):
                if a not in unreached:
                    selected[(q, k)] = cols
        for r in range(n_robots):
            g = r * per + t
            if t >= len(blocks[r]) or not valid[g]:
                continue
            parts = [selected[(r, k)] for k in range(n_ranges) if (r, k) in selected]
            cols = np.concatenate(parts) if parts else np.zeros(0, np.int64)
            cand_count[r, t] = cols.shape[0]
            cand_robot = cols // t
            robots = select_robots(cand_robot, preset.n_fq, r)
            checked[(r, t)] = robots
            verified = np.isin(cand_robot, robots)
            if holdings is not None:
                # A picked robot outside the querier's component cannot verify.
                reachable = holdings.reachable(r, t, cand_robot)
                for lost in np.unique(cand_robot[verified & ~reachable]).tolist():
                    holdings.unverified.append((r, t, lost))
                verified &= reachable
            keep = np.unique(cols[verified])
            for c in keep.tolist():
                pair_i.append(g)
                pair_j.append((c // t) * per + c % t)
        if holdings is not None:
            holdings.store(t)
        if progress:
            progress(1)
    pi = np.array(pair_i, np.int64)
    pj = np.array(pair_j, np.int64)
    lo, hi = np.minimum(pi, pj), np.maximum(pi, pj)
    # A pair reached from both sides is scored once.
    uniq = np.unique(lo * n + hi) if lo.shape[0] else np.zeros(0, np.int64)
    lo, hi = uniq // n, uniq % n
    scores = score_pairs(
        table, lo, hi, d=preset.d, min_common=preset.min_common,
        same_label_only=preset.same_label_only,
    )  # fmt: skip
    marked = decentralized_marks(valid, blocks)
    nonzero = sem != 0
    holder_of_bin = np.repeat(np.arange(n_ranges), np.diff(bounds))
    labels_per_holder = np.bincount(
        holder_of_bin, weights=nonzero.sum(axis=(0, 1)), minlength=n_ranges
    ).astype(np.int64)
    objects_per_holder = np.bincount(holder_of_bin, weights=sem.sum(axis=(0, 1)), minlength=n_ranges).astype(
        np.int64
    )
    descriptors_per_holder = (sem_part > 0).sum(axis=(0, 1)).astype(np.int64)
    return DecentralizedRun(
        matrix=ScoreMatrix(lo, hi, scores, n, preset.exclusion, ~valid, marked),
        n_robots=n_robots,
        frames_per_robot=per,
        bounds=bounds,
        descriptors=sem,
        candidate_counts=cand_count,
        checked_robots=checked,
        partial_descriptors_per_holder=descriptors_per_holder,
        labels_per_holder=labels_per_holder,
        objects_per_holder=objects_per_holder,
        holdings=holdings,
    )
