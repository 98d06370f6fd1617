"""The bound on busiest / mean for complete copies of the label groups (issue 27), by hand
on small loads, and against every packing of a few tiny ones."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from swarmrec.errors import ConfigError
from swarmrec.evaluation.balance_bound import (
    copies_for_ratio,
    group_partial_queries,
    packing_bound,
    replica_stores,
    share_bound,
    share_frontier,
    tie_straddles_cut,
)

#: Four groups queried 6, 2, 2 and 2 times: 12 partial queries, a mean of 3 on 4 shards.
LOADS = [6, 2, 2, 2]


def test_a_frame_queries_and_stores_in_each_group_it_has_labels_in_when_it_queries() -> None:
    desc = np.array([[1, 0, 2], [0, 0, 1], [0, 3, 0]])
    groups = [(0, 1), (1, 3)]
    assert group_partial_queries(desc, groups).tolist() == [1, 3]
    # The third frame has too few objects to query: it neither queries nor stores.
    assert group_partial_queries(desc, groups, [True, True, False]).tolist() == [1, 2]


def test_the_share_bound_is_the_largest_share_over_the_mean() -> None:
    assert share_bound(LOADS, [1, 1, 1, 1], 4) == 2.0  # 6 over a mean of 3
    assert share_bound(LOADS, [2, 1, 1, 1], 4) == 1.0  # 3, 2, 2, 2
    assert share_bound(LOADS, [3, 1, 1, 1], 4) == pytest.approx(2 / 3)  # 2 each
    assert share_bound([0, 0], [1, 1], 2) == 0.0


def test_every_copy_beyond_the_first_is_one_store_a_partial_query() -> None:
    assert replica_stores(LOADS, [3, 1, 2, 1]) == 6 * 2 + 2 * 1
    assert replica_stores(LOADS, [1, 1, 1, 1]) == 0


def test_the_fewest_copies_for_a_ratio_are_each_groups_own_minimum() -> None:
    # At most 1.5 x 3 = 4.5 a shard: the hot group needs 2 copies (3), the others 1.
    assert copies_for_ratio(LOADS, 4, 1.5) == [2, 1, 1, 1]
    assert copies_for_ratio(LOADS, 4, 1.0) == [2, 1, 1, 1]  # 3 is exactly the mean
    assert copies_for_ratio(LOADS, 4, 0.9) == [3, 1, 1, 1]  # 2.7: 6 / 2 is too much
    assert copies_for_ratio(LOADS, 4, 2.0) == [1, 1, 1, 1]  # on the breakpoint, no rounding up
    assert copies_for_ratio(LOADS, 4, 1.5, floor=2) == [2, 2, 2, 2]


def test_the_issues_hot_label_needs_thirteen_copies_for_one_and_a_half_times_the_mean() -> None:
    # 4660 of 25185 partial queries on 100 shards: at most 1.5 x 251.85 = 377.8 an owner;
    # 4660 / 12 = 388.3 is too many, 4660 / 13 = 358.5 is not.
    assert copies_for_ratio([4660, 25185 - 4660], 100, 1.5)[0] == 13


def test_a_ratio_below_a_copy_on_every_shard_is_refused() -> None:
    with pytest.raises(ConfigError, match="out of reach"):
        copies_for_ratio([10, 0], 2, 0.5)  # a copy on both shards is 5, the mean itself


def test_the_frontier_adds_a_copy_to_every_group_at_the_largest_share() -> None:
    points = share_frontier(LOADS, 4)
    assert [(p.copies, p.replica_stores) for p in points] == [
        ((1, 1, 1, 1), 0),
        ((2, 1, 1, 1), 6),
        ((3, 1, 1, 1), 12),
        ((4, 2, 2, 2), 24),  # all four were at 2: each gets one more
    ]
    assert [p.ratio for p in points] == pytest.approx([2.0, 1.0, 2 / 3, 0.5])


def test_the_frontier_from_a_floor_starts_at_the_floors_stores() -> None:
    points = share_frontier(LOADS, 4, floor=2)
    assert points[0].copies == (2, 2, 2, 2)
    assert points[0].replica_stores == 12
    assert points[0].ratio == 1.0


def test_the_packing_bound_counts_the_copies_a_shard_must_share_by_hand() -> None:
    # Three groups of 3 on two shards: two of them share one (6 over a mean of 4.5).
    assert packing_bound([3, 3, 3], [1, 1, 1], 2) == pytest.approx(6 / 4.5)
    # A group of 4 on both shards (2 each) and one of 2: one shard bears 4, the mean is 3.
    assert packing_bound([4, 2], [2, 1], 2) == pytest.approx(4 / 3)
    # Five groups of 1 on two shards: of any five, one shard holds three.
    assert packing_bound([1] * 5, [1] * 5, 2) == pytest.approx(3 / 2.5)
    # Four copies on four shards: nothing forces more than the largest share.
    assert packing_bound(LOADS, [1, 1, 1, 1], 4) == 2.0
    # Five copies (3, 3, 2, 2, 2) on four shards: two share one, at least 2 + 2 over a mean
    # of 3, though no share is above the mean.
    assert packing_bound(LOADS, [2, 1, 1, 1], 4) == pytest.approx(4 / 3)


def _best_packing(loads: list[int], copies: list[int], n: int) -> float:
    """busiest / mean of the best placement, every one of them tried."""
    choices = [list(itertools.combinations(range(n), k)) for k in copies]
    best = float("inf")
    for owners in itertools.product(*choices):
        load = [0.0] * n
        for q, k, own in zip(loads, copies, owners, strict=True):
            for m in own:
                load[m] += q / k
        best = min(best, max(load))
    return best * n / sum(loads)


@pytest.mark.parametrize("seed", range(6))
def test_no_placement_of_a_tiny_load_beats_the_bounds(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = 3
    loads = [int(x) for x in rng.integers(1, 20, size=4)]
    copies = [int(x) for x in rng.integers(1, n + 1, size=4)]
    best = _best_packing(loads, copies, n)
    assert share_bound(loads, copies, n) <= best + 1e-12
    assert packing_bound(loads, copies, n) <= best + 1e-12


def test_a_tie_straddles_the_cut_only_when_more_than_n_ret_positive_scores_reach_it() -> None:
    assert tie_straddles_cut([0.5] * 5, 4)
    assert tie_straddles_cut([0.9, 0.8, 0.7, 0.5, 0.5, 0.0], 4)
    assert not tie_straddles_cut([0.9, 0.8, 0.5, 0.5, 0.4], 4)  # the tie is inside the four
    assert not tie_straddles_cut([0.5, 0.5, 0.5, 0.5, 0.0, 0.0], 4)  # zeros are no candidates
    assert not tie_straddles_cut([0.5, 0.5], 4)


def test_copies_are_checked() -> None:
    with pytest.raises(ConfigError):
        share_bound(LOADS, [5, 1, 1, 1], 4)  # more copies than shards
    with pytest.raises(ConfigError):
        packing_bound(LOADS, [1, 1, 1], 4)
