"""The offline swarm: robots, lock-step order, the PR/AUC protocol, balance and bytes, by hand."""

from __future__ import annotations

import numpy as np
import pytest

from swarmrec.errors import ConfigError
from swarmrec.vpr.simulation import (
    Answers,
    Reassignment,
    answers_curve,
    arrival_order,
    bytes_per_query,
    eligible,
    robot_of_frames,
    run_queries,
    worst_balance_ratio,
)


def test_frames_are_cut_into_consecutive_runs_of_ceil_n_over_robots() -> None:
    # 10 frames, 3 robots: ceil(10 / 3) = 4, so 4 + 4 + 2.
    assert robot_of_frames(10, 3).tolist() == [0, 0, 0, 0, 1, 1, 1, 1, 2, 2]
    with pytest.raises(ConfigError):
        robot_of_frames(2, 3)


def test_robots_query_in_lock_step() -> None:
    robots = robot_of_frames(10, 3)
    # Step 0: frames 0, 4, 8; step 1: 1, 5, 9; then robot 2 has no frames left.
    assert arrival_order(robots).tolist() == [0, 4, 8, 1, 5, 9, 2, 6, 3, 7]


def test_a_query_could_match_earlier_frames_of_other_robots_only() -> None:
    robots = np.array([0, 0, 1, 1])
    order = arrival_order(robots)  # 0, 2, 1, 3
    assert order.tolist() == [0, 2, 1, 3]
    expected = np.zeros((4, 4), bool)
    expected[2, 0] = True  # frame 2 arrives after frame 0
    expected[1, 2] = True  # frame 1 after frame 2 (frame 0 is its own robot's)
    expected[3, 0] = expected[3, 1] = True  # frame 3 after 0 and 1 (2 is its own robot's)
    np.testing.assert_array_equal(eligible(robots, order), expected)


def test_the_pr_walk_and_auc_on_four_queries_by_hand() -> None:
    robots = np.array([0, 0, 1, 1])
    pairs = eligible(robots, arrival_order(robots))
    closures = np.zeros((4, 4), bool)
    closures[2, 0] = closures[3, 1] = True
    # Answers: frame 0 none; 2 -> 0 at 0.1 (true); 3 -> 1 at 0.3 (true); 1 -> 2 at 0.5 (false).
    answers = Answers(
        owners=np.zeros(4, np.int64),
        matches=np.array([-1, 2, 0, 1]),
        distances=np.array([np.inf, 0.5, 0.1, 0.3]),
    )
    curve = answers_curve(answers, closures, pairs)
    # Walk by distance: 2 (TP), 3 (TP), 1 (FP), 0 (no answer: FP). Two queries have a true match.
    np.testing.assert_allclose(curve.recall, [0.5, 1.0, 1.0, 1.0], atol=1e-9)
    np.testing.assert_allclose(curve.precision, [1.0, 1.0, 2 / 3, 0.5], atol=1e-9)
    assert curve.relevant == 2
    assert curve.auc == pytest.approx(0.5)  # precision 1 from recall 0.5 to 1
    # The same but frame 3's true match sits in another cell: it has no answer. Its closure still
    # counts in recall, which now stops at 0.5: no area.
    cut = Answers(answers.owners, np.array([-1, 2, 0, -1]), np.array([np.inf, 0.5, 0.1, np.inf]))
    curve = answers_curve(cut, closures, pairs)
    np.testing.assert_allclose(curve.recall, [0.5, 0.5, 0.5, 0.5], atol=1e-9)
    assert curve.relevant == 2 and curve.auc == pytest.approx(0.0)


def test_worst_balance_ratio_by_hand() -> None:
    # 8 queries over 4 robots: an even share is 2; robot 1 got 4 -> 2.0.
    assert worst_balance_ratio(np.array([0, 1, 1, 1, 1, 2, 3, 3]), 4) == pytest.approx(2.0)
    assert worst_balance_ratio(np.array([0, 1, 2, 3]), 4) == pytest.approx(1.0)
    assert worst_balance_ratio(np.array([2, 2, 2]), 3) == pytest.approx(3.0)  # one robot gets all
    with pytest.raises(ConfigError):
        worst_balance_ratio(np.array([4]), 4)


def test_the_byte_model_counts_only_queries_sent_to_another_robot() -> None:
    robots = np.array([0, 0, 1, 1])
    # Two of four queries go to another robot: 0.5 x (512 + 5) up, 0.5 x 13 down.
    answers = Answers(np.array([0, 1, 1, 0]), np.full(4, -1), np.full(4, np.inf))
    cost = bytes_per_query(answers, robots, 512)
    assert cost == pytest.approx(
        {"remote_share": 0.5, "replica_share": 0.0, "up": 258.5, "down": 6.5, "total": 265.0}
    )
    # Frame 0 also stored at robot 1 (remote), frame 3 at robot 1 (its own robot: free): one more
    # upload of 517 B in four queries.
    twice = Answers(answers.owners, answers.matches, answers.distances, 0, np.array([1, -1, -1, 1]))
    cost = bytes_per_query(twice, robots, 512)
    assert cost["replica_share"] == 0.25 and cost["up"] == pytest.approx(0.75 * 517)


def test_queries_run_through_owner_indexes_and_a_reassignment_moves_what_was_stored() -> None:
    x = np.array([[1, 0], [0, 1], [1, 0], [0, 1]], np.float32)
    robots = np.array([0, 0, 1, 1])
    order = arrival_order(robots)  # 0, 2, 1, 3
    # Frames 0 and 2 are the same place (identical), so are 1 and 3; owners split them.
    split = run_queries(x, robots, np.array([0, 1, 1, 0]), order)
    # Each owner only ever holds the other place: 1 gets 2 back and 3 gets 0, both 2 apart.
    assert split.matches.tolist() == [-1, 2, -1, 0]
    np.testing.assert_allclose(split.distances, [np.inf, 2.0, np.inf, 2.0])
    together = run_queries(x, robots, np.array([0, 1, 0, 1]), order)
    assert together.matches.tolist() == [-1, -1, 0, 1]
    # Start split; from the third query on, robot 0 owns everything: frames 0 and 2 move to it.
    moved = run_queries(x, robots, np.array([0, 0, 1, 0]), order, [Reassignment(2, np.zeros(4, np.int64))])
    assert moved.migrated == 1  # frame 2 was stored at robot 1
    # Query 1 (robot 0) now sees frame 2 at robot 0; query 3 (robot 1) finds frame 1, its place.
    assert moved.owners.tolist() == [0, 0, 1, 0] and moved.matches.tolist() == [-1, 2, -1, 1]


def test_a_frame_stored_twice_is_found_from_either_owner() -> None:
    x = np.array([[1, 0], [0, 1], [1, 0], [0, 1]], np.float32)
    robots = np.array([0, 0, 1, 1])
    order = arrival_order(robots)  # 0, 2, 1, 3
    # As in the split case above, but frame 0 is also stored at robot 1, where frame 2 goes.
    answers = run_queries(x, robots, np.array([0, 1, 1, 0]), order, replicas=np.array([1, -1, -1, -1]))
    assert answers.matches.tolist() == [-1, 2, 0, 0]
    assert answers.distances[2] == 0.0 and answers.replicas is not None
    assert answers.replicas.tolist() == [[1], [-1], [-1], [-1]]


def test_a_frame_stored_at_two_other_robots_is_found_from_each_and_both_copies_cost_bytes() -> None:
    x = np.array([[1, 0], [1, 0], [1, 0]], np.float32)  # one place, seen by three robots
    robots = np.array([0, 1, 2])
    order = arrival_order(robots)  # 0, 1, 2
    # Frame 0 goes to robot 0 and is also stored at robots 1 and 2 (its owner listed again is
    # no copy); frames 1 and 2 go to robots 1 and 2, which find it there.
    copies = np.array([[1, 2, 0], [-1, -1, -1], [-1, -1, -1]])
    answers = run_queries(x, robots, np.array([0, 1, 2]), order, replicas=copies)
    assert answers.matches.tolist() == [-1, 0, 0]
    assert answers.replicas is not None and answers.replicas.tolist()[0] == [1, 2, -1]
    # Two copies of frame 0 left its robot: 2 uploads of 517 B over 3 queries; no query was remote.
    cost = bytes_per_query(answers, robots, 512)
    assert cost["replica_share"] == pytest.approx(2 / 3) and cost["up"] == pytest.approx(2 / 3 * 517)


def test_a_reassignment_puts_copies_where_the_new_tables_say() -> None:
    x = np.array([[1, 0], [0, 1], [1, 0], [0, 1]], np.float32)
    robots = np.array([0, 0, 1, 1])
    order = arrival_order(robots)  # 0, 2, 1, 3
    # Frames 0 and 2 start at robot 0, frames 1 and 3 at robot 1. From the third query on,
    # everything belongs to robot 1 and frame 0 is also kept at robot 0.
    switch = Reassignment(2, np.ones(4, np.int64), replicas=np.array([0, -1, -1, -1]))
    answers = run_queries(x, robots, np.array([0, 1, 0, 1]), order, [switch])
    # Frame 2 moves to robot 1 and frame 0 is copied there (it stays at robot 0 as its copy): 2.
    assert answers.migrated == 2
    # Query 1 (robot 0) at robot 1 finds frame 2 (robot 1's, the other place: 2 apart); query 3
    # (robot 1) finds frame 1 (its place).
    assert answers.matches.tolist() == [-1, 2, 0, 1]
