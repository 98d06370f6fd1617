"""Geometric verification as the verifier runs it: argument order, pair
columns, the Eq. 5 counts, and scores that survive the wire bit for bit."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from swarmrec.core.association import full_score
from swarmrec.core.presets import Preset, get_preset
from swarmrec.core.types import Constellation
from swarmrec.core.verification import FrameMatch, verify
from swarmrec.wire import decode, encode, verify_match_to_proto
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import match_scores
from tests.conftest import make

N_LABELS = 80
PAPER = get_preset("paper")

# One scene seen twice with the objects listed in another order: query cup 0 is
# stored cup 1 and query cup 2 is stored cup 0.
QUERY = make(("cup", 0, 0, 1), ("chair", 1, 0, 1), ("cup", 3, 0, 1), ("book", 0, 1, 1))
STORED = make(("cup", 3, 0, 1), ("cup", 0, 0, 1), ("chair", 1, 0, 1), ("book", 0, 1, 1))
# Rows follow the first argument's objects sorted by label (cup 41 < chair 56 < book 73),
# ties in detection order; columns are always (query object, stored object).
ROWS_QUERY_FIRST = [[0, 1], [2, 0], [1, 2], [3, 3]]
ROWS_STORED_FIRST = [[2, 0], [0, 1], [1, 2], [3, 3]]


@pytest.mark.parametrize(
    ("query_key", "own_robot", "frame", "rows"),
    [
        ((2, 5), 1, 9, ROWS_STORED_FIRST),  # a lower robot: the stored frame comes first
        ((2, 5), 3, 0, ROWS_QUERY_FIRST),  # a higher robot: the query comes first
        ((2, 5), 2, 4, ROWS_STORED_FIRST),  # same robot, earlier frame
        ((2, 5), 2, 6, ROWS_QUERY_FIRST),  # same robot, later frame
    ],
)
def test_pairs_follow_the_earlier_frames_order_with_query_objects_in_the_first_column(
    query_key: tuple[int, int], own_robot: int, frame: int, rows: list[list[int]]
) -> None:
    (m,) = verify(QUERY, query_key, own_robot, [(frame, STORED)], N_LABELS, PAPER)
    assert m.frame == frame
    assert m.pairs.tolist() == rows
    assert m.pairs.dtype == np.int64 and m.pairs.flags.c_contiguous
    assert (m.score, m.semantic, m.n_common, m.n_union) == (1.0, 1.0, 4, 4)


def test_eq5_counts_are_the_objects_in_common_and_in_either_frame() -> None:
    # Query: 2 cups, a chair, a book. Stored: a cup, 2 chairs, a laptop.
    # In common: min(2, 1) cups + min(1, 2) chairs = 2; in either: 4 + 4 - 2 = 6.
    query = make(("cup", 0, 0, 1), ("cup", 1, 0, 1), ("chair", 0, 1, 1), ("book", 1, 1, 1))
    stored = make(("cup", 0, 0, 1), ("chair", 0, 1, 1), ("chair", 2, 1, 1), ("laptop", 1, 1, 1))
    (m,) = verify(query, (0, 1), 0, [(0, stored)], N_LABELS, PAPER)
    assert (m.n_common, m.n_union) == (2, 6)
    assert m.semantic == 2 / 6
    assert m.score == 0.0  # 2 common objects are fewer than min_common = 3
    assert m.pairs.shape == (0, 2)


def test_results_are_best_first_with_equal_scores_by_frame() -> None:
    # 3 of the query's 4 objects, in place, among 5: semantic 3 / (4 + 5 - 3), all 3 matched.
    half = make(
        ("cup", 0, 0, 1), ("chair", 1, 0, 1), ("book", 0, 1, 1), ("laptop", 5, 5, 5), ("mouse", 6, 5, 5)
    )
    frames = [(7, half), (3, STORED), (5, Constellation.empty()), (1, STORED), (2, half)]
    got = verify(QUERY, (1, 0), 0, frames, N_LABELS, PAPER)
    assert [(m.frame, m.score) for m in got] == [(1, 1.0), (3, 1.0), (2, 0.5), (7, 0.5), (5, 0.0)]


def test_no_frames_give_no_matches() -> None:
    assert verify(QUERY, (0, 0), 0, [], N_LABELS, PAPER) == []


# --- many random constellations ------------------------------------------------------


def views_of_places(seed: int, n: int) -> list[Constellation]:
    """Noisy, partial, shuffled views of a few places, so that many pairs match
    a few objects and some pairs share fewer than min_common."""
    rng = np.random.default_rng(seed)
    labels = np.array([39, 41, 56, 62, 63, 64, 73])  # bottle cup chair tv laptop mouse book
    places = [(rng.choice(labels, size=8), rng.uniform(-1.5, 1.5, (8, 3))) for _ in range(3)]
    out = []
    for _ in range(n):
        lab, pos = places[rng.integers(len(places))]
        keep = rng.permutation(np.flatnonzero(rng.random(8) < 0.75))
        out.append(Constellation(lab[keep], pos[keep] + rng.normal(0, 0.03, (keep.shape[0], 3))))
    return out


def hand_counts(a: Constellation, b: Constellation) -> tuple[int, int]:
    ca, cb = Counter(a.labels.tolist()), Counter(b.labels.tolist())
    common = sum(min(ca[lab], cb[lab]) for lab in ca)
    return common, len(a) + len(b) - common


def expected_match(
    query: Constellation, stored: Constellation, query_first: bool, preset: Preset
) -> tuple[float, float, list[list[int]]]:
    first, second = (query, stored) if query_first else (stored, query)
    s = full_score(first, second, N_LABELS, d=preset.d, min_common=preset.min_common,
                   same_label_only=preset.same_label_only)  # fmt: skip
    pairs = s.matches if query_first else s.matches[:, ::-1]
    return s.score, s.semantic, pairs.tolist()


def wire_scores(m: FrameMatch) -> tuple[float, float]:
    msg = verify_match_to_proto(m.frame, m.pairs.shape[0], m.n_common, m.n_union, m.pairs)
    reply = decode(encode(pb.VerifyReply(matches=[msg])), pb.VerifyReply)
    return match_scores(reply.matches[0])


@pytest.mark.parametrize("preset_name", ["paper", "balanced"])
@pytest.mark.parametrize("seed", range(4))
def test_verify_equals_full_score_and_the_wire_reproduces_its_scores_bit_for_bit(
    preset_name: str, seed: int
) -> None:
    preset = get_preset(preset_name)
    rng = np.random.default_rng(100 + seed)
    frames = views_of_places(seed, 40)
    matched = below_min_common = 0
    for _ in range(15):
        query = views_of_places(int(rng.integers(1 << 30)), 1)[0]
        key = (int(rng.integers(0, 4)), int(rng.integers(0, 40)))
        own = int(rng.integers(0, 4))
        got = verify(query, key, own, list(enumerate(frames)), N_LABELS, preset)
        assert sorted(m.frame for m in got) == list(range(40))
        for m in got:
            score, semantic, pairs = expected_match(query, frames[m.frame], key < (own, m.frame), preset)
            assert (m.score, m.semantic, m.pairs.tolist()) == (score, semantic, pairs)
            assert (m.n_common, m.n_union) == hand_counts(query, frames[m.frame])
            if m.n_common:
                assert wire_scores(m) == (m.score, m.semantic)  # ==, not approx
            matched += m.score > 0
            below_min_common += 0 < m.n_common < preset.min_common
    assert matched > 20 and below_min_common > 0  # both kinds of pair were met
