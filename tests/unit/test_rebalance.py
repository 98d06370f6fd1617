"""The rebalancing plan: owners per group from the observed load, packed onto the
shards largest first, current owners kept wherever the plan's quality allows."""

from __future__ import annotations

import math

import pytest

from swarmrec.core.placement import Placement, balance_ratio, groups_from_bounds, place, ring, shard_loads
from swarmrec.core.ranges import even_ranges
from swarmrec.core.rebalance import RULES, pack, rebalance
from swarmrec.errors import ConfigError

GROUPS = groups_from_bounds(even_ranges(80, 10).tolist())
MEMBERS = range(10)
#: Partial queries per group of the TUM sequence with even ranges and 10 robots (the
#: published figure's load: the busiest holder serves 2.67 times the mean).
TUM_LOAD = dict(enumerate([164.0, 2, 0, 22, 1748, 766, 15, 2060, 1046, 1894]))
HOT = {0: 1000.0, **{g: 10.0 for g in range(1, 10)}}


def test_packing_by_hand_puts_the_largest_shares_first_on_the_least_loaded_members() -> None:
    # Group 0 (5 on each of two owners) goes to members 0 and 1; group 1 (3) to the idle 2;
    # group 2 (3) to 2 again (3 < 5); group 3 (1) to 0 (5, the lower id of the two at 5).
    owners, load = pack([5.0, 3.0, 3.0, 1.0], [2, 1, 1, 1], [0, 1, 2])
    assert owners == [[0, 1], [2], [2], [0]]
    assert load == {0: 6.0, 1: 5.0, 2: 6.0}


def test_packing_keeps_current_owners_within_the_cap_and_never_one_owner_twice() -> None:
    owners, _ = pack([5.0, 3.0], [2, 1], [0, 1, 2], keep=[[2, 1], [1]], cap=8.0)
    assert owners == [[2, 1], [1]]  # 1 keeps both: 5 + 3 = 8 is within the cap
    owners, _ = pack([5.0, 3.0], [2, 1], [0, 1, 2], keep=[[2, 1], [1]], cap=7.0)
    assert owners[0] == [2, 1] and owners[1] == [0]  # 1 would reach 8: group 1 moves
    with pytest.raises(ConfigError):
        pack([1.0], [4], [0, 1, 2])


def test_the_tum_load_comes_under_one_and_a_half_without_losing_a_replica() -> None:
    a = place(GROUPS, MEMBERS, replicas=2)
    before = balance_ratio(shard_loads(a, TUM_LOAD))
    b = rebalance(a, TUM_LOAD, target=1.5)
    assert before > 1.5 and balance_ratio(shard_loads(b, TUM_LOAD)) <= 1.5
    assert b.version == a.version + 1
    assert all(len(own) >= 2 for own in b.owners)
    # The mean cannot move: every query goes to one replica of each group it touches.
    assert sum(shard_loads(b, TUM_LOAD).values()) == pytest.approx(sum(TUM_LOAD.values()))
    assert rebalance(b, TUM_LOAD, target=1.5) == b  # already balanced: no new version


def test_at_the_measured_store_weight_the_plan_reaches_what_one_move_at_a_time_could_not() -> None:
    # A store costs 0.4 of a query (measured in the 10-robot TUM swarm). The greedy rule this
    # replaced stopped at 1.35 times the mean: it moved one group at a time off the busiest shard
    # and gave up at the first move that did not help. By hand: group 7 on three owners
    # (2060 / 3 * 1.8 = 1236 each), groups 9, 4, 8, 5 on two (1326, 1224, 732, 536): ten
    # shares of 536 or more for ten shards, the two smallest paired; busiest 1326 against a
    # mean of 1179, 1.12.
    start = ring(GROUPS, MEMBERS, replicas=2)
    b = rebalance(start, TUM_LOAD, target=1.2, store_weight=0.4, min_replica_gain=0.1)
    work = shard_loads(b, TUM_LOAD, 0.4)
    assert balance_ratio(work) <= 1.2
    assert [len(o) for o in b.owners] == [2, 2, 2, 2, 2, 2, 2, 3, 2, 2]
    # The partial queries alone (what the run's report counts) are within 1.3 as well.
    assert balance_ratio(shard_loads(b, TUM_LOAD)) <= 1.3


def test_only_the_groups_that_must_move_do() -> None:
    # Shard 0 holds groups 0 and 1 (60 each), shards 1 and 2 one group of 10 each. The best
    # busiest load is 60 (a hot group alone on each of two shards, both small groups on the
    # third): group 1 leaves shard 0 and the small group where it lands leaves too. Group 0,
    # and the other small group, stay where they are.
    groups = ((0, 1), (1, 2), (2, 3), (3, 4))
    current = Placement(1, groups, ((0,), (0,), (1,), (2,)), (0, 1, 2), replicas=1)
    load = {0: 60.0, 1: 60.0, 2: 10.0, 3: 10.0}
    b = rebalance(current, load, target=1.0)
    assert max(shard_loads(b, load).values()) == 60.0
    assert set(current.moved(b)) == {1, 2}
    assert b.owners[0] == (0,) and b.owners[3] == (2,)
    # From a placement one move away from that best, only that group moves.
    near = Placement(1, groups, ((0,), (0,), (2,), (2,)), (0, 1, 2), replicas=1)
    assert set(near.moved(rebalance(near, load, target=1.0))) == {1}


def test_the_plan_is_deterministic_and_settles() -> None:
    a = ring(GROUPS, MEMBERS, replicas=2)
    b = rebalance(a, TUM_LOAD, target=1.1, store_weight=0.4, min_replica_gain=0.1)
    assert b == rebalance(
        a, dict(reversed(list(TUM_LOAD.items()))), target=1.1, store_weight=0.4, min_replica_gain=0.1
    )
    # The same load again: the placement it gave is the plan, so nothing moves.
    assert rebalance(b, TUM_LOAD, target=1.1, store_weight=0.4, min_replica_gain=0.1) == b


def test_with_free_stores_a_hot_group_is_copied_widely() -> None:
    b = rebalance(place(GROUPS, MEMBERS, replicas=2), HOT, target=1.5)
    assert len(b.owners[0]) > 3


def test_stores_as_costly_as_queries_add_no_replica_and_the_hot_group_keeps_its_owners_to_itself() -> None:
    a = place(GROUPS, MEMBERS, replicas=2)
    b = rebalance(a, HOT, target=1.5, store_weight=1.0)
    assert [len(o) for o in b.owners] == [len(o) for o in a.owners]
    assert max(shard_loads(b, HOT, 1.0).values()) < max(shard_loads(a, HOT, 1.0).values())
    hot_owners = set(b.owners[0])
    assert all(not (set(own) & hot_owners) for own in b.owners[1:])


def test_a_replica_must_lower_its_groups_share_by_the_minimum_gain() -> None:
    b = rebalance(place(GROUPS, MEMBERS, replicas=2), HOT, target=1.5, store_weight=0.5, min_replica_gain=0.1)
    # At weight 0.5 a third replica lowers each owner's share by 11 %, a fourth by 6 %.
    assert len(b.owners[0]) == 3


def test_a_group_never_has_more_owners_than_members_nor_fewer_than_its_replicas() -> None:
    b = rebalance(place(GROUPS, range(3), replicas=2), HOT, target=1.0)
    assert all(2 <= len(own) <= 3 for own in b.owners)


def test_a_plan_no_better_than_the_current_placement_leaves_it() -> None:
    # One group, two shards, one replica: whichever shard holds it is the busiest.
    current = Placement(4, ((0, 1),), ((1,),), (0, 1), replicas=1)
    assert rebalance(current, {0: 100.0}, target=1.0, store_weight=1.0) is current


@pytest.mark.parametrize(
    ("load", "weight", "target"),
    [({0: -1.0}, 0.0, 1.5), ({0: math.nan}, 0.0, 1.5), (TUM_LOAD, math.inf, 1.5), (TUM_LOAD, 0.0, 0.0)],
)
def test_a_load_weight_or_target_out_of_range_is_refused(
    load: dict[int, float], weight: float, target: float
) -> None:
    with pytest.raises(ConfigError):
        rebalance(place(GROUPS, MEMBERS), load, store_weight=weight, target=target)


def test_the_greedy_rule_kept_as_the_baseline_stops_where_the_plan_goes_on() -> None:
    start = ring(GROUPS, MEMBERS, replicas=2)
    settings = {"target": 1.2, "store_weight": 0.4, "min_replica_gain": 0.1}
    greedy = RULES["greedy"](start, TUM_LOAD, **settings)
    planned = RULES["pack"](start, TUM_LOAD, **settings)
    assert balance_ratio(shard_loads(greedy, TUM_LOAD, 0.4)) > 1.3
    assert balance_ratio(shard_loads(planned, TUM_LOAD, 0.4)) <= 1.2
