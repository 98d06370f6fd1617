"""ATE*, ARE* (the paper's Eq. 1-2) on hand-computed cases, and the cost against gtsam's own."""

from __future__ import annotations

import math

import numpy as np
import pytest

from swarmrec.slam.centralized import gtsam_graph, gtsam_values
from swarmrec.slam.graph import Edge, PoseGraph
from swarmrec.slam.keys import landmark_key, pose_key
from swarmrec.slam.lie import Pose, so3_exp
from swarmrec.slam.metrics import accuracy, are_star, ate_star
from tests.slam_graphs import make_graph

A0, A1, B0, OBJ = pose_key(0, 0), pose_key(0, 1), pose_key(1, 0), landmark_key(0, 0)


def at(x: float, y: float, z: float, yaw_deg: float = 0.0) -> Pose:
    return Pose(so3_exp([0.0, 0.0, math.radians(yaw_deg)]), np.array([x, y, z]))


def test_ate_star_is_the_root_mean_square_position_error() -> None:
    reference = {A0: at(0, 0, 0), A1: at(1, 0, 0), B0: at(0, 1, 0)}
    # errors 3-4-5 (5 m), 0 m and 1 m: sqrt((25 + 0 + 1) / 3)
    estimate = {A0: at(3, 4, 0), A1: at(1, 0, 0), B0: at(0, 1, 1)}
    assert ate_star(estimate, reference, [A0, A1, B0]) == pytest.approx(math.sqrt(26 / 3))


def test_are_star_is_the_root_mean_square_rotation_angle() -> None:
    reference = {A0: at(0, 0, 0, 10.0), A1: at(0, 0, 0, -20.0)}
    # angles 30 and 40 degrees about z: sqrt((30^2 + 40^2) / 2) degrees
    estimate = {A0: at(5, 0, 0, 40.0), A1: at(0, 0, 0, 20.0)}
    got = math.degrees(are_star(estimate, reference, [A0, A1]))
    assert got == pytest.approx(math.sqrt((30**2 + 40**2) / 2))


def test_accuracy_reports_poses_and_objects_separately() -> None:
    info = np.eye(6)
    graph = PoseGraph(
        {A0: at(0, 0, 0), A1: at(1, 0, 0), OBJ: at(2, 0, 0)},
        (Edge(A0, A1, at(1, 0, 0), info), Edge(A1, OBJ, at(1, 0, 0), info)),
    )
    estimate = {A0: at(0, 0, 0), A1: at(1, 0, 2), OBJ: at(2, 3, 0, 90.0)}
    result = accuracy(graph, estimate, graph.poses)
    assert result.ate_poses == pytest.approx(math.sqrt(4 / 2))
    assert result.ate_landmarks == pytest.approx(3.0)
    assert result.are_poses_deg == pytest.approx(0.0)
    assert result.are_landmarks_deg == pytest.approx(90.0)
    assert result.reference_cost == pytest.approx(0.0)


@pytest.mark.parametrize("seed", range(3))
def test_cost_is_the_error_gtsam_reports(seed: int) -> None:
    graph, _ = make_graph(2, 4, sigma_r=0.2, sigma_t=0.3, seed=seed, initial_noise=0.3)
    assert graph.cost() == pytest.approx(gtsam_graph(graph).error(gtsam_values(graph.poses)), rel=1e-9)
