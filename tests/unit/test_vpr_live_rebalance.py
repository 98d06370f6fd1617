"""The live re-balancing's computation (swarmrec.vpr.live): tables on the wire and their
checks, one owner's load, merging the owners' loads, the next table."""

from __future__ import annotations

import math

import numpy as np
import pytest

from swarmrec.errors import ConfigError, WireError
from swarmrec.vpr.balance import RebalanceRule, replica_owners
from swarmrec.vpr.clusters import Router, random_assignment
from swarmrec.vpr.live import MAX_CLUSTERS, LiveTable, Window, merge_loads, next_table, owner_load
from swarmrec.wire import messages as pb
from swarmrec.wire.vpr import load_from_proto, load_to_proto, table_from_proto, table_to_proto

D, N, C = 8, 3, 2


def unit_rows(n: int, seed: int) -> np.ndarray:
    x = np.random.default_rng(seed).normal(size=(n, D)).astype(np.float32)
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def start_table() -> LiveTable:
    return LiveTable(Router(unit_rows(N * C, 1), random_assignment(N, C, 0)))


def test_a_table_survives_the_wire_exactly() -> None:
    t = start_table()
    back = table_from_proto(table_to_proto(t), D, N)
    assert back.version == 0 and back.assignment.owners == t.assignment.owners
    assert np.array_equal(back.centres, t.centres) and back.copy_margin == -1.0


@pytest.mark.parametrize(
    ("change", "text"),
    [
        ({"dimension": D + 1}, "dimension"),
        ({"owners": []}, "1 to"),
        ({"owners": [N] * (N * C)}, "robots below"),
        ({"centres": b"\x00" * 7}, "bytes"),
        ({"copy_margin": math.nan}, "copy_margin"),
        ({"copy_neighbours": 0}, "copy_neighbours"),
        ({"copy_neighbours": N + 1}, "copy_neighbours"),
    ],
)
def test_a_bad_table_is_refused_with_its_reason(change: dict[str, object], text: str) -> None:
    msg = table_to_proto(start_table())
    if "owners" in change:
        del msg.owners[:]
        msg.owners.extend(change.pop("owners"))  # type: ignore[arg-type]
    for name, value in change.items():
        setattr(msg, name, value)
    with pytest.raises(WireError, match=text):
        table_from_proto(msg, D, N)


def test_non_finite_centres_and_too_many_clusters_are_refused() -> None:
    msg = table_to_proto(start_table())
    c = np.frombuffer(msg.centres, "<f4").copy()
    c[0] = np.inf
    msg.centres = c.tobytes()
    with pytest.raises(WireError, match="finite"):
        table_from_proto(msg, D, N)
    big = table_to_proto(start_table())
    big.owners.extend([0] * MAX_CLUSTERS)
    with pytest.raises(WireError, match="clusters"):
        table_from_proto(big, D, N)


def test_an_owner_splits_only_its_own_hot_cluster_and_counts_every_query() -> None:
    t = start_table()
    mine = t.assignment.clusters_of(0)
    hot = mine[0]
    # 40 queries around the hot centre, two elsewhere.
    rng = np.random.default_rng(5)
    near = t.centres[hot] + rng.normal(scale=0.05, size=(40, D)).astype(np.float32)
    w = Window(0)
    for row in near / np.linalg.norm(near, axis=1, keepdims=True):
        w.add(row.astype(np.float32))
    load = owner_load(t, 0, w, split_above=10, seed=0)
    assert load.loads.sum() == 40 and len(load.gaps) == 40
    assert set(load.replaced) <= set(mine) and hot in load.replaced
    new = load.new_centres
    assert len(new) >= 1 and len(load.loads) == N * C + len(new)
    # On the wire and back, the same load.
    back = load_from_proto(load_to_proto(load), D)
    assert np.array_equal(back.new_centres, new) and np.array_equal(back.loads, load.loads)
    assert np.array_equal(back.pair_count, load.pair_count) and back.replaced == load.replaced
    # Without a capacity to pass, nothing splits.
    same = owner_load(t, 0, w, split_above=math.inf, seed=0)
    assert same.replaced == () and len(same.new_centres) == 0 and same.loads.sum() == 40


def test_merged_halves_are_numbered_after_k_in_robot_order_and_loads_add_up() -> None:
    t = start_table()
    loads = []
    for robot in (2, 0, 1):  # any order
        own = t.assignment.clusters_of(robot)
        near = t.centres[own[0]] + np.random.default_rng(robot).normal(scale=0.05, size=(30, D))
        w = Window(0)
        for row in (near / np.linalg.norm(near, axis=1, keepdims=True)).astype(np.float32):
            w.add(row)
        loads.append(owner_load(t, robot, w, split_above=5, seed=0))
    merged = merge_loads(t, loads)
    assert merged.queries == 90
    halves = {m.robot: m.new_centres for m in loads}
    at = N * C
    for robot in range(N):
        got = merged.centres[at : at + len(halves[robot])]
        assert np.array_equal(got, halves[robot])
        at += len(halves[robot])
    assert at == len(merged.centres)
    assert (merged.report.adjacency == merged.report.adjacency.T).all()


def test_a_replaced_centre_counts_only_from_its_owner_and_a_load_of_another_version_is_refused() -> None:
    t = start_table()
    other = t.assignment.clusters_of(1)[0]
    w = Window(0)
    w.add(t.centres[0])
    msg = load_to_proto(owner_load(t, 0, w, math.inf, 0))
    msg.replaced.append(other)
    msg.replaced_centres = np.zeros(D, "<f4").tobytes()
    merged = merge_loads(t, [load_from_proto(msg, D)])
    assert np.array_equal(merged.centres[other], t.centres[other])
    msg.version = 7
    with pytest.raises(ConfigError, match="version 7"):
        merge_loads(t, [load_from_proto(msg, D)])
    bad = load_to_proto(owner_load(t, 0, w, math.inf, 0))
    bad.pair_a.append(10**6)
    bad.pair_b.append(0)
    bad.pair_count.append(1)
    with pytest.raises(ConfigError, match="pairs"):
        merge_loads(t, [load_from_proto(bad, D)])
    with pytest.raises(WireError, match="whole rows"):
        load_from_proto(pb.ClusterLoad(new_centres=b"\x00" * 5), D)


def test_the_next_table_is_the_next_version_with_the_rules_copy_margin() -> None:
    t = start_table()
    w = Window(0)
    for row in unit_rows(60, 9):
        w.add(row)
    merged = merge_loads(t, [owner_load(t, r, w, math.inf, 0) for r in range(N)])
    every = next_table(t, merged, RebalanceRule(clusters_per_robot=C))
    assert (
        every.version == 1 and every.copy_margin == math.inf and every.assignment.method == "load-adjacency"
    )
    half = next_table(t, merged, RebalanceRule(clusters_per_robot=C, replica_share=0.5))
    assert half.copy_margin == pytest.approx(float(np.quantile(merged.gaps, 0.5)))
    none = next_table(t, merged, RebalanceRule(clusters_per_robot=C, replica_share=0.0))
    assert not none.copies
    again = next_table(
        every,
        merge_loads(every, [owner_load(every, r, Window(1, 0, list(w.rows)), math.inf, 0) for r in range(N)]),
        RebalanceRule(clusters_per_robot=C),
    )
    assert again.version == 2 and again.assignment.method == "load-adjacency-repair"


def test_holders_are_the_owner_and_the_offline_copy_rule() -> None:
    t = start_table()
    x = unit_rows(50, 3)
    merged = merge_loads(t, [owner_load(t, 0, Window(0, 0, list(x)), math.inf, 0)])
    nt = next_table(t, merged, RebalanceRule(clusters_per_robot=C))
    holders = nt.holders(x)
    owners = nt.router.route_many(x)[1]
    copies = replica_owners(nt.centres, nt.assignment, x, math.inf, 2)
    assert nt.copy_neighbours == 2  # the default rule's
    for h, o, c in zip(holders, owners, copies, strict=True):
        assert h == {int(o)} | {int(r) for r in c if r >= 0}
        assert len(h) == 3  # every descriptor has two copies at other robots


def test_a_table_change_rebuilds_the_whole_table_and_is_refused_off_its_base() -> None:
    from swarmrec.errors import FailedPrecondition, InvalidArgument
    from swarmrec.services.place_owner import WHOLE_TABLE, _applied, _delta

    t = start_table()
    w = Window(0)
    hot = t.centres[t.assignment.clusters_of(0)[0]]
    near = hot + np.random.default_rng(4).normal(scale=0.05, size=(40, D))
    for row in (near / np.linalg.norm(near, axis=1, keepdims=True)).astype(np.float32):
        w.add(row)
    merged = merge_loads(t, [owner_load(t, r, w if r == 0 else Window(0), 10, 0) for r in range(N)])
    new = next_table(t, merged, RebalanceRule(clusters_per_robot=C))
    change = _delta(t, new)
    assert change.table.centres == b"" and len(change.appended_centres) > 0  # a split: only its rows
    rebuilt = table_from_proto(_applied(change, t, D), D, N)
    assert np.array_equal(rebuilt.centres, new.centres) and rebuilt.assignment.owners == new.assignment.owners
    with pytest.raises(FailedPrecondition, match=WHOLE_TABLE):
        _applied(change, new, D)  # not on the base version
    # The split's new centres are exactly int8 codes' (made so by the owner): 4 + d bytes a row.
    assert change.centres_encoding == pb.DescriptorEncoding.DESCRIPTOR_ENCODING_INT8
    assert len(change.appended_centres) % (4 + D) == 0
    change.replaced.append(10**6)
    change.replaced_centres += bytes(4 + D)
    with pytest.raises(InvalidArgument, match="below"):
        _applied(change, t, D)


def test_a_capacity_that_would_split_into_too_many_clusters_is_refused() -> None:
    from swarmrec.vpr.live import MAX_SPLITS, split_allowed

    assert split_allowed(0, 0.0) and split_allowed(10_000, math.inf)
    assert split_allowed(MAX_SPLITS * 10, 10.0) and not split_allowed(MAX_SPLITS * 10, 9.99)
    # A swarm's own capacity, 1.25 x an even share, is allowed for any robot count up to MAX_SPLITS.
    assert split_allowed(60_000, 1.25 * 60_000 / MAX_SPLITS)
