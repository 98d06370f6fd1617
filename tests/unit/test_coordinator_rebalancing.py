"""When the coordinator rebalances (its rule over the load the shards report; the
placement arithmetic itself is tested in test_placement.py).

The coordinator runs inside an index shard; here it is given a stand-in holding only
what ``_rebalanced`` reads (settings, a logger), and shard states as the shards send
them (``ShardState.group_queries``: partial queries served per group since the shard
started)."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

from swarmrec.core.placement import Placement, shard_loads
from swarmrec.services.coordinator import MIN_GAIN, Coordinator
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


def states(*per_shard: list[int]) -> dict[int, pb.ShardState]:
    return {m: pb.ShardState(shard_id=m, group_queries=q) for m, q in enumerate(per_shard)}


def test_a_move_that_lowers_the_busiest_load_by_less_than_the_gain_moves_nothing() -> None:
    # Shard 0 holds groups 0 and 1 (95 + 10), shard 1 group 2 (100), shard 2 group 3 (50).
    # Moving group 0 onto shard 2 is the only step: the busiest goes from 105 to 100 (5 %).
    current = Placement(1, GROUPS, ((0,), (0,), (1,), (2,)), (0, 1, 2), replicas=1)
    load = {0: 95.0, 1: 10.0, 2: 100.0, 3: 50.0}
    assert max(shard_loads(current, load).values()) == 105.0
    seen = states([95, 10, 0, 0], [0, 0, 100, 0], [0, 0, 0, 50])
    assert coordinator()._rebalanced(current, seen) is None


def test_a_move_that_lowers_the_busiest_load_by_the_gain_is_taken() -> None:
    # Shard 0 holds groups 0 and 1 (60 + 60); the others 10 each: a replica of each hot
    # group elsewhere halves the busiest load, far more than MIN_GAIN.
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
    c = coordinator()
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
