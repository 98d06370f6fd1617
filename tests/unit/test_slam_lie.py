"""Rotations, poses and keys against gtsam (an independent implementation) and finite differences."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest

from swarmrec.slam.keys import (
    describe_key,
    landmark_key,
    pose_key,
    robot_of_key,
    symbol_chr,
    symbol_index,
    symbol_key,
)
from swarmrec.slam.lie import (
    Pose,
    hat,
    project_to_so3,
    quaternion_from_matrix,
    right_jacobian_inverse,
    se3_log,
    so3_exp,
    so3_log,
)

RNG = np.random.default_rng(7)
VECTORS = [
    np.array([0.3, -0.2, 0.5]),
    np.array([1e-9, 2e-9, -1e-9]),
    np.array([0.0, 0.0, 0.0]),
    np.array([0.0, math.pi - 1e-6, 0.0]),
    np.array([2.0, 1.0, -1.5]) / np.linalg.norm([2.0, 1.0, -1.5]) * (math.pi - 1e-4),
    *RNG.normal(0.0, 1.0, (5, 3)),
]


@pytest.mark.parametrize("omega", VECTORS)
def test_exp_and_log_agree_with_gtsam(omega: np.ndarray) -> None:
    expected = gtsam.Rot3.Expmap(omega).matrix()
    assert so3_exp(omega) == pytest.approx(expected, abs=1e-12)
    assert so3_log(expected) == pytest.approx(gtsam.Rot3.Logmap(gtsam.Rot3(expected)), abs=1e-6)


def test_log_of_a_half_turn_is_pi_about_the_axis() -> None:
    # 180 degrees about z: diag(-1, -1, 1), whose antisymmetric part is zero.
    assert np.abs(so3_log(np.diag([-1.0, -1.0, 1.0]))) == pytest.approx([0.0, 0.0, math.pi])


@pytest.mark.parametrize("omega", [VECTORS[0], VECTORS[3] * 0.9, VECTORS[6], np.array([1e-7, 0.0, 2e-7])])
def test_right_jacobian_inverse_matches_finite_differences(omega: np.ndarray) -> None:
    h = 1e-6
    numeric = np.zeros((3, 3))
    for k in range(3):
        d = np.zeros(3)
        d[k] = h
        numeric[:, k] = (so3_log(so3_exp(omega) @ so3_exp(d)) - so3_log(so3_exp(omega) @ so3_exp(-d))) / (
            2 * h
        )
    assert right_jacobian_inverse(omega) == pytest.approx(numeric, abs=1e-6)


def test_hat_is_the_cross_product() -> None:
    assert hat([1.0, 2.0, 3.0]) @ np.array([4.0, 5.0, 6.0]) == pytest.approx([-3.0, 6.0, -3.0])


@pytest.mark.parametrize("seed", range(4))
def test_se3_log_equals_gtsam_pose3_logmap(seed: int) -> None:
    rng = np.random.default_rng(seed)
    rotation = so3_exp(rng.normal(0.0, 1.0, 3))
    translation = rng.normal(0.0, 3.0, 3)
    expected = gtsam.Pose3.Logmap(gtsam.Pose3(gtsam.Rot3(rotation), translation))
    assert se3_log(rotation, translation) == pytest.approx(expected, abs=1e-9)
    round_trip = Pose.exp(expected)
    assert round_trip.rotation == pytest.approx(rotation, abs=1e-9)
    assert round_trip.translation == pytest.approx(translation, abs=1e-9)


@pytest.mark.parametrize("omega", [*VECTORS, np.array([math.pi, 0.0, 0.0]), np.array([0.0, 0.0, math.pi])])
def test_quaternion_from_matrix_agrees_with_gtsam_up_to_sign(omega: np.ndarray) -> None:
    rotation = so3_exp(omega)
    q = quaternion_from_matrix(rotation)
    g = gtsam.Rot3(rotation).toQuaternion()  # (w, x, y, z)
    expected = np.array([g.x(), g.y(), g.z(), g.w()])
    assert min(np.abs(q - expected).max(), np.abs(q + expected).max()) < 1e-9
    assert Pose.from_quaternion(np.zeros(3), q).rotation == pytest.approx(rotation, abs=1e-12)


def test_projection_recovers_the_rotation_of_a_polar_decomposition() -> None:
    # M = R S with S symmetric positive definite: the nearest rotation to M is R.
    rotation = so3_exp([0.4, -1.1, 0.7])
    s = np.array([[3.0, 0.2, 0.1], [0.2, 2.0, -0.3], [0.1, -0.3, 1.0]])
    assert project_to_so3(rotation @ s) == pytest.approx(rotation, abs=1e-12)
    assert np.linalg.det(project_to_so3(-np.eye(3))) == pytest.approx(1.0)


def test_pose_between_and_compose_are_inverse_operations() -> None:
    a = Pose(so3_exp([0.1, 0.2, 0.3]), np.array([1.0, 2.0, 3.0]))
    b = Pose(so3_exp([-0.3, 0.1, 0.5]), np.array([-1.0, 0.5, 2.0]))
    back = a.compose(a.between(b))
    assert back.rotation == pytest.approx(b.rotation) and back.translation == pytest.approx(b.translation)
    # (1, 0, 0) in a frame rotated 90 degrees about z and moved by (1, 1, 0) is (1, 2, 0).
    quarter = Pose(so3_exp([0.0, 0.0, math.pi / 2]), np.array([1.0, 1.0, 0.0]))
    assert quarter.transform([[1.0, 0.0, 0.0]])[0] == pytest.approx([1.0, 2.0, 0.0])


def test_symbol_keys_have_gtsams_layout() -> None:
    for character, index in [("a", 0), ("b", 5), ("A", 12), ("x", 2**40)]:
        key = symbol_key(character, index)
        assert key == gtsam.Symbol(character, index).key()
        assert (symbol_chr(key), symbol_index(key)) == (character, index)
    assert pose_key(1, 3) == gtsam.Symbol("b", 3).key()
    assert landmark_key(0, 7) == gtsam.Symbol("A", 7).key()
    assert [robot_of_key(pose_key(2, 1)), robot_of_key(landmark_key(2, 1)), robot_of_key(42)] == [2, 2, None]
    assert describe_key(pose_key(0, 12)) == "a12" and describe_key(42) == "42"
    with pytest.raises(ValueError, match="index"):
        symbol_key("a", 2**56)
