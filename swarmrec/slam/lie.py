"""Rotations and rigid poses: SO(3)/SE(3) exponential and logarithm, Jacobians, projections.

Conventions follow gtsam, so that costs computed here equal the ones gtsam
reports: a pose ``(R, t)`` maps points from its own frame to the world,
``x = R p + t``; tangent vectors of SE(3) are ``(omega, v)``, rotation first;
perturbations act on the right, ``R Exp(omega)``; the logarithm of a pose is
``(Log R, V(Log R)^-1 t)``, gtsam's ``Pose3.Logmap``. Quaternions are written
``(qx, qy, qz, qw)`` as in g2o files.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from swarmrec.core.geometry import quaternion_to_matrix

__all__ = [
    "FloatArray",
    "Pose",
    "hat",
    "project_to_so3",
    "quaternion_from_matrix",
    "right_jacobian_inverse",
    "se3_log",
    "so3_exp",
    "so3_log",
]

FloatArray = npt.NDArray[np.float64]

# Below this angle the closed forms divide 0 by 0; their Taylor series are used
# instead (errors of order angle^4, far below float64 resolution at 1e-5).
_SMALL_ANGLE = 1e-5


def hat(v: npt.ArrayLike) -> FloatArray:
    """The skew-symmetric matrix ``[v]x`` with ``[v]x w = v x w``."""
    x, y, z = np.asarray(v, dtype=np.float64)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def so3_exp(omega: npt.ArrayLike) -> FloatArray:
    """The rotation ``Exp(omega)`` of the rotation vector ``omega`` (Rodrigues' formula)."""
    w = np.asarray(omega, dtype=np.float64)
    theta = float(np.linalg.norm(w))
    k = hat(w)
    if theta < _SMALL_ANGLE:
        return np.eye(3) + k + 0.5 * (k @ k)
    return np.eye(3) + (math.sin(theta) / theta) * k + ((1.0 - math.cos(theta)) / theta**2) * (k @ k)


def so3_log(rotation: npt.ArrayLike) -> FloatArray:
    """The rotation vector ``Log(R)`` in ``[0, pi]`` of a rotation matrix.

    Near pi the antisymmetric part vanishes, so the axis is read from the
    symmetric part instead (the column of ``R + I`` with the largest norm).
    """
    r = np.asarray(rotation, dtype=np.float64)
    cos_theta = min(1.0, max(-1.0, (float(np.trace(r)) - 1.0) / 2.0))
    axis_sin = 0.5 * np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    sin_theta = float(np.linalg.norm(axis_sin))
    theta = math.atan2(sin_theta, cos_theta)
    if theta < _SMALL_ANGLE:
        # sin(theta)/theta -> 1: the antisymmetric part is the vector itself.
        return axis_sin * (1.0 + theta**2 / 6.0)
    if math.pi - theta > 1e-3:
        return axis_sin * (theta / sin_theta)
    # The symmetric part is cos(theta) I + (1 - cos(theta)) a a^T: read a a^T from it and take
    # its column with the largest diagonal entry (the antisymmetric part only gives the sign).
    outer = (0.5 * (r + r.T) - cos_theta * np.eye(3)) / (1.0 - cos_theta)
    best = int(np.argmax(np.diag(outer)))
    axis = outer[:, best] / math.sqrt(outer[best, best])
    if float(axis @ axis_sin) < 0.0:
        axis = -axis
    return axis * theta


def right_jacobian_inverse(omega: npt.ArrayLike) -> FloatArray:
    """The inverse right Jacobian of SO(3): ``Log(Exp(w) Exp(d)) ~ w + Jr^-1(w) d`` for small ``d``."""
    w = np.asarray(omega, dtype=np.float64)
    theta = float(np.linalg.norm(w))
    k = hat(w)
    if theta < _SMALL_ANGLE:
        return np.eye(3) + 0.5 * k + (k @ k) / 12.0
    coefficient = 1.0 / theta**2 - (1.0 + math.cos(theta)) / (2.0 * theta * math.sin(theta))
    return np.eye(3) + 0.5 * k + coefficient * (k @ k)


def project_to_so3(matrix: npt.ArrayLike) -> FloatArray:
    """The rotation nearest to a 3x3 matrix in the Frobenius norm (SVD, determinant forced to +1)."""
    u, _, vt = np.linalg.svd(np.asarray(matrix, dtype=np.float64))
    d = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(u @ vt))) or 1.0])
    rotation: FloatArray = u @ d @ vt
    return rotation


def quaternion_from_matrix(rotation: npt.ArrayLike) -> FloatArray:
    """The unit quaternion ``(qx, qy, qz, qw)`` with ``qw >= 0`` of a rotation matrix.

    Branches on the largest of ``qw, qx, qy, qz`` so the square root is never
    taken of a number near zero (precise for every rotation, 180 degrees included).
    """
    r = np.asarray(rotation, dtype=np.float64)
    trace = float(np.trace(r))
    diagonal = (trace, r[0, 0], r[1, 1], r[2, 2])
    largest = int(np.argmax(diagonal))
    if largest == 0:
        s = 2.0 * math.sqrt(1.0 + trace)
        q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, s / 4.0]
    elif largest == 1:
        s = 2.0 * math.sqrt(max(0.0, 1.0 + r[0, 0] - r[1, 1] - r[2, 2]))
        q = [s / 4.0, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s]
    elif largest == 2:
        s = 2.0 * math.sqrt(max(0.0, 1.0 + r[1, 1] - r[0, 0] - r[2, 2]))
        q = [(r[0, 1] + r[1, 0]) / s, s / 4.0, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s]
    else:
        s = 2.0 * math.sqrt(max(0.0, 1.0 + r[2, 2] - r[0, 0] - r[1, 1]))
        q = [(r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, s / 4.0, (r[1, 0] - r[0, 1]) / s]
    quat = np.array(q)
    quat /= np.linalg.norm(quat)
    if quat[3] < 0.0:
        quat = -quat
    return quat


def _translation_log_matrix(omega: FloatArray) -> FloatArray:
    """``V(omega)^-1``: maps a pose's translation to the ``v`` part of its SE(3) logarithm."""
    theta = float(np.linalg.norm(omega))
    k = hat(omega)
    if theta < _SMALL_ANGLE:
        return np.eye(3) - 0.5 * k + (k @ k) / 12.0
    half = 0.5 * theta
    coefficient = (1.0 - half / math.tan(half)) / theta**2
    return np.eye(3) - 0.5 * k + coefficient * (k @ k)


def se3_log(rotation: npt.ArrayLike, translation: npt.ArrayLike) -> FloatArray:
    """The SE(3) logarithm ``(omega, v)`` of a pose, equal to gtsam's ``Pose3.Logmap``."""
    omega = so3_log(rotation)
    v = _translation_log_matrix(omega) @ np.asarray(translation, dtype=np.float64)
    return np.concatenate([omega, v])


@dataclass(frozen=True, eq=False)
class Pose:
    """A rigid pose: ``rotation`` (3x3, proper orthonormal) and ``translation`` (3,)."""

    rotation: FloatArray
    translation: FloatArray

    @staticmethod
    def identity() -> Pose:
        return Pose(np.eye(3), np.zeros(3))

    @staticmethod
    def from_quaternion(translation: npt.ArrayLike, quaternion: npt.ArrayLike) -> Pose:
        """A pose from ``(x, y, z)`` and a quaternion ``(qx, qy, qz, qw)`` (normalised here)."""
        rotation: FloatArray = quaternion_to_matrix(quaternion)
        return Pose(rotation, np.asarray(translation, dtype=np.float64).copy())

    @staticmethod
    def exp(xi: npt.ArrayLike) -> Pose:
        """A pose near the identity from a tangent vector ``(omega, v)`` (the SE(3) exponential)."""
        x = np.asarray(xi, dtype=np.float64)
        omega = x[:3]
        v_inverse = _translation_log_matrix(omega)
        translation = np.asarray(np.linalg.solve(v_inverse, x[3:]), dtype=np.float64)
        return Pose(so3_exp(omega), translation)

    def quaternion(self) -> FloatArray:
        return quaternion_from_matrix(self.rotation)

    def compose(self, other: Pose) -> Pose:
        """``self * other``: ``other`` expressed in this pose's frame, mapped to the world."""
        return Pose(self.rotation @ other.rotation, self.rotation @ other.translation + self.translation)

    def inverse(self) -> Pose:
        rt = self.rotation.T
        return Pose(rt, -(rt @ self.translation))

    def between(self, other: Pose) -> Pose:
        """``self^-1 * other``: where ``other`` is, seen from this pose (a g2o edge measurement)."""
        return self.inverse().compose(other)

    def log(self) -> FloatArray:
        return se3_log(self.rotation, self.translation)

    def matrix(self) -> FloatArray:
        """The 4x4 homogeneous matrix."""
        m = np.eye(4)
        m[:3, :3] = self.rotation
        m[:3, 3] = self.translation
        return m

    def transform(self, points: npt.ArrayLike) -> FloatArray:
        """Points ``(n, 3)`` of this pose's frame in the world frame."""
        p = np.asarray(points, dtype=np.float64)
        out: FloatArray = p @ self.rotation.T + self.translation
        return out
