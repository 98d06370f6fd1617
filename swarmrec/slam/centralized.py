"""The centralized references: gtsam's Gauss-Newton / Levenberg-Marquardt, and the two-stage solve.

:func:`solve_centralized` builds the gtsam problem the paper compares against
(one ``BetweenFactorPose3`` per edge with the edge's information as a Gaussian
noise model, and a ``PriorFactorPose3`` fixing the gauge at the anchor, the first
pose of robot 0) and optimises it with Gauss-Newton or Levenberg-Marquardt,
starting from the chordal initialisation (as the public implementation's
"two stage + GN") or from the graph's own vertices.

:func:`solve_two_stage` is the same two-stage method the distributed solver
runs, solved in one piece: chordal rotations (projected to SO(3)), then one
linearised pose step (:mod:`swarmrec.slam.two_stage`). It is the fixed point the
distributed Gauss-Seidel iterations converge to, and the chordal initialisation.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Literal

import gtsam
import numpy as np

from swarmrec.errors import ConfigError
from swarmrec.slam.errors import GraphError
from swarmrec.slam.graph import Edge, PoseGraph
from swarmrec.slam.lie import FloatArray, Pose, project_to_so3
from swarmrec.slam.two_stage import (
    pose_system,
    retract,
    rotation_system,
    solve_pose_updates,
    solve_rotations,
)

__all__ = [
    "ANCHOR_SIGMA",
    "METHODS",
    "CentralizedResult",
    "Method",
    "TwoStageResult",
    "from_gtsam_pose",
    "gtsam_graph",
    "gtsam_values",
    "solve_centralized",
    "solve_two_stage",
    "to_gtsam_pose",
]

Method = Literal["gauss-newton", "levenberg-marquardt"]
METHODS: tuple[Method, ...] = ("gauss-newton", "levenberg-marquardt")
# Standard deviation of the anchor prior (variance 1e-12, as the public
# distributed implementation): a hard constraint in practice, still a factor
# gtsam's solvers take.
ANCHOR_SIGMA = 1e-6


def to_gtsam_pose(pose: Pose) -> gtsam.Pose3:
    return gtsam.Pose3(gtsam.Rot3(pose.rotation), np.asarray(pose.translation, dtype=np.float64))


def from_gtsam_pose(pose: gtsam.Pose3) -> Pose:
    return Pose(
        np.asarray(pose.rotation().matrix(), dtype=np.float64),
        np.asarray(pose.translation(), dtype=np.float64),
    )


def _between(edge: Edge) -> gtsam.BetweenFactorPose3:
    noise = gtsam.noiseModel.Gaussian.Information(edge.information)
    return gtsam.BetweenFactorPose3(edge.source, edge.target, to_gtsam_pose(edge.measurement), noise)


def gtsam_graph(graph: PoseGraph, *, anchor: int | None = None) -> gtsam.NonlinearFactorGraph:
    """The edges as ``BetweenFactorPose3``, plus a prior at ``anchor``'s vertex when one is given."""
    factors = gtsam.NonlinearFactorGraph()
    for edge in graph.edges:
        factors.add(_between(edge))
    if anchor is not None:
        factors.add(
            gtsam.PriorFactorPose3(
                anchor, to_gtsam_pose(graph.poses[anchor]), gtsam.noiseModel.Isotropic.Sigma(6, ANCHOR_SIGMA)
            )
        )
    return factors


def gtsam_values(poses: Mapping[int, Pose]) -> gtsam.Values:
    values = gtsam.Values()
    for key, pose in poses.items():
        values.insert(key, to_gtsam_pose(pose))
    return values


@dataclass(frozen=True)
class TwoStageResult:
    """The two-stage estimate: ``rotations`` (stage 1, projected) and ``poses`` (after stage 2)."""

    relaxed_rotations: dict[int, FloatArray]
    rotations: dict[int, FloatArray]
    poses: dict[int, Pose]


def _check_solvable(graph: PoseGraph) -> None:
    if len(graph.poses) < 2:
        raise GraphError("a pose graph needs at least two vertices to optimise")
    if not graph.is_connected():
        raise GraphError("the pose graph is not connected: no single frame holds all of it")


def solve_two_stage(graph: PoseGraph, *, anchor: int | None = None) -> TwoStageResult:
    """Chordal rotations then one linearised pose step, over the whole graph at once.

    The anchor keeps its vertex's pose (rotation and translation) exactly; the
    pose step linearises at zero translation, as the distributed solver does.
    """
    _check_solvable(graph)
    anchor = graph.anchor_key() if anchor is None else anchor
    anchor_pose = graph.poses[anchor]
    free = [k for k in graph.keys if k != anchor]
    relaxed = solve_rotations(rotation_system(free, graph.edges), {anchor: anchor_pose.rotation})
    relaxed[anchor] = anchor_pose.rotation.copy()
    rotations = {k: project_to_so3(r) for k, r in relaxed.items()}
    rotations[anchor] = anchor_pose.rotation.copy()
    linearisation = {k: Pose(r, np.zeros(3)) for k, r in rotations.items()}
    anchor_delta = np.concatenate([np.zeros(3), anchor_pose.translation])
    deltas = solve_pose_updates(pose_system(free, graph.edges, linearisation), {anchor: anchor_delta})
    deltas[anchor] = anchor_delta
    return TwoStageResult(relaxed, rotations, retract(linearisation, deltas))


@dataclass(frozen=True)
class CentralizedResult:
    """gtsam's estimate: ``poses``, ``cost`` (edges only, no prior), iterations, and where it started."""

    poses: dict[int, Pose]
    cost: float
    iterations: int
    method: Method
    initial: Literal["chordal", "graph"]
    anchor: int


def solve_centralized(
    graph: PoseGraph,
    *,
    method: Method = "gauss-newton",
    initial: Literal["chordal", "graph"] = "chordal",
    anchor: int | None = None,
    max_iterations: int = 100,
    relative_tolerance: float = 1e-10,
) -> CentralizedResult:
    """gtsam's centralized optimum of the pose graph, the gauge fixed at ``anchor``'s vertex."""
    if method not in METHODS:
        raise ConfigError(f"method must be one of {METHODS}, got {method!r}")
    if initial not in ("chordal", "graph"):
        raise ConfigError(f"initial must be 'chordal' or 'graph', got {initial!r}")
    _check_solvable(graph)
    anchor = graph.anchor_key() if anchor is None else anchor
    start = solve_two_stage(graph, anchor=anchor).poses if initial == "chordal" else dict(graph.poses)
    factors = gtsam_graph(graph, anchor=anchor)
    values = gtsam_values(start)
    optimizer: gtsam.NonlinearOptimizer
    if method == "gauss-newton":
        gn = gtsam.GaussNewtonParams()
        gn.setMaxIterations(max_iterations)
        gn.setRelativeErrorTol(relative_tolerance)
        gn.setAbsoluteErrorTol(0.0)
        optimizer = gtsam.GaussNewtonOptimizer(factors, values, gn)
    else:
        lm = gtsam.LevenbergMarquardtParams()
        lm.setMaxIterations(max_iterations)
        lm.setRelativeErrorTol(relative_tolerance)
        lm.setAbsoluteErrorTol(0.0)
        optimizer = gtsam.LevenbergMarquardtOptimizer(factors, values, lm)
    result = optimizer.optimize()
    poses = {k: from_gtsam_pose(result.atPose3(k)) for k in graph.keys}
    return CentralizedResult(poses, graph.cost(poses), int(optimizer.iterations()), method, initial, anchor)
