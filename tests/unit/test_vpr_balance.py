"""Re-balancing from observed load: counts, the greedy table and hot-cluster splits, by hand."""

from __future__ import annotations

import numpy as np
import pytest

from swarmrec.errors import ConfigError
from swarmrec.vpr.balance import (
    LoadReport,
    RebalanceRule,
    balanced_assignment,
    boundary_margin,
    observe,
    repair_assignment,
    replica_owners,
    schedule,
    split_hot_clusters,
)
from swarmrec.vpr.clusters import Assignment


def test_observe_counts_queries_per_cluster_and_nearest_second_nearest_pairs() -> None:
    centres = np.array([[0.0], [1.0], [3.0]], np.float32)
    # 0.1: nearest 0, then 1. 0.9: nearest 1, then 0. 2.5: nearest 2 (3.0), then 1.
    report = observe(centres, np.array([[0.1], [0.9], [2.5]], np.float32))
    assert report.loads.tolist() == [1, 1, 1]
    assert report.adjacency.tolist() == [[0, 2, 0], [2, 0, 1], [0, 1, 0]]


def _report(loads: list[int], edges: dict[tuple[int, int], int]) -> LoadReport:
    adjacency = np.zeros((len(loads), len(loads)), np.int64)
    for (a, b), w in edges.items():
        adjacency[a, b] = adjacency[b, a] = w
    return LoadReport(np.array(loads, np.int64), adjacency)


def test_the_busiest_clusters_go_first_to_robots_with_room() -> None:
    # Two robots, 16 queries, slack 0: capacity 8. Cluster 0 (6) -> robot 0; 1 (3) no longer fits
    # robot 0 (9 > 8) -> robot 1; 2 (3) -> robot 1 (6); 3 (2) fits both, robot 0 touches it -> 0;
    # 4 (2) fits only robot 1.
    table = balanced_assignment(_report([6, 3, 3, 2, 2], {(0, 3): 5}), 2, slack=0.0)
    assert table.owners == (0, 1, 1, 0, 1)
    # The same loads, but cluster 3 touches cluster 1: it joins robot 1, and 4 goes to robot 0.
    table = balanced_assignment(_report([6, 3, 3, 2, 2], {(1, 3): 5}), 2, slack=0.0)
    assert table.owners == (0, 1, 1, 1, 0)
    assert table.method == "load-adjacency" and table.extra["observed_queries"] == 16


def test_a_cluster_with_no_room_anywhere_goes_to_the_least_loaded_robot() -> None:
    # Capacity (1.0) x 12 / 2 = 6: cluster 0 (10) fits nowhere -> the least loaded (robot 0);
    # cluster 1 (2) -> robot 1 (robot 0 is over capacity).
    assert balanced_assignment(_report([10, 2], {}), 2, slack=0.0).owners == (0, 1)
    with pytest.raises(ConfigError):
        balanced_assignment(_report([1], {}), 0)


def test_a_hot_cluster_is_split_in_two_on_its_own_descriptors() -> None:
    rng = np.random.default_rng(0)
    seen = np.concatenate([rng.normal((-1, 0), 0.05, (50, 2)), rng.normal((1, 0), 0.05, (50, 2))])
    centres = np.array([[0.0, 0.0], [0.0, 10.0]], np.float32)
    split = split_hot_clusters(centres, seen.astype(np.float32), max_load=60, seed=0)
    assert split.shape == (3, 2)
    np.testing.assert_array_equal(split[1], centres[1])  # untouched clusters keep their index
    assert sorted(np.round(split[[0, 2], 0]).tolist()) == [-1.0, 1.0]
    unchanged = split_hot_clusters(centres, seen.astype(np.float32), max_load=100, seed=0)
    np.testing.assert_array_equal(unchanged, centres)


def test_a_descriptor_near_a_boundary_is_also_stored_at_the_neighbours_owner() -> None:
    centres = np.array([[0.0], [2.0], [10.0]], np.float32)
    table = Assignment((0, 1, 1), 2)
    x = np.array([[0.9], [0.2], [1.9], [6.5]], np.float32)
    # Gaps d2^2 - d1^2: 0.9 -> 1.21 - 0.81 = 0.4 (cells 0, 1); 0.2 -> 3.24 - 0.04 = 3.2;
    # 1.9 -> 3.61 - 0.01 = 3.6 (cells 1, 0); 6.5 -> 20.25 - 12.25 = 8.0 (cells 2, 1).
    assert boundary_margin(centres, x, 0.25) == pytest.approx(np.quantile([0.4, 3.2, 3.6, 8.0], 0.25))
    assert boundary_margin(centres, x, 0.0) < 0  # nothing is copied
    # Margin 3.6: 0.9 and 0.2 are copied to robot 1, 1.9 to robot 0; 6.5's neighbour (cell 1) has
    # the same owner as its own cell (robot 1), so no copy.
    assert replica_owners(centres, table, x, 3.6).tolist() == [[1], [1], [0], [-1]]
    assert replica_owners(centres, table, x, 0.5).tolist() == [[1], [-1], [-1], [-1]]
    assert boundary_margin(centres, x, 1.0) == np.inf  # share 1: every descriptor


def test_copies_go_to_the_owners_of_the_next_cells_each_robot_once() -> None:
    # Cells at 0, 1, 2, 3 owned by robots 0, 1, 1, 2. A descriptor at 0.4: cells by distance
    # 0 (0.16), 1 (0.36), 2 (2.56), 3 (6.76); gaps 0.2, 2.4, 6.6 after its own cell's.
    centres = np.array([[0.0], [1.0], [2.0], [3.0]], np.float32)
    table = Assignment((0, 1, 1, 2), 3)
    x = np.array([[0.4]], np.float32)
    # Two neighbours, no margin: robot 1 (cell 1), cell 2 is robot 1 again, so robot 2 (cell 3).
    assert replica_owners(centres, table, x, np.inf, neighbours=2).tolist() == [[1, 2]]
    # A margin of 3 stops before cell 3 (gap 6.6): one copy, the other slot empty.
    assert replica_owners(centres, table, x, 3.0, neighbours=2).tolist() == [[1, -1]]
    # A descriptor at 2.9 is robot 2's (cell 3); cells 2 and 1 are both robot 1's, then robot 0.
    assert replica_owners(centres, table, np.array([[2.9]], np.float32), np.inf, 2).tolist() == [[1, 0]]


def test_a_cluster_stays_with_its_previous_owner_when_that_is_as_good() -> None:
    # Four equal clusters, two robots, no adjacency: from scratch 0 -> robot 0, 1 -> robot 1,
    # 2 -> robot 0, 3 -> robot 1 (least loaded, then lowest id).
    report = _report([2, 2, 2, 2], {})
    assert balanced_assignment(report, 2, slack=0.0).owners == (0, 1, 0, 1)
    # With a previous table (1, 0, 0, 1), each cluster keeps its owner: nothing has to move.
    previous = Assignment((1, 0, 0, 1), 2)
    assert balanced_assignment(report, 2, slack=0.0, previous=previous).owners == (1, 0, 0, 1)


def test_a_repair_moves_only_what_overloads_a_robot() -> None:
    # Robot 0 holds clusters 0, 1, 2 (loads 4, 3, 1: 8), robot 1 holds cluster 3 (load 2).
    # Capacity (slack 0) is 10 / 2 = 5: robot 0's busiest cluster that fits elsewhere is
    # cluster 0 (4 + 2 <= 5? no), then cluster 1 (3 + 2 = 5, yes): it moves; robot 0 is at 5.
    previous = Assignment((0, 0, 0, 1), 2)
    table = repair_assignment(_report([4, 3, 1, 2], {}), previous, slack=0.0)
    assert table.owners == (0, 1, 0, 1)
    # Loads 4, 0, 1, 0 and a new cluster 4 (a split half) of load 1; capacity 6 / 2 = 3. The new
    # cluster goes where there is room, robot 1 (load 1). Robot 0 (5) is over: cluster 0 (4) fits
    # nowhere, cluster 2 (1) moves to robot 1 (2); robot 0 is still at 4 but nothing else can move.
    table = repair_assignment(_report([4, 0, 1, 0, 1], {}), Assignment((0, 0, 0, 1), 2), slack=0.0)
    assert table.owners == (0, 0, 1, 1, 1)


@pytest.mark.parametrize(
    "knobs",
    [{"clusters_per_robot": 0}, {"neighbours": 0}, {"period_share": 1.0}, {"replica_share": 1.5},
     {"slack": -0.1}, {"slack": float("nan")}],
)  # fmt: skip
def test_a_rule_refuses_knobs_out_of_range(knobs: dict[str, float]) -> None:
    with pytest.raises(ConfigError):
        RebalanceRule(**knobs)  # type: ignore[arg-type]


def test_a_schedule_switches_tables_after_every_period_and_never_copies_to_the_owner() -> None:
    rng = np.random.default_rng(0)
    other = rng.normal(size=(200, 4)).astype(np.float32)
    x = rng.normal(size=(40, 4)).astype(np.float32)
    rule = RebalanceRule(clusters_per_robot=2, period_share=0.25, neighbours=2)
    plan = schedule(rule, x, np.arange(40, dtype=np.int64), other, n_robots=3, seed=0)
    # 40 queries in periods of 10: new tables after the 10th, 20th and 30th query.
    assert [s.at for s in plan.switches] == [10, 20, 30]
    assert plan.start.clusters_per_robot().tolist() == [2, 2, 2] and plan.period == 10
    for switch in plan.switches:
        assert switch.replicas is not None and switch.replicas.shape == (40, 2)
        assert not (switch.replicas == switch.owners[:, None]).any()
        assert set(switch.owners.tolist()) <= {0, 1, 2}
