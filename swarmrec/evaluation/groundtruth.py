"""Ground-truth loop closures from camera poses (paper Sec. IV-A).

Each frame gets a *scene point*: the point straight ahead of the camera
(camera z axis) at the frame's mean object depth. Two frames are a true loop
closure when their scene points are closer than ``max_distance`` (2.0 m) and
they are more than ``exclusion`` frames apart.

The published evaluation also applies hand-made rules for the TUM
``fr3/long_office_household`` sequence that separate the two sides of its
desks; they are available as ``rules="tum-fr3-office"`` and only make sense
for that sequence (its world frame is aligned with the desks).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt

from swarmrec.core.geometry import quaternion_to_matrix
from swarmrec.core.types import ConstellationSequence, Trajectory
from swarmrec.datasets.tum import POSE_MAX_DT, PoseAssociation, associate_poses
from swarmrec.evaluation.band import fill_band

__all__ = ["GroundTruth", "ground_truth", "quaternion_to_matrix", "scene_points"]

FloatArray = npt.NDArray[np.float64]
Rules = Literal["none", "tum-fr3-office"]


def scene_points(seq: ConstellationSequence, poses: Trajectory) -> FloatArray:
    """World position of each frame's scene point (``poses`` already one per frame).

    The depth is the mean z of the frame's objects, 0 for an empty frame (the
    scene point is then the camera itself), as in the published evaluation.
    """
    depth = np.array([c.positions[:, 2].mean() if len(c) else 0.0 for c in seq.constellations])
    rot = quaternion_to_matrix(poses.quaternions)
    points: FloatArray = poses.positions + rot[:, :, 2] * depth[:, None]
    return points


def _tum_fr3_office_filter(cam: FloatArray, scene: FloatArray, dist: FloatArray) -> FloatArray:
    """The published hand-made rules for fr3/long_office_household (vectorised).

    The desks' long side is along x; the middle between the two desks is
    y = 0. Pairs whose cameras are on opposite sides (y > 0.3 vs y < -0.3)
    never match; a camera in the middle band (|y| < 0.25) only matches a
    camera over the desks' extent when their scene points are within 0.3 m in
    x. As published, the rules are evaluated with the earlier frame as "pose 1"
    and mirrored, and the second rule mixes the two poses' x (pose 1's lower
    bound, pose 2's upper bound); both are kept, they produced the numbers.
    """
    cy, cx = cam[:, 1], cam[:, 0]
    out = dist.copy()
    opposite = ((cy[:, None] > 0.3) & (cy[None, :] < -0.3)) | ((cy[None, :] > 0.3) & (cy[:, None] < -0.3))
    dx = np.abs(scene[:, None, 0] - scene[None, :, 0]) > 0.3
    middle_1 = (np.abs(cy)[:, None] < 0.25) & ((cx[None, :] > -1.8) & (cx[None, :] < 0.5))
    middle_2 = (np.abs(cy)[None, :] < 0.25) & ((cx[:, None] > -1.8) & (cx[None, :] < 0.5))
    upper = np.triu(opposite | (middle_1 & dx) | (middle_2 & dx))
    out[upper | upper.T] = np.inf
    return out


@dataclass(frozen=True, eq=False)
class GroundTruth:
    """Scene distances between frames and the true closures they imply."""

    distances: FloatArray  # (N, N), inf inside the exclusion window or filtered out
    closures: npt.NDArray[np.bool_]  # distances < max_distance
    scene: FloatArray  # (N, 3) scene points
    poses: PoseAssociation  # which pose each frame took, and how far in time


#: Rows of the distance matrix computed at a time: the (rows, N, 3) differences of a
#: block stay small (5000 frames at once took 600 MB).
_ROWS = 256


def _distances(scene: FloatArray) -> FloatArray:
    """Euclidean distances between every two scene points, block of rows by block of rows:
    each entry computed as the whole-matrix expression computes it, so the same doubles."""
    n = scene.shape[0]
    dist = np.empty((n, n))
    for lo in range(0, n, _ROWS):
        block = dist[lo : lo + _ROWS]
        dx, dy, dz = (scene[lo : lo + _ROWS, None, c] - scene[None, :, c] for c in range(3))
        # (dx² + dy²) + dz², in place: what summing the last axis of 3 does, in that order.
        np.multiply(dx, dx, out=block)
        block += dy * dy
        block += dz * dz
        np.sqrt(block, out=block)
    return dist


def ground_truth(
    seq: ConstellationSequence,
    trajectory: Trajectory,
    *,
    max_distance: float = 2.0,
    exclusion: int = 100,
    rules: Rules = "none",
    max_dt: float = POSE_MAX_DT,
) -> GroundTruth:
    """True loop closures of ``seq`` from ``trajectory``: each frame takes the pose nearest
    in time, as the published evaluation does (:func:`~swarmrec.datasets.tum.associate_poses`;
    ``associated.describe()`` says which frames were far from every pose)."""
    associated = associate_poses(trajectory, seq.timestamps, max_dt=max_dt)
    idx = associated.index
    poses = Trajectory(trajectory.timestamps[idx], trajectory.positions[idx], trajectory.quaternions[idx])
    scene = scene_points(seq, poses)
    dist = _distances(scene)
    if rules == "tum-fr3-office":
        dist = _tum_fr3_office_filter(poses.positions, scene, dist)
    elif rules != "none":
        raise ValueError(f"unknown ground-truth rules {rules!r}")
    fill_band(dist, exclusion, np.inf)
    return GroundTruth(dist, dist < max_distance, scene, associated)
