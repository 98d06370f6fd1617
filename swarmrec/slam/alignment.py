"""The rigid motion between two frames from matched 3D points, robust to wrong matches.

A verified constellation loop closure gives pairs of 3D points, the same
objects seen from two robots' frames. :func:`rigid_transform` is the
least-squares rotation and translation (Horn / Umeyama without scale, by SVD
of the cross-covariance, determinant forced to +1 so a reflection is never
returned); :func:`ransac_rigid` fits it on minimal 3-point samples, keeps the
largest consensus and refits on it, so a few wrong matches do not bend the
result. :meth:`Alignment.edge` turns the result into an inter-robot
relative-pose constraint for the pose graph.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from swarmrec.slam.errors import AlignmentError
from swarmrec.slam.graph import Edge
from swarmrec.slam.lie import FloatArray, Pose

__all__ = ["Alignment", "ransac_rigid", "rigid_transform"]

# Centred points whose second singular value is below this fraction of the
# first lie on a line: the rotation about that line is undetermined.
_COLLINEAR = 1e-6


def _points(source: npt.ArrayLike, target: npt.ArrayLike) -> tuple[FloatArray, FloatArray]:
    p = np.asarray(source, dtype=np.float64)
    q = np.asarray(target, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or p.shape != q.shape:
        raise AlignmentError(f"need two (n, 3) arrays of matched points, got {p.shape} and {q.shape}")
    if len(p) < 3:
        raise AlignmentError(f"need at least 3 matched points, got {len(p)}")
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
        raise AlignmentError("points must be finite")
    return p, q


def _degenerate(points: FloatArray) -> bool:
    singular = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    return bool(singular[0] == 0.0 or singular[1] < _COLLINEAR * singular[0])


def rigid_transform(source: npt.ArrayLike, target: npt.ArrayLike) -> Pose:
    """The pose ``T`` minimising ``sum || target_i - (R source_i + t) ||^2``."""
    p, q = _points(source, target)
    if _degenerate(p) or _degenerate(q):
        raise AlignmentError("the points are collinear (or coincide): the rotation is undetermined")
    p_mean, q_mean = p.mean(axis=0), q.mean(axis=0)
    cross = (p - p_mean).T @ (q - q_mean)
    u, _, vt = np.linalg.svd(cross)
    d = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(vt.T @ u.T))) or 1.0])
    rotation = vt.T @ d @ u.T
    return Pose(rotation, q_mean - rotation @ p_mean)


@dataclass(frozen=True)
class Alignment:
    """A robust fit: ``pose`` maps source points onto target points; ``inliers`` marks the pairs it explains.

    ``rms`` is the root mean square distance of the inliers after the fit (m).
    """

    pose: Pose
    inliers: npt.NDArray[np.bool_]
    rms: float

    @property
    def inlier_count(self) -> int:
        return int(self.inliers.sum())

    def edge(self, source_frame_key: int, target_frame_key: int, information: npt.ArrayLike) -> Edge:
        """The constraint between the two frames' poses: ``x_target^-1 x_source = pose``."""
        return Edge(target_frame_key, source_frame_key, self.pose, np.asarray(information, dtype=np.float64))


def _distances(pose: Pose, p: FloatArray, q: FloatArray) -> FloatArray:
    out: FloatArray = np.linalg.norm(pose.transform(p) - q, axis=1)
    return out


def ransac_rigid(
    source: npt.ArrayLike,
    target: npt.ArrayLike,
    *,
    threshold: float = 0.1,
    iterations: int = 200,
    min_inliers: int = 3,
    seed: int = 0,
) -> Alignment:
    """RANSAC over minimal 3-point samples, then least squares on the largest consensus.

    A pair is an inlier when the fitted pose maps its source point within
    ``threshold`` metres of its target point. The best sample has the most
    inliers (fewer residual on ties); the final pose is refitted on its
    inliers until the inlier set stops changing. Seeded: the same input gives
    the same answer.
    """
    p, q = _points(source, target)
    if threshold <= 0.0 or iterations < 1 or min_inliers < 3:
        raise AlignmentError("threshold must be positive, iterations at least 1, min_inliers at least 3")
    rng = np.random.default_rng(seed)
    best: tuple[int, float, npt.NDArray[np.bool_]] | None = None
    n = len(p)
    for _ in range(iterations):
        sample = rng.choice(n, size=3, replace=False)
        if _degenerate(p[sample]) or _degenerate(q[sample]):
            continue
        distances = _distances(rigid_transform(p[sample], q[sample]), p, q)
        inliers = distances < threshold
        score = (int(inliers.sum()), -float(np.sum(distances[inliers] ** 2)))
        if best is None or score > (best[0], best[1]):
            best = (score[0], score[1], inliers)
    if best is None:
        raise AlignmentError("every 3-point sample was degenerate (collinear points)")
    inliers = best[2]
    if best[0] < max(3, min_inliers):
        raise AlignmentError(f"best consensus has {best[0]} inliers, fewer than {max(3, min_inliers)}")
    pose = rigid_transform(p[inliers], q[inliers])
    for _ in range(5):  # refit until the consensus is stable
        distances = _distances(pose, p, q)
        refreshed = distances < threshold
        if refreshed.sum() < 3 or np.array_equal(refreshed, inliers) or _degenerate(p[refreshed]):
            break
        inliers = refreshed
        pose = rigid_transform(p[inliers], q[inliers])
    if int(inliers.sum()) < min_inliers:
        raise AlignmentError(f"best consensus has {int(inliers.sum())} inliers, fewer than {min_inliers}")
    rms = math.sqrt(float(np.mean(_distances(pose, p, q)[inliers] ** 2)))
    return Alignment(pose, inliers, rms)
