"""Rigid alignment of matched points: exact recovery, reflections, outliers, degenerate input."""

from __future__ import annotations

import math

import numpy as np
import pytest

from swarmrec.slam.alignment import ransac_rigid, rigid_transform
from swarmrec.slam.errors import AlignmentError
from swarmrec.slam.keys import pose_key
from swarmrec.slam.lie import Pose, so3_exp

TRUE = Pose(so3_exp([0.2, -0.4, 1.1]), np.array([2.0, -1.0, 0.5]))


def cloud(n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-3.0, 3.0, (n, 3))


def test_a_quarter_turn_is_recovered_from_three_points() -> None:
    # Rotating (1,0,0), (0,1,0), (0,0,1) by 90 degrees about z and shifting by (1, 2, 3), by hand.
    source = np.eye(3)
    target = np.array([[1.0, 3.0, 3.0], [0.0, 2.0, 3.0], [1.0, 2.0, 4.0]])
    pose = rigid_transform(source, target)
    assert pose.rotation == pytest.approx(
        np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), abs=1e-12
    )
    assert pose.translation == pytest.approx([1.0, 2.0, 3.0], abs=1e-12)


def test_mirrored_points_give_a_rotation_not_a_reflection() -> None:
    source = cloud(6)
    mirrored = source * np.array([1.0, 1.0, -1.0])
    pose = rigid_transform(source, mirrored)
    assert np.linalg.det(pose.rotation) == pytest.approx(1.0)


def test_ransac_ignores_wrong_matches() -> None:
    source = cloud(20, seed=1)
    target = TRUE.transform(source) + np.random.default_rng(2).normal(0.0, 0.01, (20, 3))
    wrong = [3, 7, 11, 15, 19]
    target[wrong] = cloud(5, seed=3) + 10.0  # five matches to the wrong objects
    plain = rigid_transform(source, target)
    robust = ransac_rigid(source, target, threshold=0.1, seed=4)
    assert sorted(np.flatnonzero(~robust.inliers)) == wrong
    assert robust.pose.translation == pytest.approx(TRUE.translation, abs=0.02)
    angle = np.linalg.norm(np.asarray(Pose(robust.pose.rotation.T @ TRUE.rotation, np.zeros(3)).log()[:3]))
    assert math.degrees(float(angle)) < 0.5
    assert np.linalg.norm(plain.translation - TRUE.translation) > 1.0  # least squares alone is dragged away
    assert robust.rms < 0.03
    assert ransac_rigid(source, target, threshold=0.1, seed=4).inliers.tolist() == robust.inliers.tolist()


def test_alignment_becomes_an_edge_between_the_two_frames() -> None:
    source = cloud(5)
    result = ransac_rigid(source, TRUE.transform(source))
    a, b = pose_key(0, 3), pose_key(1, 8)
    edge = result.edge(a, b, np.eye(6))
    # x_b^-1 x_a = T: with x_b at the identity, x_a is T itself and the edge's cost is zero.
    assert (edge.source, edge.target) == (b, a)
    assert edge.cost(Pose.identity(), TRUE) == pytest.approx(0.0, abs=1e-18)


@pytest.mark.parametrize(
    ("source", "target", "message"),
    [
        (np.zeros((2, 3)), np.zeros((2, 3)), "at least 3"),
        (np.zeros((4, 3)), np.zeros((4, 2)), r"\(n, 3\)"),
        (np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]]), np.zeros((4, 3)), "collinear"),
    ],
)
def test_unusable_points_are_refused(source: np.ndarray, target: np.ndarray, message: str) -> None:
    with pytest.raises(AlignmentError, match=message):
        ransac_rigid(source, target) if message != "collinear" else rigid_transform(source, target)


def test_too_small_a_consensus_is_refused() -> None:
    source = cloud(6)
    target = cloud(6, seed=9)  # nothing matches anything
    with pytest.raises(AlignmentError, match="fewer than 5"):
        ransac_rigid(source, target, threshold=0.01, min_inliers=5)
