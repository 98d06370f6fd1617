"""The handheld camera: pinhole model, rotations, and the path around the desks.

Conventions (TUM): the camera frame has x right, y down, z forward; a pose
``(t, q)`` maps camera to world, ``p_world = R(q) @ p_cam + t``, with
``q = (qx, qy, qz, qw)``. The world frame has z up and the floor at z = 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from swarmrec.core.geometry import quaternion_to_matrix
from swarmrec.synthetic.config import OfficeConfig

__all__ = [
    "TUM_FR3_CAMERA",
    "PinholeCamera",
    "matrices_to_quaternions",
    "orbit_path",
    "quaternions_to_matrices",
]

FloatArray = npt.NDArray[np.float64]

#: Height of the point the camera looks at (a little above the tabletops).
LOOK_AT_HEIGHT_M = 0.8
# The look-at point is the camera's (x, y) times these factors, clipped to the
# near half of the block: the near desk fills the view, the far row shows behind.
_TARGET_PULL = (0.7, 1.0)
# Duration of the turn of a glance away (about the logistic step's 10-90 % time).
_GLANCE_TURN_S = 0.5
# The orbit's radius varies by up to this fraction, so loops and views differ.
_BREATHING = 0.12


@dataclass(frozen=True)
class PinholeCamera:
    """Pinhole intrinsics in pixels and the image size."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def project(self, p_cam: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Pixel coordinates ``(u, v)`` of camera-frame points (``...x3``, z > 0)."""
        z = p_cam[..., 2]
        return self.fx * p_cam[..., 0] / z + self.cx, self.fy * p_cam[..., 1] / z + self.cy

    def unproject(self, u: FloatArray, v: FloatArray, z: FloatArray) -> FloatArray:
        """Camera-frame points at depth ``z`` seen at pixels ``(u, v)``."""
        return np.stack([(u - self.cx) * z / self.fx, (v - self.cy) * z / self.fy, z], axis=-1)


#: The TUM freiburg3 RGB camera (640x480), as in the real sequence.
TUM_FR3_CAMERA = PinholeCamera(fx=535.4, fy=539.2, cx=320.1, cy=247.6, width=640, height=480)


def quaternions_to_matrices(q: FloatArray) -> FloatArray:
    """Rotation matrices (``n x 3 x 3``) of quaternions ``(qx, qy, qz, qw)`` (``n x 4``; one
    quaternion gives ``1 x 3 x 3``); :func:`swarmrec.core.geometry.quaternion_to_matrix`, batched."""
    return quaternion_to_matrix(np.asarray(q, dtype=np.float64).reshape(-1, 4))


def matrices_to_quaternions(r: FloatArray) -> FloatArray:
    """Unit quaternions ``(qx, qy, qz, qw)`` with ``qw >= 0`` of rotation matrices.

    Shepperd's method: each row uses the largest of the four candidate
    denominators, so no division by a small number happens near 180 degrees.
    """
    r = np.asarray(r, dtype=np.float64).reshape(-1, 3, 3)
    m00, m11, m22 = r[:, 0, 0], r[:, 1, 1], r[:, 2, 2]
    trace = m00 + m11 + m22
    cand = np.stack([trace, m00, m11, m22], axis=1)
    case = np.argmax(cand, axis=1)
    q = np.empty((r.shape[0], 4))
    # s = 4 * (the component that is largest), always >= 1 for a rotation.
    s = 2.0 * np.sqrt(np.maximum(1.0 + 2.0 * cand.max(axis=1) - trace, 1e-300))
    c0, c1, c2, c3 = (case == k for k in range(4))
    q[c0, 3] = s[c0] / 4
    q[c0, 0] = (r[c0, 2, 1] - r[c0, 1, 2]) / s[c0]
    q[c0, 1] = (r[c0, 0, 2] - r[c0, 2, 0]) / s[c0]
    q[c0, 2] = (r[c0, 1, 0] - r[c0, 0, 1]) / s[c0]
    q[c1, 0] = s[c1] / 4
    q[c1, 3] = (r[c1, 2, 1] - r[c1, 1, 2]) / s[c1]
    q[c1, 1] = (r[c1, 0, 1] + r[c1, 1, 0]) / s[c1]
    q[c1, 2] = (r[c1, 0, 2] + r[c1, 2, 0]) / s[c1]
    q[c2, 1] = s[c2] / 4
    q[c2, 3] = (r[c2, 0, 2] - r[c2, 2, 0]) / s[c2]
    q[c2, 0] = (r[c2, 0, 1] + r[c2, 1, 0]) / s[c2]
    q[c2, 2] = (r[c2, 1, 2] + r[c2, 2, 1]) / s[c2]
    q[c3, 2] = s[c3] / 4
    q[c3, 3] = (r[c3, 1, 0] - r[c3, 0, 1]) / s[c3]
    q[c3, 0] = (r[c3, 0, 2] + r[c3, 2, 0]) / s[c3]
    q[c3, 1] = (r[c3, 1, 2] + r[c3, 2, 1]) / s[c3]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 3] < 0] *= -1.0
    return q


def _axis_rotations(axis: int, angle: FloatArray) -> FloatArray:
    """Rotations by ``angle`` (radians, ``n``) about coordinate axis 0, 1 or 2."""
    c, s = np.cos(angle), np.sin(angle)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    r = np.zeros((angle.shape[0], 3, 3))
    r[:, axis, axis] = 1.0
    r[:, i, i] = c
    r[:, j, j] = c
    r[:, i, j] = -s
    r[:, j, i] = s
    return r


def _smooth_wave(
    rng: np.random.Generator, t: FloatArray, freq_hz: tuple[float, float], n_terms: int = 3
) -> FloatArray:
    """A smooth random signal of unit-ish amplitude: a few sinusoids, random frequencies."""
    freqs = rng.uniform(freq_hz[0], freq_hz[1], n_terms)
    phases = rng.uniform(0.0, 2 * np.pi, n_terms)
    weights = rng.uniform(0.5, 1.0, n_terms)
    weights /= weights.sum()
    return np.asarray(
        (weights[None, :] * np.sin(2 * np.pi * t[:, None] * freqs[None, :] + phases)).sum(axis=1)
    )


def orbit_path(config: OfficeConfig, rng: np.random.Generator) -> tuple[FloatArray, FloatArray]:
    """Camera positions (``n x 3``) and camera-to-world rotations (``n x 3 x 3``).

    The camera walks ``n_loops`` times around the desk block on an ellipse
    (semi-axes :attr:`OfficeConfig.orbit_semi_axes_m`, radius breathing by up to
    12 % so loops do not coincide), at a walking speed that varies, with
    the height drifting between the two ``camera_height_m`` limits. It looks at
    a point above the desks near the camera's side of the block, plus smooth
    hand wobble in yaw, pitch and roll, plus a few quick glances away.
    """
    n = config.n_frames
    t = np.arange(n) / config.rate_hz
    x = np.linspace(0.0, 1.0, n)

    # Walking speed varies (handheld): the phase is a monotone warp of time,
    # derivative 1 + sum(a_k cos(...)) >= 1 - 3 * 0.3 > 0. Where the terms
    # line up the camera nearly stops and lingers on a desk, as in TUM.
    amps = rng.uniform(0.15, 0.3, 3)
    cycles = rng.integers(2, 3 + int(2 * config.n_loops), 3)
    phases = rng.uniform(0.0, 2 * np.pi, 3)
    warp = x + (
        amps[None, :]
        / (2 * np.pi * cycles[None, :])
        * np.sin(2 * np.pi * cycles[None, :] * x[:, None] + phases[None, :])
    ).sum(axis=1)
    warp = (warp - warp[0]) / (warp[-1] - warp[0])
    theta = rng.uniform(0.0, 2 * np.pi) + 2 * np.pi * config.n_loops * warp

    ax, ay = config.orbit_semi_axes_m
    breathing = 1.0 + _BREATHING * np.sin(0.5 * theta + rng.uniform(0.0, 2 * np.pi))
    shake = 0.015 * np.stack([_smooth_wave(rng, t, (0.3, 1.5)) for _ in range(3)], axis=1)
    lo, hi = config.camera_height_m
    height = (lo + hi) / 2 + (hi - lo) / 2 * _smooth_wave(rng, t, (0.02, 0.12))
    pos = np.stack([ax * breathing * np.cos(theta), ay * breathing * np.sin(theta), height], axis=1)
    pos = pos + shake
    pos[:, 2] = np.clip(pos[:, 2], lo, hi)

    hx, hy = config.block_half_extent_m
    target = np.stack(
        [
            np.clip(_TARGET_PULL[0] * pos[:, 0], -(hx - 0.35), hx - 0.35),
            np.clip(_TARGET_PULL[1] * pos[:, 1], -0.5 * hy, 0.5 * hy),
            np.full(n, LOOK_AT_HEIGHT_M),
        ],
        axis=1,
    )
    forward = target - pos
    # Glances turn the body, about the world's vertical (turning about the
    # tilted camera axis would make a look back point at the ceiling).
    glance = _glances(config, rng, t)
    c, s = np.cos(glance), np.sin(glance)
    forward = np.stack(
        [c * forward[:, 0] - s * forward[:, 1], s * forward[:, 0] + c * forward[:, 1], forward[:, 2]],
        axis=1,
    )
    forward /= np.linalg.norm(forward, axis=1, keepdims=True)
    right = np.cross(forward, np.array([0.0, 0.0, 1.0]))
    right /= np.linalg.norm(right, axis=1, keepdims=True)
    down = np.cross(forward, right)
    look = np.stack([right, down, forward], axis=2)  # columns: camera axes in the world

    w = np.deg2rad(config.wobble_deg)
    yaw = w * _smooth_wave(rng, t, (0.02, 0.25))
    pitch = 0.7 * w * _smooth_wave(rng, t, (0.02, 0.25))
    roll = 0.5 * w * _smooth_wave(rng, t, (0.02, 0.25))
    # Wobble in the camera frame: yaw about y (down), pitch about x, roll about z.
    wobble = _axis_rotations(1, yaw) @ _axis_rotations(0, pitch) @ _axis_rotations(2, roll)
    return pos, look @ wobble


def _glances(config: OfficeConfig, rng: np.random.Generator, t: FloatArray) -> FloatArray:
    """Yaw offsets (radians) of looks away from the desks.

    Each is a quick turn (a logistic step, about half a second), a hold of
    0.5-2 s and a turn back; the turns are fast enough to blur the images.
    """
    n_glances = round(config.glances_per_minute * config.duration_s / 60.0)
    if n_glances == 0:
        return np.zeros_like(t)
    starts = rng.uniform(t[0], t[-1], n_glances)
    holds = rng.uniform(0.5, 2.0, n_glances)
    amps = np.deg2rad(rng.uniform(60.0, 160.0, n_glances)) * rng.choice([-1.0, 1.0], n_glances)
    tau = _GLANCE_TURN_S / 4
    up = _logistic((t[:, None] - starts[None, :]) / tau)
    down = _logistic((t[:, None] - starts[None, :] - holds[None, :]) / tau)
    return np.asarray((amps[None, :] * (up - down)).sum(axis=1))


def _logistic(x: FloatArray) -> FloatArray:
    """1 / (1 + exp(-x)), written with tanh so that it never overflows."""
    return np.asarray(0.5 * (1.0 + np.tanh(0.5 * x)))
