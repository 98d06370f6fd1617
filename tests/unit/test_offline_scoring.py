"""Offline centralized/decentralized scoring against a plain re-statement of
REFERENCE_NOTES.md written here with loops, on random scenes small enough for
it, plus hand-checked properties of the lock-step protocol."""

from __future__ import annotations

import math

import numpy as np
import pytest

from swarmrec.core.association import build_table
from swarmrec.core.presets import Preset, get_preset
from swarmrec.core.types import Constellation, ConstellationSequence
from swarmrec.evaluation.scoring import (
    same_objects,
    score_centralized,
    score_decentralized,
    split_frames,
)
from tests.conftest import make

N_LABELS = 80


def _random_sequence(n_frames: int, seed: int) -> ConstellationSequence:
    """Frames drawn from a few 'places' so that scenes repeat with noise; few
    labels so partial scores tie often, as in real data."""
    rng = np.random.default_rng(seed)
    places = [
        (rng.choice([39, 41, 73, 56, 62, 64], size=8), rng.uniform(-1, 1, (8, 3)) + np.array([0, 0, 2]))
        for _ in range(4)
    ]
    frames = []
    for _ in range(n_frames):
        labels, pos = places[rng.integers(len(places))]
        keep = rng.random(len(labels)) < 0.7
        frames.append(Constellation(labels[keep], pos[keep] + rng.normal(0, 0.02, pos[keep].shape)))
    return ConstellationSequence(
        frame_ids=tuple(f"{i}.0" for i in range(n_frames)),
        timestamps=np.arange(n_frames, dtype=float),
        constellations=tuple(frames),
        label_names=tuple(str(i) for i in range(N_LABELS)),
    )


def _plain_score(a: Constellation, b: Constellation, p: Preset) -> float:
    """Eq. 2-7 with loops, following the notes' wording step by step."""
    ha = np.bincount(a.labels, minlength=N_LABELS)
    hb = np.bincount(b.labels, minlength=N_LABELS)
    common = int(np.minimum(ha, hb).sum())
    if common == 0:
        return 0.0
    s = common / (ha.sum() + hb.sum() - common)
    if common < p.min_common:
        return 0.0
    labels = [lab for lab in range(N_LABELS) if ha[lab] and hb[lab]]

    def nearest(c: Constellation, k: int, lab: int) -> float:
        return min(math.dist(c.positions[k], c.positions[n]) for n in range(len(c)) if c.labels[n] == lab)

    def vectors(c: Constellation) -> list[list[float]]:
        objs = [k for lab in labels for k in range(len(c)) if c.labels[k] == lab]
        return [[nearest(c, k, lab) for lab in labels] for k in objs]

    va = vectors(a)
    vb = vectors(b)
    dist = [[math.dist(x, y) for y in vb] for x in va]
    best_a = [min(range(len(vb)), key=lambda n, r=row: (r[n], n)) for row in dist]
    best_b = [min(range(len(va)), key=lambda k, n=n: (dist[k][n], k)) for n in range(len(vb))]
    matches = sum(1 for k, n in enumerate(best_a) if best_b[n] == k and dist[k][n] < p.d)
    return s * matches / common


def _plain_decentralized(
    seq: ConstellationSequence, n_robots: int, p: Preset
) -> dict[tuple[int, int], float]:
    n = len(seq)
    per = math.ceil(n / n_robots)
    valid = [len(c) >= p.min_objects for c in seq.constellations]
    desc = [np.bincount(c.labels, minlength=N_LABELS) if v else np.zeros(N_LABELS, int)
            for c, v in zip(seq.constellations, valid, strict=True)]  # fmt: skip
    bounds = np.linspace(0, N_LABELS, n_robots + 1, dtype=int)

    def frame(r: int, t: int) -> int | None:
        g = r * per + t
        return g if t < per and g < n else None

    scores: dict[tuple[int, int], float] = {}
    for t in range(1, per):
        for r in range(n_robots):
            q = frame(r, t)
            if q is None or not valid[q]:
                continue
            cands: list[tuple[int, int]] = []
            for k in range(n_robots):
                lo, hi = bounds[k], bounds[k + 1]
                vals = np.zeros((n_robots, t))
                for r2 in range(n_robots):
                    for t2 in range(t):
                        g = frame(r2, t2)
                        dq = desc[q][lo:hi]
                        dg = desc[g][lo:hi] if g is not None else np.zeros(hi - lo)
                        c = float(np.minimum(dq, dg).sum())
                        vals[r2, t2] = c / (float(dq.sum() + dg.sum()) - c + 1e-12)
                flat = vals.flatten()
                order = np.argsort(-flat)  # the notes: ties in that sort's order
                cands += [(int(i) // t, int(i) % t) for i in order[: p.n_ret] if flat[i] > 0]
            robots = (
                set(np.argsort(-np.bincount([c[0] for c in cands]))[: p.n_fq].tolist()) if cands else set()
            )
            robots.add(r)
            for r2, t2 in cands:
                if r2 in robots:
                    g = frame(r2, t2)
                    assert g is not None
                    key = (min(q, g), max(q, g))
                    scores[key] = _plain_score(seq.constellations[q], seq.constellations[g], p)
    return scores


PRESET = get_preset("paper").with_(exclusion=5)


@pytest.mark.parametrize("seed", [0, 1])
def test_centralized_scores_every_valid_pair_beyond_the_exclusion_like_the_plain_loops(
    seed: int,
) -> None:
    seq = _random_sequence(40, seed)
    m = score_centralized(seq, PRESET)
    got = dict(zip(zip(m.pairs_i.tolist(), m.pairs_j.tolist(), strict=True), m.scores.tolist(), strict=True))
    valid = [len(c) >= 3 for c in seq.constellations]
    expected = {
        (i, j): _plain_score(seq.constellations[i], seq.constellations[j], PRESET)
        for i in range(40) for j in range(i + 6, 40) if valid[i] and valid[j]
    }  # fmt: skip
    assert got.keys() == expected.keys()
    for key, value in expected.items():
        assert got[key] == pytest.approx(value, abs=1e-12), key
    assert any(v > 0 for v in expected.values())  # the case is not trivially all zero


@pytest.mark.parametrize(("n_robots", "seed"), [(2, 0), (3, 1), (4, 2)])
def test_decentralized_checks_and_scores_the_pairs_of_the_plain_lock_step(n_robots: int, seed: int) -> None:
    seq = _random_sequence(37, seed)
    run = score_decentralized(seq, n_robots, PRESET)
    m = run.matrix
    got = dict(zip(zip(m.pairs_i.tolist(), m.pairs_j.tolist(), strict=True), m.scores.tolist(), strict=True))
    expected = _plain_decentralized(seq, n_robots, PRESET)
    assert got.keys() == expected.keys()
    for key, value in expected.items():
        assert got[key] == pytest.approx(value, abs=1e-12), key


def test_split_gives_consecutive_blocks_of_ceil_n_over_robots() -> None:
    assert [list(b) for b in split_frames(10, 4)] == [[0, 1, 2], [3, 4, 5], [6, 7, 8], [9]]
    assert [len(b) for b in split_frames(2585, 10)] == [259] * 9 + [254]


def test_frames_of_the_same_step_are_never_compared() -> None:
    # 2 robots x 2 frames: robot 0 = frames 0, 1; robot 1 = frames 2, 3. All
    # four frames show the same scene. At step 1, robot 0's frame 1 sees the
    # step-0 frames 0 and 2; robot 1's frame 3 sees 0 and 2. Frames 1 and 3
    # (same step) and 0 and 2 (step 0, nobody queries) are never paired.
    scene = make(("cup", 0, 0, 1), ("book", 1, 0, 1), ("bottle", 0, 1, 1))
    seq = ConstellationSequence(
        ("0", "1", "2", "3"), np.arange(4.0), (scene,) * 4, tuple(map(str, range(80)))
    )
    run = score_decentralized(seq, 2, get_preset("paper").with_(exclusion=0))
    pairs = set(zip(run.matrix.pairs_i.tolist(), run.matrix.pairs_j.tolist(), strict=True))
    assert pairs == {(0, 1), (1, 2), (0, 3), (2, 3)}
    assert np.all(run.matrix.scores == 1.0)


def test_dense_matrix_uses_the_published_sentinels() -> None:
    seq = _random_sequence(30, 3)
    frames = list(seq.constellations)
    frames[20] = make(("cup", 0, 0, 1))  # too few objects: ignored
    seq = ConstellationSequence(seq.frame_ids, seq.timestamps, tuple(frames), seq.label_names)
    dense = score_centralized(seq, PRESET).dense()
    assert dense[3, 5] == -1.0 and dense[7, 7] == -1.0  # within the exclusion window
    assert dense[20, 2] == -2.0 and dense[2, 20] == -2.0  # ignored frame
    assert dense[20, 17] == -1.0  # the exclusion wins over "ignored"
    valid = [j for j in range(6, 30) if len(seq.constellations[j]) >= 3]
    assert len(seq.constellations[0]) >= 3 and 20 not in valid
    assert np.all(dense[0, valid] >= 0.0)  # checked pairs hold a score


@pytest.mark.parametrize(("n_frames", "exclusion"), [(30, 5), (12, 0), (6, 10), (1, 3)])
def test_dense_marks_exactly_the_band_within_the_exclusion(n_frames: int, exclusion: int) -> None:
    seq = _random_sequence(n_frames, 4)
    dense = score_centralized(seq, PRESET.with_(exclusion=exclusion)).dense()
    band = [[abs(i - j) <= exclusion for j in range(n_frames)] for i in range(n_frames)]
    assert ((dense == -1.0) == np.array(band)).all()


def _moved(seq: ConstellationSequence, seed: int) -> ConstellationSequence:
    """The same frames and objects, each object moved by a few millimetres."""
    rng = np.random.default_rng(seed)
    frames = tuple(
        Constellation(c.labels, c.positions + rng.normal(0, 0.004, c.positions.shape))
        for c in seq.constellations
    )
    return ConstellationSequence(seq.frame_ids, seq.timestamps, frames, seq.label_names)


@pytest.mark.parametrize(("n_robots", "seed"), [(2, 0), (3, 5), (5, 6)])
def test_the_pairs_of_one_run_rescored_on_moved_objects_equal_the_run_of_those_objects(
    n_robots: int, seed: int
) -> None:
    seq = _random_sequence(45, seed)
    moved = _moved(seq, seed)
    table, moved_table = (
        build_table(seq.constellations, N_LABELS),
        build_table(moved.constellations, N_LABELS),
    )
    assert same_objects(table, moved_table)
    first = score_decentralized(seq, n_robots, PRESET, table=table).matrix
    again = first.rescored(moved_table, PRESET)
    fresh = score_decentralized(moved, n_robots, PRESET).matrix
    assert np.array_equal(again.pairs_i, fresh.pairs_i) and np.array_equal(again.pairs_j, fresh.pairs_j)
    assert again.scores.tobytes() == fresh.scores.tobytes()  # the same doubles
    assert not np.array_equal(again.scores, first.scores)  # the positions did change scores
    assert np.array_equal(again.ignored_marked, fresh.ignored_marked)


def test_tables_of_other_objects_are_not_rescored() -> None:
    seq = _random_sequence(20, 7)
    frames = list(seq.constellations)
    c = frames[4]
    frames[4] = Constellation(np.r_[c.labels[:-1], (c.labels[-1] + 1) % N_LABELS], c.positions)
    relabelled = ConstellationSequence(seq.frame_ids, seq.timestamps, tuple(frames), seq.label_names)
    table = build_table(seq.constellations, N_LABELS)
    assert not same_objects(table, build_table(relabelled.constellations, N_LABELS))
    fewer = ConstellationSequence(
        seq.frame_ids[:19], seq.timestamps[:19], seq.constellations[:19], seq.label_names
    )
    with pytest.raises(ValueError, match="not this matrix's"):
        score_decentralized(seq, 2, PRESET, table=table).matrix.rescored(
            build_table(fewer.constellations, N_LABELS), PRESET
        )
