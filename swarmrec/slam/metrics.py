"""Accuracy of an estimate against a reference, as the object-based SLAM paper measures it.

With ``n = sum_alpha n_alpha`` the number of compared variables over all robots
(robot poses and object poses are reported separately, as the paper's
"Poses" and "Lmrks." columns), ``t`` and ``R`` the estimate, ``t*`` and ``R*``
the centralized Gauss-Newton estimate (same gauge, no alignment):

    ATE* = ( 1/n  sum_alpha sum_i || t_alpha_i - t*_alpha_i ||^2 )^(1/2)            (Eq. 1)
    ARE* = ( 1/n  sum_alpha sum_i || Log( (R*_alpha_i)^T R_alpha_i ) ||^2 )^(1/2)   (Eq. 2)

ATE* is in metres; ARE* is an angle (radians from Eq. 2, reported in degrees
as the paper's tables). The cost is gtsam's nonlinear error of the graph's
between factors at the estimate, ``sum 1/2 e^T Omega e`` with
``e = Log(z^-1 x_i^-1 x_j)``, without the anchor prior.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numpy as np

from swarmrec.slam.graph import PoseGraph, is_landmark_key
from swarmrec.slam.lie import Pose, so3_log

__all__ = ["Accuracy", "accuracy", "are_star", "ate_star"]


def ate_star(estimate: Mapping[int, Pose], reference: Mapping[int, Pose], keys: Iterable[int]) -> float:
    """Eq. 1 over ``keys`` (metres); nan for no key."""
    squared = [float(np.sum((estimate[k].translation - reference[k].translation) ** 2)) for k in keys]
    return math.sqrt(sum(squared) / len(squared)) if squared else math.nan


def are_star(estimate: Mapping[int, Pose], reference: Mapping[int, Pose], keys: Iterable[int]) -> float:
    """Eq. 2 over ``keys`` (radians); nan for no key."""
    squared = [float(np.sum(so3_log(reference[k].rotation.T @ estimate[k].rotation) ** 2)) for k in keys]
    return math.sqrt(sum(squared) / len(squared)) if squared else math.nan


@dataclass(frozen=True)
class Accuracy:
    """ATE* (m) and ARE* (degrees) for robot poses and for objects, and the costs of both estimates."""

    ate_poses: float
    ate_landmarks: float
    are_poses_deg: float
    are_landmarks_deg: float
    cost: float
    reference_cost: float


def accuracy(graph: PoseGraph, estimate: Mapping[int, Pose], reference: Mapping[int, Pose]) -> Accuracy:
    """Compare ``estimate`` with ``reference`` on every key of ``graph`` (objects are upper-case Symbols)."""
    poses = [k for k in graph.keys if not is_landmark_key(k)]
    landmarks = [k for k in graph.keys if is_landmark_key(k)]
    return Accuracy(
        ate_star(estimate, reference, poses),
        ate_star(estimate, reference, landmarks),
        math.degrees(are_star(estimate, reference, poses)),
        math.degrees(are_star(estimate, reference, landmarks)),
        graph.cost(estimate),
        graph.cost(reference),
    )
