"""The index of one label range: candidates against a plain-loop statement of
the paper's rule, and against the offline lock-step evaluation it must equal."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
import pytest

from swarmrec.core.index import PARTIAL_EPSILON, IndexCandidate, RangeIndex
from swarmrec.core.presets import get_preset
from swarmrec.core.selection import select_candidates, select_candidates_many
from swarmrec.core.types import Constellation, ConstellationSequence
from swarmrec.evaluation.scoring import score_decentralized

IntArray = npt.NDArray[np.int64]
FloatArray = npt.NDArray[np.float64]
N_LABELS = 80


def partial_scores(
    stored: dict[tuple[int, int], IntArray], query: IntArray, n_robots: int, t: int
) -> FloatArray:
    """Partial Jaccard of every (robot, frame < t) slot, robot-major, with loops:
    sum min / (sum a + sum b - sum min + 1e-12); 0 for an unstored slot."""
    values = np.zeros(n_robots * t)
    for r in range(n_robots):
        for f in range(t):
            s = stored.get((r, f))
            if s is None:
                continue
            common = float(sum(min(int(x), int(y)) for x, y in zip(s, query, strict=True)))
            values[r * t + f] = common / (float(sum(s)) + float(sum(query)) - common + 1e-12)
    return values


def reference_candidates(values: FloatArray, t: int, n_ret: int) -> list[tuple[int, int, float]]:
    """The paper's pick: the first n_ret of ``argsort(-values)`` that are > 0;
    listed best first, equal scores by slot."""
    order = np.argsort(-values)
    kept = [int(c) for c in order[:n_ret] if values[c] > 0]
    kept.sort(key=lambda c: (-values[c], c))
    return [(c // t, c % t, float(values[c])) for c in kept]


def slot_order_candidates(values: FloatArray, t: int, n_ret: int) -> list[tuple[int, int, float]]:
    """Without a step: the n_ret best > 0, equal scores in (robot, frame) order."""
    kept = sorted((c for c in range(values.shape[0]) if values[c] > 0), key=lambda c: (-values[c], c))[:n_ret]
    return [(c // t, c % t, float(values[c])) for c in kept]


def tie_straddles_the_cut(values: FloatArray, n_ret: int) -> bool:
    """More than n_ret positive scores reach the n_ret-th best: the sort picks among equals."""
    positive = np.sort(values[values > 0])[::-1]
    return bool(positive.shape[0] > n_ret and np.count_nonzero(positive >= positive[n_ret - 1]) > n_ret)


def as_tuples(found: list[IndexCandidate]) -> list[tuple[int, int, float]]:
    return [(c.robot, c.frame, c.score) for c in found]


# --- against the plain loops -----------------------------------------------------


@pytest.mark.parametrize("seed", range(6))
def test_candidates_are_the_papers_top_n_ret_on_random_slices(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n_robots, width = int(rng.integers(2, 6)), int(rng.integers(1, 6))
    index = RangeIndex(10, 10 + width, n_robots)
    stored: dict[tuple[int, int], IntArray] = {}
    for r in range(n_robots):
        for f in range(int(rng.integers(0, 40))):
            if rng.random() < 0.8:  # some slots stay unstored
                # Counts 0-2 over few bins: scores tie often, as in real data.
                stored[(r, f)] = rng.integers(0, 3, width)
                index.add(r, f, stored[(r, f)])
    t_max = max((f + 1 for _r, f in stored), default=0)
    straddling = 0
    for _ in range(30):
        query = rng.integers(0, 3, width)
        n_ret = int(rng.integers(1, 8))
        for before in (None, int(rng.integers(0, t_max + 3))):
            t = t_max if before is None else before
            values = partial_scores(stored, query, n_robots, t)
            pick = reference_candidates if before is not None else slot_order_candidates
            expected = pick(values, t, n_ret) if t > 0 else []
            assert as_tuples(index.candidates(query, n_ret, before=before)) == expected
            straddling += tie_straddles_the_cut(values, n_ret)
    assert straddling > 0  # the argsort had ties to decide, so they were compared too


def test_equal_fractions_rank_by_the_published_epsilon() -> None:
    # Query [1, 1, 0, 0]. Frame (0, 0) = [1, 0, 0, 0]: 1 common of 2, 1 / (2 + 1e-12).
    # Frame (1, 0) = [1, 1, 1, 1]: 2 common of 4, 2 / (4 + 1e-12), which is the larger.
    index = RangeIndex(0, 4, 2)
    index.add(0, 0, [1, 0, 0, 0])
    index.add(1, 0, [1, 1, 1, 1])
    best = index.candidates([1, 1, 0, 0], 1)
    assert [(c.robot, c.frame) for c in best] == [(1, 0)]
    assert best[0].score == 2 / (4 + 1e-12)


# --- against the offline lock-step evaluation ---------------------------------------


def random_sequence(n_frames: int, seed: int) -> ConstellationSequence:
    """Frames drawn from a few places whose labels fall in every range of 2-4 robots."""
    rng = np.random.default_rng(seed)
    pool = np.array([0, 1, 3, 7, 20, 22, 27, 30, 31, 41, 45, 55, 60, 61, 66, 70, 79])
    places = [rng.choice(pool, size=9) for _ in range(5)]
    frames = []
    for _ in range(n_frames):
        labels = places[rng.integers(len(places))]
        keep = rng.random(labels.shape[0]) < 0.6
        frames.append(Constellation(labels[keep], rng.uniform(-1, 1, (np.count_nonzero(keep), 3))))
    return ConstellationSequence(
        frame_ids=tuple(f"{i}.0" for i in range(n_frames)),
        timestamps=np.arange(n_frames, dtype=float),
        constellations=tuple(frames),
        label_names=tuple(str(i) for i in range(N_LABELS)),
    )


@pytest.mark.parametrize(
    ("n_frames", "n_robots", "n_ret", "seed"), [(90, 3, 2, 0), (83, 4, 4, 1), (61, 2, 1, 2)]
)
def test_a_lock_step_replay_returns_the_offline_evaluations_candidates(
    n_frames: int, n_robots: int, n_ret: int, seed: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    seq = random_sequence(n_frames, seed)
    preset = get_preset("paper").with_(n_ret=n_ret, exclusion=3)

    # What the offline evaluation selects: each call's values and chosen columns.
    calls: list[tuple[FloatArray, list[IntArray]]] = []

    def spy(values: FloatArray, n: int) -> list[IntArray]:
        chosen = select_candidates_many(values, n)
        calls.append((values.copy(), chosen))
        return chosen

    monkeypatch.setattr("swarmrec.evaluation.scoring.select_candidates_many", spy)
    run = score_decentralized(seq, n_robots, preset)

    # The swarm in lock-step: every robot's step-t frame queries each range with a
    # non-empty slice (before=t), then the shard stores the slice.
    bounds = np.linspace(0, N_LABELS, n_robots + 1, dtype=int).tolist()
    np.testing.assert_array_equal(run.bounds, bounds)
    per = math.ceil(n_frames / n_robots)
    indexes = [RangeIndex(bounds[k], bounds[k + 1], n_robots) for k in range(n_robots)]
    found: dict[tuple[int, int, int], list[IndexCandidate]] = {}
    for t in range(per):
        for r in range(n_robots):
            g = r * per + t
            if g >= n_frames or len(seq.constellations[g]) < preset.min_objects:
                continue
            desc = np.bincount(seq.constellations[g].labels, minlength=N_LABELS)
            for k, index in enumerate(indexes):
                part = desc[bounds[k] : bounds[k + 1]]
                if part.any():
                    found[(r, t, k)] = index.candidates(part, n_ret, before=t)
                    index.add(r, t, part)

    assert all(found[key] == [] for key in found if key[1] == 0)  # step 0 has nothing before it
    steps = sorted({t for (_r, t, _k) in found if t > 0})
    assert [values.shape[1] // n_robots for values, _ in calls] == steps
    straddling = 0
    for values, chosen in calls:
        t = values.shape[1] // n_robots
        active = sorted((r, k) for (r, t2, k) in found if t2 == t)  # robot-major, like np.nonzero
        assert len(active) == len(chosen) == values.shape[0]
        for (r, k), row, cols in zip(active, values, chosen, strict=True):
            got = found[(r, t, k)]
            assert sorted((c.robot, c.frame) for c in got) == [(int(c) // t, int(c) % t) for c in cols]
            assert [c.score for c in got] == [float(row[c.robot * t + c.frame]) for c in got]
            straddling += tie_straddles_the_cut(row, n_ret)
    assert straddling > 0  # some cuts fell inside a tie, which the argsort decided

    # The same from the offline run's own output, without the spy: candidates per query.
    queries = sorted({(r, t) for (r, t, _k) in found if t > 0})
    for r, t in queries:
        assert run.candidate_counts[r, t] == sum(len(found.get((r, t, k), [])) for k in range(n_robots))
    assert {(int(r), int(t)) for r, t in np.argwhere(run.candidate_counts)} <= set(queries)


# --- storage ---------------------------------------------------------------------


def test_before_limits_every_robot_to_earlier_frames() -> None:
    index = RangeIndex(0, 2, 3)
    for r in range(3):
        for f in range(10):
            index.add(r, f, [1, 1])
    got = index.candidates([1, 1], 100, before=4)
    assert sorted((c.robot, c.frame) for c in got) == [(r, f) for r in range(3) for f in range(4)]
    assert index.candidates([1, 1], 100, before=0) == []


@pytest.mark.parametrize("before", [None, 3])
def test_the_excluded_frame_is_never_named_and_the_others_keep_their_order(before: int | None) -> None:
    index = RangeIndex(0, 2, 2)
    index.add(0, 0, [1, 0])
    index.add(1, 0, [1, 1])
    index.add(1, 1, [1, 1])
    every = [(c.robot, c.frame) for c in index.candidates([1, 1], 10, before=before)]
    assert every == [(1, 0), (1, 1), (0, 0)]
    got = [(c.robot, c.frame) for c in index.candidates([1, 1], 10, before=before, exclude=(1, 1))]
    assert got == [(1, 0), (0, 0)]


def test_before_past_the_stored_frames_searches_everything() -> None:
    index = RangeIndex(0, 2, 2)
    index.add(0, 1, [1, 0])
    index.add(1, 2, [1, 1])
    got = index.candidates([1, 0], 10, before=500)
    assert [(c.robot, c.frame) for c in got] == [(0, 1), (1, 2)]
    assert [c.score for c in got] == [1 / (1 + 1e-12), 1 / (2 + 1e-12)]


def test_replacing_a_frame_keeps_the_size_and_scores_the_new_slice() -> None:
    index = RangeIndex(5, 7, 2)
    assert index.add(1, 3, [1, 0]) is True
    assert index.add(1, 3, [0, 2]) is False
    assert index.size == 1
    assert index.frames_of(1) == 4
    assert index.frames_of(0) == 0
    assert index.candidates([1, 0], 4) == []
    assert [(c.robot, c.frame) for c in index.candidates([0, 1], 4)] == [(1, 3)]


def test_frames_far_past_the_first_capacity_are_stored() -> None:
    index = RangeIndex(0, 1, 2)
    index.add(0, 0, [1])
    index.add(1, 1000, [2])
    assert (index.size, index.frames_of(1)) == (2, 1001)
    assert [(c.robot, c.frame) for c in index.candidates([2], 5)] == [(1, 1000), (0, 0)]


def test_a_query_with_no_objects_in_the_range_has_no_candidates() -> None:
    index = RangeIndex(0, 3, 1)
    index.add(0, 0, [1, 2, 3])
    assert index.candidates([0, 0, 0], 4) == []


def test_an_empty_index_has_no_candidates() -> None:
    assert RangeIndex(0, 3, 4).candidates([1, 1, 1], 4) == []


@pytest.mark.parametrize("counts", [[1, 2, 3], [1], np.ones((2, 2))])
def test_a_slice_of_the_wrong_width_is_refused(counts: npt.ArrayLike) -> None:
    index = RangeIndex(10, 12, 2)
    with pytest.raises(ValueError, match="for a range of 2"):
        index.add(0, 0, counts)
    assert index.size == 0


@pytest.mark.parametrize(("lo", "hi"), [(5, 5), (6, 5), (-1, 3)])
def test_an_empty_or_negative_label_range_is_refused(lo: int, hi: int) -> None:
    with pytest.raises(ValueError, match="empty label range"):
        RangeIndex(lo, hi, 2)


# --- the compact layout against the dense one it replaced -----------------------------


class DenseRangeIndex:
    """The layout RangeIndex had before it stored one row per frame: per-robot arrays
    indexed by frame (n_robots x frames x bins), kept here verbatim as the reference."""

    def __init__(self, lo: int, hi: int, n_robots: int) -> None:
        self.lo, self.hi, self.n_robots = lo, hi, n_robots
        self._counts = np.zeros((n_robots, 0, hi - lo))
        self._sums = np.zeros((n_robots, 0))
        self._stored = np.zeros((n_robots, 0), np.bool_)
        self._frames = np.zeros(n_robots, np.int64)

    @property
    def frames(self) -> int:
        return int(self._frames.max(initial=0))

    def _grow(self, frames: int) -> None:
        cap = self._counts.shape[1]
        if frames <= cap:
            return
        new_cap = max(frames, 2 * cap, 64)
        counts = np.zeros((self.n_robots, new_cap, self.hi - self.lo))
        counts[:, :cap] = self._counts
        sums = np.zeros((self.n_robots, new_cap))
        sums[:, :cap] = self._sums
        stored = np.zeros((self.n_robots, new_cap), np.bool_)
        stored[:, :cap] = self._stored
        self._counts, self._sums, self._stored = counts, sums, stored

    def add(self, robot: int, frame: int, counts: npt.ArrayLike) -> None:
        row = np.asarray(counts, dtype=np.float64).reshape(-1)
        self._grow(frame + 1)
        self._counts[robot, frame] = row
        self._sums[robot, frame] = row.sum()
        self._stored[robot, frame] = True
        self._frames[robot] = max(self._frames[robot], frame + 1)

    def candidates(
        self, counts: npt.ArrayLike, n_ret: int, *, before: int | None = None
    ) -> list[IndexCandidate]:
        query = np.asarray(counts, dtype=np.float64).reshape(-1)
        t = before if before is not None else self.frames
        if t <= 0:
            return []
        self._grow(t)
        bins = np.flatnonzero(query)
        common = np.minimum(self._counts[:, :t, bins], query[bins]).sum(axis=2)
        total = self._sums[:, :t] + query.sum() - common
        values = (common / (total + PARTIAL_EPSILON)).reshape(-1)
        cols = select_candidates(values, n_ret)
        order = cols[np.argsort(-values[cols], kind="stable")]
        return [IndexCandidate(int(c // t), int(c % t), float(values[c])) for c in order.tolist()]


def both(
    lo: int, hi: int, n_robots: int, rows: list[tuple[int, int, list[int]]]
) -> tuple[RangeIndex, DenseRangeIndex]:
    new, old = RangeIndex(lo, hi, n_robots), DenseRangeIndex(lo, hi, n_robots)
    for r, f, c in rows:
        new.add(r, f, c)
        old.add(r, f, c)
    return new, old


def test_a_tie_straddling_the_cut_is_decided_as_the_dense_layout_decides_it() -> None:
    # Twelve frames scoring exactly 1/2 against [1, 1] (one of two labels), stored out of
    # order over three robots with gaps; n_ret 5 cuts inside the tie, so the published
    # unstable argsort over every slot (the unstored zeros too) picks which five.
    rows = [(2, 9, [1, 0]), (0, 4, [0, 1]), (1, 0, [1, 0]), (0, 0, [0, 1]), (2, 1, [1, 0]),
            (1, 7, [0, 1]), (0, 8, [1, 0]), (2, 5, [0, 1]), (1, 3, [1, 0]), (0, 2, [0, 1]),
            (2, 3, [1, 0]), (1, 9, [0, 1]), (1, 5, [2, 2])]  # fmt: skip
    new, old = both(0, 2, 3, rows)
    for before in (4, 6, 10, 11, 37):
        for n_ret in (1, 3, 5, 12):
            got = new.candidates([1, 1], n_ret, before=before)
            assert got == old.candidates([1, 1], n_ret, before=before)
    # Without a step the tie is cut in (robot, frame) order.
    half = 1 / (2 + 1e-12)
    got = new.candidates([1, 1], 5)
    assert got[0] == IndexCandidate(1, 5, 2 / (4 + 1e-12))  # the one frame above the tie
    assert got[1:] == [IndexCandidate(0, f, half) for f in (0, 2, 4, 8)]


def test_a_row_stored_again_takes_its_new_slice_and_keeps_its_slot() -> None:
    new, old = both(3, 6, 2, [(1, 2, [1, 1, 0]), (0, 2, [0, 1, 0]), (1, 0, [0, 1, 1]), (1, 2, [0, 1, 0])])
    assert new.size == 3
    for query in ([0, 1, 0], [1, 1, 1], [0, 0, 4]):
        for before in (1, 3, 9):
            assert new.candidates(query, 2, before=before) == old.candidates(query, 2, before=before)


@pytest.mark.parametrize("seed", range(8))
def test_in_lock_step_the_compact_layout_returns_the_dense_layouts_candidates_in_its_order(seed: int) -> None:
    # Frames arrive in any order, robots interleaved, with long gaps (a robot's slice is
    # sent only when its frame has labels in the range); scores tie often.
    rng = np.random.default_rng(seed)
    n_robots, width = int(rng.integers(1, 5)), int(rng.integers(1, 5))
    slots = [
        (r, int(f))
        for r in range(n_robots)
        for f in rng.choice(600, size=int(rng.integers(0, 60)), replace=False)
    ]
    order = rng.permutation(len(slots))
    rows = [(slots[i][0], slots[i][1], rng.integers(0, 3, width).tolist()) for i in order]
    new, old = both(7, 7 + width, n_robots, rows)
    for _ in range(25):
        query = rng.integers(0, 3, width)
        n_ret = int(rng.integers(1, 9))
        for before in (int(rng.integers(0, 700)), 600, old.frames):
            assert new.candidates(query, n_ret, before=before) == old.candidates(query, n_ret, before=before)


def test_memory_follows_the_frames_stored_not_the_frame_indices_claimed(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # 256 slices at frame indices stepping by 4096 (the gap a shard allows) up to 2^20:
    # the dense layout held n_robots x 2^20 x bins doubles (670 MB here) and scanned
    # them on every query; one row per stored frame holds 256.
    index = RangeIndex(0, 8, 10)
    for i in range(256):
        index.add(3, 4096 * i, [1, 0, 0, 0, 0, 0, 0, 1])
    assert index.frames == 4096 * 255 + 1
    assert index.nbytes < 256 * 8 * 8 * 4  # well under 100 bytes a stored row
    index.add(0, 7, [1, 1, 0, 0, 0, 0, 0, 0])
    got = index.candidates([1, 1, 0, 0, 0, 0, 0, 0], 4, before=10)
    assert got == [IndexCandidate(0, 7, 2 / (2 + 1e-12)), IndexCandidate(3, 0, 1 / (3 + 1e-12))]

    # Without a step, not even a tie at the cut (256 equal scores for 4 places) builds
    # the n_robots x 2^20 vector: the dense selection is never called.
    def dense(*_args: object) -> None:
        raise AssertionError("the dense slot vector was built")

    monkeypatch.setattr("swarmrec.core.index.select_candidates", dense)
    got = index.candidates([1, 0, 0, 0, 0, 0, 0, 0], 4)
    assert [(c.robot, c.frame) for c in got] == [(0, 7), (3, 0), (3, 4096), (3, 8192)]


def test_a_stored_slice_is_read_back_and_an_unstored_one_is_none() -> None:
    index = RangeIndex(0, 3, 2)
    index.add(1, 5, [0, 2, 1])
    stored = index.get(1, 5)
    assert stored is not None and stored.tolist() == [0.0, 2.0, 1.0]
    assert index.get(0, 5) is None and index.get(1, 4) is None


@pytest.mark.parametrize(("robot", "frame"), [(-1, 0), (2, 0), (0, -1), (0, 2**32)])
def test_a_robot_or_frame_outside_the_index_is_refused(robot: int, frame: int) -> None:
    index = RangeIndex(0, 1, 2)
    with pytest.raises(ValueError, match="outside"):
        index.add(robot, frame, [1])
    assert index.size == 0
