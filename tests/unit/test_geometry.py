"""The one quaternion-to-rotation conversion every module uses (TUM order qx qy qz qw)."""

from __future__ import annotations

import numpy as np

from swarmrec.core.geometry import quaternion_to_matrix
from swarmrec.evaluation import groundtruth
from swarmrec.synthetic.camera import matrices_to_quaternions, quaternions_to_matrices


def test_a_quarter_turn_about_z_maps_x_to_y() -> None:
    r = quaternion_to_matrix([0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)])
    assert r.shape == (3, 3)
    assert np.allclose(r @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])


def test_batches_keep_their_shape_and_unnormalised_quaternions_are_normalised() -> None:
    q = np.random.default_rng(0).normal(size=(4, 5, 4))
    r = quaternion_to_matrix(q)
    assert r.shape == (4, 5, 3, 3)
    assert np.allclose(r @ np.swapaxes(r, -1, -2), np.eye(3))
    assert np.allclose(np.linalg.det(r), 1.0)
    assert np.allclose(r, quaternion_to_matrix(3.0 * q))


def test_the_ground_truth_and_the_camera_path_use_this_conversion() -> None:
    q = matrices_to_quaternions(quaternion_to_matrix(np.random.default_rng(1).normal(size=(6, 4))))
    assert groundtruth.quaternion_to_matrix is quaternion_to_matrix
    assert np.array_equal(quaternions_to_matrices(q), quaternion_to_matrix(q))
    assert quaternions_to_matrices(q[0]).shape == (1, 3, 3)
