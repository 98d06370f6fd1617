"""What the live view draws of a SLAM team: trajectories, objects and separators from the
answers the slam services give (keys written here by hand as gtsam lays them out: the
character in the top 8 bits, the index below)."""

from __future__ import annotations

import itertools
import math

from swarmrec.services.live_view_slam import MAX_POSES, separator_keys, slam_robot_view, trajectory
from swarmrec.wire import messages as pb


def key(char: str, index: int) -> int:
    return (ord(char) << 56) | index


def pose_values(x: float, y: float) -> list[float]:
    # Identity rotation row by row, then the translation.
    return [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, x, y, 7.0]


def estimate(vertices: list[tuple[int, float, float]]) -> pb.SlamEstimate:
    values: list[float] = []
    for _, x, y in vertices:
        values += pose_values(x, y)
    return pb.SlamEstimate(robot_id=1, keys=[k for k, _, _ in vertices], values=values)


def test_poses_are_drawn_in_index_order_and_objects_apart() -> None:
    e = estimate(
        [(key("b", 2), 2.0, 0.5), (key("B", 0), 9.0, 9.0), (key("b", 0), 0.0, 0.0), (key("b", 1), 1.0, 0.25)]
    )
    poses, objects, where = trajectory(e)
    assert poses == [[0.0, 0.0], [1.0, 0.25], [2.0, 0.5]]
    assert objects == [[9.0, 9.0]]
    assert where[key("B", 0)] == [9.0, 9.0] and len(where) == 4


def test_a_long_trajectory_is_thinned_evenly_and_keeps_its_last_pose() -> None:
    n = 1001
    poses, _, _ = trajectory(estimate([(key("a", i), float(i), 0.0) for i in range(n)]))
    assert len(poses) <= MAX_POSES
    assert poses[0] == [0.0, 0.0] and poses[-1] == [float(n - 1), 0.0]
    steps = {round(b[0] - a[0]) for a, b in itertools.pairwise(poses[:-1])}
    assert steps == {3}  # ceil(1001 / 400); the last pose is 1000, one after 999


def test_a_malformed_estimate_draws_nothing() -> None:
    short = pb.SlamEstimate(keys=[key("a", 0), key("a", 1)], values=pose_values(0, 0))
    assert trajectory(short) == ([], [], {})
    bad = estimate([(key("a", 0), 0.0, 0.0), (key("a", 1), math.nan, 1.0)])
    assert trajectory(bad) == ([], [], {})
    infinite = estimate([(key("a", 0), math.inf, 0.0)])
    assert trajectory(infinite) == ([], [], {})


def test_separators_are_the_first_keys_sent_to_each_neighbour() -> None:
    steps = [
        pb.SlamStep(receiver_robot_id=2, keys=[]),  # a step to a non-neighbour carries no keys
        pb.SlamStep(receiver_robot_id=0, keys=[key("b", 1), key("B", 0)]),
        pb.SlamStep(receiver_robot_id=0, keys=[key("b", 9)]),
        pb.SlamStep(receiver_robot_id=3, keys=[key("b", 2)]),
    ]
    assert separator_keys(steps) == {0: [key("b", 1), key("B", 0)], 3: [key("b", 2)]}


def test_a_robot_view_places_each_separator_at_its_vertex() -> None:
    e = estimate([(key("b", 0), 0.0, 0.0), (key("b", 1), 1.0, 0.0), (key("B", 0), 4.0, 4.0)])
    status = pb.SlamStatus(
        robot_id=1,
        solve_id=3,
        state=pb.SlamState.SLAM_STATE_DONE,
        linearisation=2,
        iteration=5,
        converged=True,
    )
    shared = {0: [key("b", 1), key("B", 0)], 2: [key("b", 7)]}  # b7 is not in the estimate
    view = slam_robot_view(status, e, shared, 1)
    assert view["state"] == "done" and view["stage"] == "pose 2" and view["iteration"] == 5
    assert view["separators"] == [{"with": 0, "at": [1.0, 0.0]}, {"with": 0, "at": [4.0, 4.0]}]
    assert view["poses"] == [[0.0, 0.0], [1.0, 0.0]] and view["objects"] == [[4.0, 4.0]]


def test_a_robot_that_does_not_answer_is_shown_so() -> None:
    view = slam_robot_view(None, None, {}, 4, error="no reply")
    assert view["state"] == "not answering" and view["error"] == "no reply" and view["poses"] == []


def test_the_keys_read_are_the_slam_packages_symbols() -> None:
    from swarmrec.slam.keys import landmark_key, pose_key

    e = estimate([(pose_key(2, 1), 1.0, 1.0), (pose_key(2, 0), 0.0, 0.0), (landmark_key(2, 0), 5.0, 5.0)])
    poses, objects, _ = trajectory(e)
    assert poses == [[0.0, 0.0], [1.0, 1.0]] and objects == [[5.0, 5.0]]
