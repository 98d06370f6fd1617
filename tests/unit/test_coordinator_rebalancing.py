"""When the coordinator rebalances (its rule over the load the shards report; the
placement arithmetic itself is tested in test_placement.py).

The coordinator runs inside an index shard; here it is given a stand-in holding only
what ``_rebalanced`` reads (settings, a logger), and shard states as the shards send
them (``ShardState.served_groups``/``served_queries``: partial queries served per group
since the shard started, groups with none left out)."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import pytest

from swarmrec.core.placement import Placement, shard_loads
from swarmrec.errors import WireError
from swarmrec.services.coordinator import (
    DEFAULT_STORE_WEIGHT,
    LEARNING_LOOKS,
    MAX_STORE_WEIGHT,
    MIN_COST_SAMPLES,
    MIN_GAIN,
    Coordinator,
    View,
    cost_totals,
    group_changes,
    must_look,
    present_members,
    reason_name,
    served_load,
    store_weight,
)
from swarmrec.services.settings import IndexSettings
from swarmrec.wire import messages as pb

GROUPS = ((0, 1), (1, 2), (2, 3), (3, 4))


@dataclass
class _Ctx:
    log: logging.Logger = field(default_factory=lambda: logging.getLogger("test-coordinator"))


@dataclass
class _Shard:
    index_settings: IndexSettings
    ctx: _Ctx = field(default_factory=_Ctx)


def coordinator(target: float = 1.0, min_queries: int = 1) -> Coordinator:
    shard = _Shard(IndexSettings(rebalance_target=target, rebalance_min_queries=min_queries))
    return Coordinator(shard)  # type: ignore[arg-type]  # only settings and log are read


def served(per_group: list[int]) -> dict[str, list[int]]:
    """A shard's served load as it sends it: the groups with any queries, and their counts."""
    return {
        "served_groups": [g for g, n in enumerate(per_group) if n],
        "served_queries": [n for n in per_group if n],
    }


def states(*per_shard: list[int]) -> dict[int, pb.ShardState]:
    return {m: pb.ShardState(shard_id=m, **served(q)) for m, q in enumerate(per_shard)}


def test_a_move_that_lowers_the_busiest_load_by_less_than_the_gain_moves_nothing() -> None:
    # Shard 0 holds groups 0 and 1 (95 + 10), shard 1 group 2 (100), shard 2 group 3 (50).
    # Moving group 0 onto shard 2 is the only step: the busiest goes from 105 to 100 (5 %).
    current = Placement(1, GROUPS, ((0,), (0,), (1,), (2,)), (0, 1, 2), replicas=1)
    load = {0: 95.0, 1: 10.0, 2: 100.0, 3: 50.0}
    assert max(shard_loads(current, load).values()) == 105.0
    seen = states([95, 10, 0, 0], [0, 0, 100, 0], [0, 0, 0, 50])
    assert coordinator()._rebalanced(current, seen) is None


def test_a_move_that_lowers_the_busiest_load_by_the_gain_is_taken() -> None:
    # Shard 0 holds groups 0 and 1 (60 + 60); the others 10 each: moving a hot group
    # elsewhere halves the busiest load, far more than MIN_GAIN.
    current = Placement(1, GROUPS, ((0,), (0,), (1,), (2,)), (0, 1, 2), replicas=1)
    seen = states([60, 60, 0, 0], [0, 0, 10, 0], [0, 0, 0, 10])
    balanced = coordinator()._rebalanced(current, seen)
    assert balanced is not None
    load = {0: 60.0, 1: 60.0, 2: 10.0, 3: 10.0}
    before = max(shard_loads(current, load).values())
    assert max(shard_loads(balanced, load).values()) <= (1 - MIN_GAIN) * before
    assert balanced.version == current.version + 1


def test_the_load_is_every_query_served_not_the_last_window() -> None:
    # Served so far: a balanced layout for a load spread evenly over the four groups.
    current = Placement(1, GROUPS, ((0,), (1,), (2,), (0, 1, 2)), (0, 1, 2), replicas=1)
    c = coordinator(target=1.2)
    first = states([300, 0, 0, 100], [0, 300, 0, 100], [0, 0, 300, 100])
    assert c._rebalanced(current, first) is None  # balanced: nothing to move
    # The next window is all group 0 (a robot in a room full of one label): over that window
    # alone shard 0 would look three times as busy as the mean, over everything it is not.
    later = states([400, 0, 0, 100], [0, 300, 0, 100], [0, 0, 300, 100])
    assert c._rebalanced(current, later) is None


def test_no_look_before_enough_new_queries() -> None:
    current = Placement(1, GROUPS, ((0,), (0,), (1,), (2,)), (0, 1, 2), replicas=1)
    seen = states([60, 60, 0, 0], [0, 0, 10, 0], [0, 0, 0, 10])
    # 140 queries served; 200 needed (and 20 a member shard: 60).
    assert coordinator(min_queries=200)._rebalanced(current, seen) is None


def costed(queries: int, query_s: float, stores: int, store_s: float) -> pb.ShardState:
    return pb.ShardState(query_calls=queries, query_cpu_s=query_s, store_calls=stores, store_cpu_s=store_s)


def test_the_store_weight_is_the_measured_cost_of_a_store_over_a_query() -> None:
    # Two shards: 300 queries in 0.6 s (2 ms each), 200 stores in 0.1 s (0.5 ms each).
    seen = [costed(100, 0.2, 150, 0.05), costed(200, 0.4, 50, 0.05)]
    assert store_weight(seen) == pytest.approx(0.25)


def test_the_store_weight_is_assumed_until_both_costs_were_measured() -> None:
    few = MIN_COST_SAMPLES - 1
    assert store_weight([costed(1000, 1.0, few, 0.001)]) == DEFAULT_STORE_WEIGHT
    assert store_weight([costed(few, 1.0, 1000, 0.001)]) == DEFAULT_STORE_WEIGHT
    assert store_weight([]) == DEFAULT_STORE_WEIGHT


def test_a_shard_reporting_nonsense_costs_is_left_out_and_the_weight_bounded() -> None:
    good = costed(200, 0.2, 200, 0.1)
    assert store_weight([good, costed(10**9, math.nan, 10**9, 1.0)]) == 0.5
    assert store_weight([good, costed(10**9, -1.0, 10**9, 1.0)]) == 0.5
    assert store_weight([costed(200, 0.001, 200, 1000.0)]) == MAX_STORE_WEIGHT


def test_where_a_store_costs_as_much_as_a_query_the_coordinator_moves_rather_than_copies() -> None:
    # Shard 0 holds the hot group 0 (300 queries) with shard 1, and group 1 (60) with
    # shard 2; shard 3 is idle. With stores nearly free more replicas spread group 0;
    # with stores measured as costly as queries a replica spreads nothing (each owner
    # stores every slice), so a group moves off shard 0 instead.
    groups = ((0, 1), (1, 2))
    current = Placement(1, groups, ((0, 1), (0, 2)), (0, 1, 2, 3), replicas=2)
    per_shard = [[150, 30], [150, 0], [0, 30], [0, 0]]

    def seen(store_s: float) -> dict[int, pb.ShardState]:
        return {
            m: pb.ShardState(
                shard_id=m,
                **served(q),
                query_calls=300,
                query_cpu_s=0.3,
                store_calls=300,
                store_cpu_s=store_s,
            )
            for m, q in enumerate(per_shard)
        }

    load = {0: 300.0, 1: 60.0}
    costly = coordinator()._rebalanced(current, seen(0.3))
    assert costly is not None
    assert [len(o) for o in costly.owners] == [2, 2]
    assert max(shard_loads(costly, load, 1.0).values()) < max(shard_loads(current, load, 1.0).values())
    cheap = coordinator()._rebalanced(current, seen(0.003))
    assert cheap is not None
    assert len(cheap.owners[0]) > 2


def test_members_keep_their_groups_while_gone_briefly_or_still_starting() -> None:
    def present(now: float) -> set[int]:
        # Shard 0 live; 1 seen at t=100; 2 seen at t=104; 3 never seen (the coordinator
        # started at t=90).
        seen = {0: now, 1: 100.0, 2: 104.0}
        return present_members(range(4), {0}, seen, started=90.0, now=now, grace_s=5.0, start_grace_s=60.0)

    assert present(104.9) == {0, 1, 2, 3}
    assert present(105.0) == {0, 2, 3}  # 1 gone for the grace: its groups move
    assert present(149.9) == {0, 3}  # 3 never started: it keeps its groups for the start grace
    assert present(150.0) == {0}


def test_served_load_reads_the_sparse_lists_and_refuses_what_does_not_check_out() -> None:
    st = pb.ShardState(shard_id=0, served_groups=[1, 3], served_queries=[7, 2])
    assert served_load(st, 4) == {1: 7, 3: 2}
    assert served_load(pb.ShardState(shard_id=0), 4) == {}
    for bad in (
        pb.ShardState(served_groups=[1, 3], served_queries=[7]),  # lengths differ
        pb.ShardState(served_groups=[1, 1], served_queries=[7, 2]),  # a group twice
        pb.ShardState(served_groups=[4], served_queries=[7]),  # beyond the groups
    ):
        with pytest.raises(WireError):
            served_load(bad, 4)


def test_a_shard_whose_load_does_not_check_out_is_left_out_of_the_rebalancing() -> None:
    # The same hot layout as above, where moving a group off shard 0 is taken; a fourth shard
    # claims a huge load on a group beyond the placement: ignored, the decision is unchanged.
    current = Placement(1, GROUPS, ((0,), (0,), (1,), (2,)), (0, 1, 2), replicas=1)
    seen = states([60, 60, 0, 0], [0, 0, 10, 0], [0, 0, 0, 10])
    liar = pb.ShardState(shard_id=3, served_groups=[9], served_queries=[10**9])
    honest = coordinator()._rebalanced(current, seen)
    with_liar = coordinator()._rebalanced(current, {**seen, 3: liar})
    assert honest is not None and with_liar is not None
    assert with_liar.owners == honest.owners


def _view(live: set[int], draining: frozenset[int] = frozenset(), present: set[int] | None = None) -> View:
    return (frozenset(live), frozenset(draining), frozenset(live if present is None else present))


def test_a_settled_coordinator_asks_the_shards_only_every_interval() -> None:
    quiet = {
        "acting": True,
        "settled": True,
        "confirmed": True,
        "dirty": False,
        "learning": False,
        "interval_s": 10.0,
    }
    v = _view({0, 1, 2})
    assert not must_look(view=v, last_view=v, since_look_s=9.9, **quiet)  # type: ignore[arg-type]
    assert must_look(view=v, last_view=v, since_look_s=10.0, **quiet)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    "change",
    [
        {"acting": False},  # taking over: it reads everyone first
        {"settled": False},  # a handoff: the learners' progress is in the states
        {"confirmed": False},
        {"dirty": True},  # a shard did not confirm an adoption
        {"learning": True},  # no whole window of load seen yet: the first rebalancing waits on it
        {"view": _view({0, 1})},  # a shard went
        {"view": _view({0, 1, 2, 3})},  # one came
        {"view": _view({0, 1, 2}, draining=frozenset({2}))},  # one began draining
        {"view": _view({0, 1, 2}, present={0, 1, 2, 5})},  # a member's grace ran out, or began
    ],
)
def test_the_coordinator_looks_at_once_when_anything_changed(change: dict[str, object]) -> None:
    v = _view({0, 1, 2})
    args: dict[str, object] = {
        "acting": True,
        "settled": True,
        "confirmed": True,
        "dirty": False,
        "learning": False,
        "interval_s": 10.0,
        "view": v,
        "last_view": v,
        "since_look_s": 0.5,
    }
    assert not must_look(**args)  # type: ignore[arg-type]
    assert must_look(**{**args, **change})  # type: ignore[arg-type]


def test_learning_ends_with_a_balanced_load_or_after_a_few_windows() -> None:
    # Balanced already: nothing to learn.
    even = Placement(1, GROUPS, ((0,), (1,), (2,), (0, 1, 2)), (0, 1, 2), replicas=1)
    c = coordinator(target=1.2)
    assert c._rebalanced(even, states([300, 0, 0, 100], [0, 300, 0, 100], [0, 0, 300, 100])) is None
    assert not c._learning
    # Unbalanced, and no move gains enough (the 5 % case above): it looks again at the next
    # windows, LEARNING_LOOKS of them, then only every state_interval_s. A rebalancing does not
    # end it either: the first windows of a run may plan on loads that still shift.
    current = Placement(1, GROUPS, ((0,), (0,), (1,), (2,)), (0, 1, 2), replicas=1)
    c = coordinator()
    per_shard = ([95, 10, 0, 0], [0, 0, 100, 0], [0, 0, 0, 50])
    for look in range(1, LEARNING_LOOKS + 1):
        grown = states(*([n * look for n in q] for q in per_shard))
        assert c._rebalanced(current, grown) is None
        assert c._learning == (look < LEARNING_LOOKS)
    c = coordinator()
    assert c._rebalanced(current, states([60, 60, 0, 0], [0, 0, 10, 0], [0, 0, 0, 10])) is not None
    assert c._learning


def test_the_store_weight_is_read_over_the_window_since_the_last_look_when_it_has_enough() -> None:
    # Since the start: stores 0.5 ms, queries 1 ms (weight 0.5); over the last window queries
    # cost 2 ms (the index has filled), stores the same: 0.25.
    start = [costed(200, 0.2, 200, 0.1)]
    later = [costed(400, 0.6, 400, 0.2)]
    assert store_weight(later) == pytest.approx(1 / 3)  # (0.2 / 400) / (0.6 / 400)
    assert store_weight(later, cost_totals(start)) == pytest.approx(0.25)
    # Too few new samples, or a shard restarted (sums went down): since the start instead.
    assert store_weight([costed(250, 0.25, 250, 0.125)], cost_totals(start)) == pytest.approx(0.5)
    assert store_weight(start, cost_totals(later)) == pytest.approx(0.5)


def test_a_placement_reason_is_named_as_the_metrics_name_it() -> None:
    assert reason_name(pb.PlacementReason.PLACEMENT_REASON_HANDOFF_DONE) == "handoff_done"
    assert reason_name(pb.PlacementReason.PLACEMENT_REASON_REBALANCE) == "rebalance"
    assert reason_name(99) == "unspecified"  # a value from a newer schema


def test_group_changes_name_the_holders_each_step_of_a_handoff_adds_and_removes() -> None:
    groups = ((0, 1), (1, 2))
    settled = Placement(4, groups, ((0, 1), (2,)), (0, 1, 2, 3), replicas=1)
    # Group 0 moves from shard 0 to 3: 3 learns and 0 leaves, then 3 owns and 0 has let go.
    moving = Placement(
        5, groups, ((0, 1), (2,)), (0, 1, 2, 3), replicas=1, learners=((3,), ()), leaving=((0,), ())
    )
    done = Placement(6, groups, ((1, 3), (2,)), (0, 1, 2, 3), replicas=1)
    first = group_changes(settled, moving)
    assert [(c.group, list(c.gained), list(c.lost)) for c in first] == [(0, [3], [0])]
    second = group_changes(moving, done)
    assert [(c.group, list(c.gained), list(c.lost)) for c in second] == [(0, [], [0])]
    assert group_changes(done, done) == []
