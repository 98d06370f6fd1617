"""Small multi-robot pose graphs for the SLAM tests, built from known ground truth.

Each robot drives a short chain; separators join chosen pairs of poses of two
robots. Measurements are the ground truth's relative poses, optionally
perturbed by a seeded noise, so a test knows exactly what the noise-free
optimum is (the ground truth) and can build any reference it needs.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from swarmrec.slam.graph import Edge, PoseGraph
from swarmrec.slam.keys import pose_key
from swarmrec.slam.lie import Pose, so3_exp


def pose(yaw: float, x: float, y: float, z: float = 0.0, roll: float = 0.0) -> Pose:
    return Pose(so3_exp([roll, 0.0, yaw]), np.array([x, y, z]))


def perturbed(p: Pose, rng: np.random.Generator, sigma_r: float, sigma_t: float) -> Pose:
    return Pose(
        p.rotation @ so3_exp(rng.normal(0.0, sigma_r, 3)), p.translation + rng.normal(0.0, sigma_t, 3)
    )


def information(sigma_r: float = 0.05, sigma_t: float = 0.1) -> np.ndarray:
    return np.diag([sigma_r**-2] * 3 + [sigma_t**-2] * 3)


def chain_truth(robots: int, poses_per_robot: int) -> dict[int, Pose]:
    """Robot r's poses on a gentle arc, robots side by side 1 m apart (a 3D wobble keeps it non-planar)."""
    truth = {}
    for r in range(robots):
        for i in range(poses_per_robot):
            truth[pose_key(r, i)] = pose(
                0.3 * i + 0.2 * r,
                1.0 * i + 0.1 * r,
                1.0 * r + 0.2 * math.sin(i),
                0.1 * math.cos(i + r),
                0.05 * i,
            )
    return truth


def make_graph(
    robots: int = 2,
    poses_per_robot: int = 4,
    separators: Sequence[tuple[int, int]] | None = None,
    *,
    sigma_r: float = 0.0,
    sigma_t: float = 0.0,
    seed: int = 0,
    initial_noise: float = 0.0,
) -> tuple[PoseGraph, dict[int, Pose]]:
    """A chain per robot plus separators ``(key_a, key_b)`` (default: pose i of robot r to pose i of r+1).

    Returns the graph (vertices at the ground truth, or perturbed by
    ``initial_noise``) and the ground truth.
    """
    rng = np.random.default_rng(seed)
    truth = chain_truth(robots, poses_per_robot)
    pairs = [(pose_key(r, i), pose_key(r, i + 1)) for r in range(robots) for i in range(poses_per_robot - 1)]
    if separators is None:
        separators = [
            (pose_key(r, i), pose_key(r + 1, i)) for r in range(robots - 1) for i in (0, poses_per_robot - 1)
        ]
    pairs += list(separators)
    edges = []
    for a, b in pairs:
        z = truth[a].between(truth[b])
        if sigma_r or sigma_t:
            z = perturbed(z, rng, sigma_r, sigma_t)
        edges.append(Edge(a, b, z, information(max(sigma_r, 0.05), max(sigma_t, 0.1))))
    initial = {
        k: perturbed(p, rng, initial_noise, initial_noise) if initial_noise else p for k, p in truth.items()
    }
    return PoseGraph(initial, tuple(edges)), truth
