"""Rotations in the TUM convention: quaternions ``(qx, qy, qz, qw)``, camera to world."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = ["quaternion_to_matrix"]

FloatArray = npt.NDArray[np.float64]


def quaternion_to_matrix(q: npt.ArrayLike) -> FloatArray:
    """Rotation matrices ``(..., 3, 3)`` of quaternions ``(..., 4)`` given as ``qx qy qz qw``.

    The quaternions are normalised first, so a pose read back from a text file
    with rounded digits still gives a proper rotation.
    """
    quat: FloatArray = np.asarray(q, dtype=np.float64)
    quat = quat / np.linalg.norm(quat, axis=-1, keepdims=True)
    x, y, z, w = quat[..., 0], quat[..., 1], quat[..., 2], quat[..., 3]
    matrices: FloatArray = np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )
    return matrices
