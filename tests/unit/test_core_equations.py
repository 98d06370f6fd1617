"""Each equation of the constellation paper on small cases worked out by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from swarmrec.core.association import associate, full_score
from swarmrec.core.descriptor import jaccard, partial_jaccard, semantic_descriptor
from swarmrec.core.ranges import balanced_ranges, even_ranges, holder_of_labels, validate_bounds
from swarmrec.core.selection import select_candidates, select_candidates_many, select_robots
from swarmrec.errors import ConfigError
from tests.conftest import label, make

N_LABELS = 80


def test_semantic_descriptor_counts_objects_per_label() -> None:
    c = make(("bottle", 0, 0, 1), ("bottle", 1, 0, 1), ("book", 0, 1, 1))
    d = semantic_descriptor(c, N_LABELS)
    assert d[label("bottle")] == 2 and d[label("book")] == 1 and d.sum() == 3


def test_jaccard_is_sum_of_min_over_sum_of_max() -> None:
    # min = 1 + 1 + 0 = 2, max = 2 + 1 + 3 = 6
    assert jaccard(np.array([2, 1, 0]), np.array([1, 1, 3])) == pytest.approx(2 / 6)


def test_jaccard_of_two_empty_descriptors_is_zero() -> None:
    assert jaccard(np.zeros(4, np.int64), np.zeros(4, np.int64)) == 0.0


def test_partial_jaccard_uses_only_the_bins_of_its_range() -> None:
    a, b = np.array([2, 1, 0, 5]), np.array([1, 1, 3, 0])
    assert partial_jaccard(a, b, 0, 2) == pytest.approx(2 / 3)  # min 1+1, max 2+1
    assert partial_jaccard(a, b, 2, 4) == 0.0  # min 0, max 3+5


# A: bottle, cup, book in an L shape; B: the same scene seen from elsewhere
# (translated by (5, 5, 5)) with the bottle 0.1 m further in z.
A = make(("bottle", 0, 2, 0), ("cup", 0, 0, 0), ("book", 1, 0, 0))
B = make(("cup", 5, 5, 5), ("book", 6, 5, 5), ("bottle", 5, 7, 5.1))
# Surroundings vectors over (bottle, cup, book), worked out by hand:
#   A: bottle [0, 2, sqrt 5]   cup [2, 0, 1]          book [sqrt 5, 1, 0]
#   B: bottle [0, sqrt 4.01, sqrt 5.01]   cup [sqrt 4.01, 0, 1]   book [sqrt 5.01, 1, 0]
CUP_GAP = math.sqrt(4.01) - 2  # 0.002498: |v_cup(A) - v_cup(B)|
BOOK_GAP = math.sqrt(5.01) - math.sqrt(5)  # 0.002235
BOTTLE_GAP = math.hypot(CUP_GAP, BOOK_GAP)  # 0.003352


def test_association_matches_the_same_objects_across_viewpoints() -> None:
    matches = associate(A, B, N_LABELS, d=0.25)
    # A's bottle (0) <-> B's bottle (2), cup (1) <-> cup (0), book (2) <-> book (1)
    assert sorted(map(tuple, matches.tolist())) == [(0, 2), (1, 0), (2, 1)]


def test_identical_scenes_score_one() -> None:
    result = full_score(A, B, N_LABELS, d=0.25)
    assert result.semantic == 1.0 and result.score == 1.0 and result.geometric == 1.0


def test_match_needs_a_vector_distance_strictly_below_d() -> None:
    # d between the cup/book gaps and the bottle gap: the bottle pair is lost.
    assert BOOK_GAP < CUP_GAP < 0.003 < BOTTLE_GAP
    result = full_score(A, B, N_LABELS, d=0.003)
    assert len(result.matches) == 2
    assert result.score == pytest.approx(1.0 * 2 / 3)  # s = 1, g = 2 matches / 3 common
    assert full_score(A, B, N_LABELS, d=0.002).score == 0.0


def test_final_score_multiplies_jaccard_by_matched_fraction() -> None:
    # B plus two extra bottles far away: s = 3 / 5, common objects 3.
    b_more = make(*[("cup", 5, 5, 5), ("book", 6, 5, 5), ("bottle", 5, 7, 5.1)],
                  ("bottle", 20, 0, 0), ("bottle", 25, 0, 0))  # fmt: skip
    result = full_score(A, b_more, N_LABELS, d=0.25)
    # With two more bottles, B's nearest-bottle distances are unchanged for cup
    # and book, but the far bottles' vectors are far from all of A's: 3 matches remain.
    assert result.semantic == pytest.approx(3 / 5)
    assert len(result.matches) == 3
    assert result.score == pytest.approx(3 / 5 * 3 / 3)


def test_fewer_than_three_common_objects_never_match() -> None:
    a = make(("cup", 0, 0, 0), ("book", 1, 0, 0), ("chair", 0, 0, 3))
    b = make(("cup", 0, 0, 0), ("book", 1, 0, 0), ("mouse", 0, 0, 3))
    result = full_score(a, b, N_LABELS)
    assert result.semantic == pytest.approx(2 / 4)
    assert result.score == 0.0 and len(result.matches) == 0


def test_disjoint_labels_score_zero() -> None:
    a = make(("cup", 0, 0, 0), ("cup", 1, 0, 0), ("cup", 0, 1, 0))
    b = make(("book", 0, 0, 0), ("book", 1, 0, 0), ("book", 0, 1, 0))
    assert full_score(a, b, N_LABELS).score == 0.0


# A bottle and a cup detected at the same spot have identical surroundings
# vectors [0, 0, 2]; only the label tells them apart.
TWIN = make(("bottle", 0, 0, 0), ("cup", 0, 0, 0), ("book", 2, 0, 0))


def test_paper_association_searches_across_labels_as_the_published_scripts() -> None:
    # Cross-label search: A's cup's nearest vector is B's bottle (first of a
    # tie), whose nearest is A's bottle, so the cup is not mutual: 2 of 3.
    result = full_score(TWIN, TWIN, N_LABELS, same_label_only=False)
    assert sorted(map(tuple, result.matches.tolist())) == [(0, 0), (2, 2)]
    assert result.score == pytest.approx(2 / 3)


def test_same_label_association_matches_each_object_to_its_own_label() -> None:
    result = full_score(TWIN, TWIN, N_LABELS, same_label_only=True)
    assert len(result.matches) == 3 and result.score == 1.0


def test_association_ties_go_to_the_first_object_in_detection_order() -> None:
    # Two bottles at the same place in B: A's bottle matches the first one.
    a = make(("bottle", 0, 0, 0), ("cup", 1, 0, 0), ("book", 0, 1, 0))
    b = make(("bottle", 0, 0, 0), ("cup", 1, 0, 0), ("book", 0, 1, 0), ("bottle", 0, 0, 0))
    assert (0, 0) in map(tuple, associate(a, b, N_LABELS).tolist())


def test_even_ranges_truncate_linspace_as_the_paper() -> None:
    assert even_ranges(80, 10).tolist() == list(range(0, 81, 8))
    assert even_ranges(80, 3).tolist() == [0, 26, 53, 80]  # 26.67 -> 26, 53.33 -> 53


def test_holder_of_labels_follows_the_boundaries() -> None:
    assert holder_of_labels(np.array([0, 26, 53, 80]), [0, 25, 26, 79]).tolist() == [0, 0, 1, 2]


def test_balanced_ranges_minimise_the_busiest_holder() -> None:
    # Loads 5,1,1,1,1,1 over 2 holders: [5] | [1,1,1,1,1] has max 5, the optimum.
    assert balanced_ranges([5, 1, 1, 1, 1, 1], 2).tolist() == [0, 1, 6]
    # 1,1,1,1 over 2 holders: 2 | 2.
    assert balanced_ranges([1, 1, 1, 1], 2).tolist() == [0, 2, 4]


def test_balanced_ranges_reject_more_holders_than_labels() -> None:
    with pytest.raises(ConfigError, match="non-empty ranges"):
        balanced_ranges([1, 1], 3)


def test_validate_bounds_names_the_problem() -> None:
    with pytest.raises(ConfigError, match="start at 0 and end at 80"):
        validate_bounds([0, 40, 79], 80)
    with pytest.raises(ConfigError, match="must not decrease"):
        validate_bounds([0, 50, 40, 80], 80)


def test_candidates_are_the_best_positive_scores() -> None:
    assert select_candidates(np.array([0.5, 0.0, 0.9, 0.5, 0.7]), 2).tolist() == [2, 4]
    # Fewer positive scores than n_ret: all of them, never a zero score.
    assert select_candidates(np.array([0.0, 0.3, 0.0]), 4).tolist() == [1]


def test_candidates_resolve_straddling_ties_like_the_published_argsort() -> None:
    scores = np.array([0.5, 0.9, 0.5, 0.7, 0.5, 0.5, 0.2])
    expected = sorted(np.argsort(-scores)[:3].tolist())  # the published rule itself
    assert select_candidates(scores, 3).tolist() == expected
    assert [r.tolist() for r in select_candidates_many(scores[None], 3)] == [expected]


def test_robot_selection_takes_the_most_frequent_plus_the_querying_robot() -> None:
    # Robot 3 returned three candidates, robot 2 two, robot 1 one.
    assert select_robots([2, 2, 3, 3, 3, 1], n_fq=1, self_robot=0).tolist() == [0, 3]
    assert select_robots([2, 2, 3, 3, 3, 1], n_fq=2, self_robot=0).tolist() == [0, 2, 3]
    assert select_robots([], n_fq=4, self_robot=5).tolist() == [5]
