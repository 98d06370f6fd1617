"""Where label groups live: rendezvous placement, membership changes, replicas,
rebalancing from observed load, and the replica that answers a query."""

from __future__ import annotations

import pytest

from swarmrec.core.placement import (
    Placement,
    balance_ratio,
    follow_members,
    groups_from_bounds,
    owner_load,
    place,
    promote,
    ring,
    serving_owner,
    shard_loads,
    stable_hash,
    transition,
)
from swarmrec.core.ranges import even_ranges
from swarmrec.errors import ConfigError

GROUPS = groups_from_bounds(even_ranges(80, 10).tolist())
MEMBERS = range(10)
#: Partial queries per group of the TUM sequence with even ranges and 10 robots (the
#: published figure's load: the busiest holder serves 2.67 times the mean).
TUM_LOAD = dict(enumerate([164, 2, 0, 22, 1748, 766, 15, 2060, 1046, 1894]))


def test_groups_are_the_paper_even_ranges() -> None:
    assert GROUPS[:3] == ((0, 8), (8, 16), (16, 24)) and GROUPS[-1] == (72, 80)


def test_the_stable_hash_is_the_same_in_every_process() -> None:
    # Fixed values: Python's hash() is salted per process, this one is not.
    assert stable_hash(1, 2, 3) == stable_hash(1, 2, 3)
    assert stable_hash(1, 2, 3) != stable_hash(3, 2, 1)
    assert stable_hash(0) == 0xE220A8397B1DCDAF  # splitmix64's published first output from seed 0


def test_every_group_has_its_replicas_on_distinct_members_and_placement_is_deterministic() -> None:
    a = place(GROUPS, MEMBERS, replicas=2)
    assert a == place(GROUPS, reversed(list(MEMBERS)), replicas=2)
    assert all(len(set(own)) == 2 for own in a.owners)
    assert place(GROUPS, [4], replicas=2).owners == ((4,),) * 10  # never more replicas than members


def test_a_member_leaving_moves_only_the_groups_it_held_and_every_group_keeps_two_owners() -> None:
    a = place(GROUPS, MEMBERS, replicas=2)
    b = follow_members(a, [m for m in MEMBERS if m != 3])
    assert b.version == a.version + 1
    moved = a.moved(b)
    assert set(moved) == set(a.groups_of(3))
    for gained, lost in moved.values():
        assert lost == {3} and len(gained) == 1
    assert all(len(own) == 2 and 3 not in own for own in b.owners)


def test_a_member_joining_takes_only_what_rendezvous_gives_it() -> None:
    a = place(GROUPS, range(9), replicas=2)
    b = follow_members(a, range(10))
    for _g, (gained, lost) in a.moved(b).items():
        assert gained == {9} and len(lost) == 1
    # Joining then leaving again comes back to where it started.
    assert follow_members(b, range(9)).owners == a.owners


def test_nothing_changes_when_the_members_do_not() -> None:
    a = place(GROUPS, MEMBERS)
    assert follow_members(a, MEMBERS) == a


def test_balance_ratio_by_hand() -> None:
    assert balance_ratio([1, 1, 1, 1]) == 1.0
    assert balance_ratio([4, 0, 0, 0]) == 4.0
    assert balance_ratio([0, 0]) == 0.0
    assert balance_ratio({0: 3.0, 1: 1.0}) == 1.5


def test_shard_loads_split_a_group_evenly_over_its_owners() -> None:
    p = Placement(0, ((0, 2), (2, 4)), ((0, 1), (1,)), (0, 1))
    assert shard_loads(p, {0: 10.0, 1: 4.0}) == {0: 5.0, 1: 9.0}


def test_a_query_is_answered_by_one_live_owner_spread_over_them() -> None:
    p = place(GROUPS, MEMBERS, replicas=3)
    chosen = [serving_owner(p, 4, robot=r, frame=f, alive=MEMBERS) for r in range(10) for f in range(100)]
    counts = {m: chosen.count(m) for m in p.owners[4]}
    assert set(chosen) == set(p.owners[4]) and min(counts.values()) > 250
    dead = p.owners[4][0]
    alive = [m for m in MEMBERS if m != dead]
    assert all(serving_owner(p, 4, r, f, alive) != dead for r in range(5) for f in range(20))
    assert serving_owner(p, 4, 0, 0, alive=[]) is None


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"groups": ((0, 4), (5, 8))}, "tile the labels"),
        ({"owners": ((0,), ())}, "group 1 has no owner"),
        ({"owners": ((0, 0), (1,))}, "lists an owner twice"),
        ({"owners": ((0,), (7,))}, "non-members"),
    ],
)
def test_a_placement_that_does_not_make_sense_is_refused(kwargs: dict[str, object], match: str) -> None:
    base: dict[str, object] = {
        "version": 1,
        "groups": ((0, 4), (4, 8)),
        "owners": ((0,), (1,)),
        "members": (0, 1),
    }
    with pytest.raises(ConfigError, match=match):
        Placement(**{**base, **kwargs})  # type: ignore[arg-type]


# --- version 0 and handoffs -------------------------------------------------------


def test_version_0_with_one_replica_is_the_papers_layout_and_with_two_a_ring() -> None:
    one = ring(GROUPS, range(10), replicas=1)
    assert one.version == 0 and one.owners == tuple((k,) for k in range(10))
    two = ring(GROUPS, range(10), replicas=2)
    assert two.owners[0] == (0, 1) and two.owners[9] == (9, 0)
    assert two.settled and two.store_targets(9) == (9, 0)


def test_a_new_owner_learns_first_and_owns_only_when_promoted() -> None:
    # Three shards, groups on (0, 1), (1, 2), (2, 0); shard 3 joins and is to take group 1 from 1.
    current = ring(GROUPS[:3], range(3), replicas=2)
    target = Placement(0, GROUPS[:3], ((0, 1), (3, 2), (2, 0)), (0, 1, 2, 3), 2)
    step = transition(current, target)
    assert step is not None and step.version == 1
    assert step.owners[1] == (1, 2)  # still answering
    assert step.learners == ((), (3,), ())
    assert step.leaving == ((), (1,), ())
    assert step.store_targets(1) == (1, 2, 3)  # the learner takes every new store
    assert step.groups_of(3) == [] and step.learning(3) == [1]
    # Not before the learner has copied group 1.
    assert promote(step, {3: []}, alive=range(4)) is None
    done = promote(step, {3: [1]}, alive=range(4))
    assert done is not None and done.version == 2 and done.settled
    assert done.owners == ((0, 1), (2, 3), (2, 0))


def test_a_gone_owner_is_dropped_at_once_and_replaced_by_a_learner() -> None:
    current = ring(GROUPS[:3], range(3), replicas=2)
    live = (0, 2)
    target = follow_members(current, live)
    step = transition(current, target)
    assert step is not None
    assert step.owners == ((0,), (2,), (2, 0))  # shard 1 answers nothing any more
    assert step.learners == ((2,), (0,), ())  # each group back to two replicas
    assert 1 not in step.members


def test_a_group_whose_every_owner_is_gone_keeps_them_listed_and_learns_from_nobody() -> None:
    current = ring(GROUPS[:3], range(3), replicas=2)  # (0, 1), (1, 2), (2, 0)
    step = transition(current, follow_members(current, (0,)))
    assert step is not None
    assert step.owners == ((0,), (1, 2), (0,))
    assert step.learners == ((), (), ())  # nobody holds group 1 to copy it from
    assert set(step.members) == {0, 1, 2}
    # With one replica there is nothing to do at all until the owner is back.
    alone = ring(GROUPS[:3], range(3), replicas=1)
    assert transition(alone, follow_members(alone, (0, 2))) is None


def test_a_learner_that_is_gone_is_forgotten_at_promotion() -> None:
    current = ring(GROUPS[:2], range(2), replicas=1)
    target = Placement(0, GROUPS[:2], ((0, 2), (1,)), (0, 1, 2), 1)
    step = transition(current, target)
    assert step is not None and step.learners[0] == (2,)
    done = promote(step, {}, alive=(0, 1))
    assert done is not None and done.owners == ((0,), (1,))


def test_a_handoff_in_progress_is_finished_before_another_starts() -> None:
    current = ring(GROUPS[:3], range(3), replicas=2)
    step = transition(current, follow_members(current, (0, 2)))
    assert step is not None
    with pytest.raises(ConfigError, match="in progress"):
        transition(step, follow_members(step, (0, 2)))
    assert transition(current, current) is None


def test_learners_and_leaving_owners_are_checked() -> None:
    with pytest.raises(ConfigError, match="learners"):
        Placement(1, GROUPS[:1], ((0,),), (0, 1), 2, learners=((0,),))
    with pytest.raises(ConfigError, match="leaving"):
        Placement(1, GROUPS[:1], ((0,),), (0, 1), 2, leaving=((0,),))


def test_a_draining_owner_is_leaving_not_gone_so_it_is_copied_from_until_the_learners_own() -> None:
    current = ring(GROUPS[:3], range(3), replicas=2)  # (0, 1), (1, 2), (2, 0)
    # Shards 1 and 2 are stopping (draining) but still answer: only 0 stays.
    target = follow_members(current, (0,))
    step = transition(current, target, alive=(0, 1, 2))
    assert step is not None
    assert step.owners == ((0, 1), (1, 2), (2, 0))  # nobody dropped yet
    assert step.leaving == ((1,), (1, 2), (2,))
    assert step.learners == ((), (0,), ())
    done = promote(step, {0: [1]}, alive=(0,))
    assert done is not None and done.owners == ((0,), (0,), (0,))


def test_an_empty_label_range_is_no_group_so_groups_always_hold_a_label() -> None:
    # 5 robots over 3 labels: the paper's split [0, 0, 1, 1, 2, 3] leaves two empty ranges.
    assert groups_from_bounds([0, 0, 1, 1, 2, 3]) == ((0, 1), (1, 2), (2, 3))
    # And the placement of 5 shards over those 3 groups is a valid one.
    p = ring(groups_from_bounds([0, 0, 1, 1, 2, 3]), range(5), replicas=2)
    assert p.owners == ((0, 1), (1, 2), (2, 3))


def test_owner_load_by_hand() -> None:
    # 12 queries on 3 owners: 4 each, and each stores the 8 the others were asked for.
    assert owner_load(12.0, 3, 0.0) == 4.0
    assert owner_load(12.0, 3, 0.5) == 4.0 + 0.5 * 8.0
    assert owner_load(12.0, 3, 1.0) == 12.0  # a store as costly as a query: no spreading
    assert owner_load(12.0, 1, 0.7) == 12.0


def test_shard_loads_count_the_stores_of_the_slices_others_were_asked_for() -> None:
    p = Placement(0, ((0, 2), (2, 4)), ((0, 1), (1,)), (0, 1))
    # Group 0 (10 queries) on both: 5 queries and 5 stores of weight 0.5 each; group 1 on 1.
    assert shard_loads(p, {0: 10.0, 1: 4.0}, 0.5) == {0: 7.5, 1: 11.5}


@pytest.mark.parametrize("weight", [float("nan"), -0.1, float("inf")])
def test_a_store_weight_must_be_finite_and_not_negative(weight: float) -> None:
    with pytest.raises(ConfigError):
        shard_loads(place(GROUPS, MEMBERS), TUM_LOAD, weight)
