"""Rejecting wrong inter-robot associations (beyond the paper, whose back end assumes none).

Two independent checks on the separators of a team's graph:

- :func:`pcm`, pairwise consistency maximisation (Mangelson et al., ICRA 2018)
  per pair of robots, with no optimisation of the team graph. Two separators
  ``k`` and ``l`` between robots alpha and beta (``Z ~ x_a^-1 x_b``, ``a`` alpha's key)
  close a cycle through each robot's own map,

      C_kl = Z_k  (x_bk^-1 x_bl)  Z_l^-1  (x_ak^-1 x_al)^-1  = I  when both are right,

  where the relative poses inside a map come from that robot's own
  single-robot estimate (:func:`local_estimates`). They are consistent when
  ``e = Log(C_kl)`` has a squared Mahalanobis norm below the chi-square
  quantile (6 degrees of freedom) of ``confidence``. Its covariance is the four
  factors' covariances moved to the cycle's end by adjoints, first order: the
  two separators' (their information inverted) and the two relative poses
  inside the maps (from each robot's joint marginal covariance, gtsam's
  ``Marginals``), plus ``map_sigma_*`` each, a floor for the local solve's
  own linearisation error. The kept set is
  a maximum clique of the consistency graph: the largest set of separators
  that all agree with each other. For object-object factors (``Z = I``) this
  asks whether two shared objects sit the same way relative to each other in
  both robots' maps.
- :func:`gnc`, gtsam's graduated non-convexity (``GncLMOptimizer``, truncated
  least squares) on the centralized graph, the robots' own edges declared as
  known inliers: separators whose final weight is below one half are rejected.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import gtsam
import numpy as np
import numpy.typing as npt
from scipy.stats import chi2

from swarmrec.errors import ConfigError
from swarmrec.slam.centralized import (
    ANCHOR_SIGMA,
    from_gtsam_pose,
    gtsam_graph,
    gtsam_values,
    solve_centralized,
    solve_two_stage,
    to_gtsam_pose,
)
from swarmrec.slam.graph import Edge, PoseGraph, is_landmark_key
from swarmrec.slam.lie import FloatArray, Pose, hat

__all__ = [
    "GncResult",
    "LocalMaps",
    "PcmResult",
    "PcmSettings",
    "gnc",
    "local_estimates",
    "max_clique",
    "pairwise_consistency",
    "pcm",
]

# Above this many candidates an exact maximum clique may take long; a greedy one is used instead.
EXACT_CLIQUE_LIMIT = 60


@dataclass(frozen=True)
class PcmSettings:
    """PCM's test: ``confidence`` of the chi-square gate; ``map_sigma_*`` an extra uncertainty of a
    relative pose inside one robot's map (degrees, metres) added to its marginal covariance."""

    confidence: float = 0.99
    map_sigma_rotation_deg: float = 1.0
    map_sigma_translation: float = 0.05

    def __post_init__(self) -> None:
        if not 0.0 < self.confidence < 1.0:
            raise ConfigError(f"confidence must be in (0, 1), got {self.confidence}")
        if self.map_sigma_rotation_deg <= 0.0 or self.map_sigma_translation <= 0.0:
            raise ConfigError("map sigmas must be positive")

    @property
    def threshold(self) -> float:
        return float(chi2.ppf(self.confidence, 6))

    def map_covariance(self) -> FloatArray:
        return np.diag(
            [math.radians(self.map_sigma_rotation_deg) ** 2] * 3 + [self.map_sigma_translation**2] * 3
        )


@dataclass(frozen=True)
class LocalMaps:
    """Each robot's own estimate of its keys, and the covariance of relative poses inside its map."""

    poses: dict[int, Pose]
    marginals: dict[int, gtsam.Marginals]
    robot_of: dict[int, int]

    def relative_covariance(self, a: int, b: int) -> FloatArray:
        """Covariance of ``x_a^-1 x_b`` (right perturbation) from the joint marginal of ``a`` and ``b``."""
        joint = self.marginals[self.robot_of[a]].jointMarginalCovariance(gtsam.KeyVector([a, b]))
        blocks = [[np.asarray(joint.at(r, c), dtype=np.float64) for c in (a, b)] for r in (a, b)]
        # x_a^-1 x_b perturbed: xi_b - Ad(D^-1) xi_a
        j_a = -_adjoint(self.poses[a].between(self.poses[b]).inverse())
        cov: FloatArray = (
            j_a @ blocks[0][0] @ j_a.T + j_a @ blocks[0][1] + blocks[1][0] @ j_a.T + blocks[1][1]
        )
        return 0.5 * (cov + cov.T)


def _adjoint(pose: Pose) -> FloatArray:
    """SE(3) adjoint in gtsam's (rotation, translation) order: ``T Exp(xi) = Exp(Ad_T xi) T``."""
    out = np.zeros((6, 6))
    out[:3, :3] = pose.rotation
    out[3:, 3:] = pose.rotation
    out[3:, :3] = hat(pose.translation) @ pose.rotation
    return out


def local_estimates(graph: PoseGraph) -> LocalMaps:
    """Each robot's own estimate of its keys (its own edges only, gtsam GN anchored at its first pose)."""
    poses: dict[int, Pose] = {}
    marginals: dict[int, gtsam.Marginals] = {}
    owner: dict[int, int] = {}
    for robot in graph.robots:
        keys = set(graph.robot_keys(robot))
        own = PoseGraph(
            {k: graph.poses[k] for k in keys},
            tuple(e for e in graph.edges if e.source in keys and e.target in keys),
        )
        anchor = min((k for k in keys if not is_landmark_key(k)), default=min(keys))
        estimate = solve_centralized(own, anchor=anchor).poses if len(keys) > 1 else dict(own.poses)
        poses.update(estimate)
        owner.update({k: robot for k in keys})
        marginals[robot] = gtsam.Marginals(gtsam_graph(own, anchor=anchor), gtsam_values(estimate))
    return LocalMaps(poses, marginals, owner)


def _oriented(edge: Edge, graph: PoseGraph, alpha: int) -> tuple[int, int, Pose]:
    """``(a, b, Z)`` with ``a`` alpha's key and ``Z ~ x_a^-1 x_b``."""
    if graph.robot_of(edge.source) == alpha:
        return edge.source, edge.target, edge.measurement
    return edge.target, edge.source, edge.measurement.inverse()


def pairwise_consistency(
    graph: PoseGraph, separators: Sequence[Edge], local: LocalMaps, settings: PcmSettings
) -> npt.NDArray[np.bool_]:
    """The consistency matrix of separators between one pair of robots (see the module doc)."""
    if not separators:
        return np.zeros((0, 0), dtype=bool)
    alpha = min(graph.robot_of(separators[0].source), graph.robot_of(separators[0].target))
    oriented = [_oriented(e, graph, alpha) for e in separators]
    covariances = [np.linalg.inv(e.information) for e in separators]
    floor = settings.map_covariance()
    n = len(separators)
    consistent = np.eye(n, dtype=bool)
    for k in range(n):
        a_k, b_k, z_k = oriented[k]
        for m in range(k + 1, n):
            a_m, b_m, z_m = oriented[m]
            delta_a = local.poses[a_k].between(local.poses[a_m])
            delta_b = local.poses[b_k].between(local.poses[b_m])
            # C = Z_k dB Z_m^-1 dA^-1; the inverse factors' perturbations move through Ad(factor).
            factors = [z_k, delta_b, z_m.inverse(), delta_a.inverse()]
            ad_zm, ad_da = _adjoint(z_m), _adjoint(delta_a)
            factor_cov = [
                covariances[k],
                local.relative_covariance(b_k, b_m) + floor,
                ad_zm @ covariances[m] @ ad_zm.T,
                ad_da @ (local.relative_covariance(a_k, a_m) + floor) @ ad_da.T,
            ]
            sigma = np.zeros((6, 6))
            tail = Pose.identity()
            for factor, cov in zip(reversed(factors), reversed(factor_cov), strict=True):
                move = _adjoint(tail.inverse())
                sigma += move @ cov @ move.T
                tail = factor.compose(tail)
            e = tail.log()
            consistent[k, m] = consistent[m, k] = float(e @ np.linalg.solve(sigma, e)) < settings.threshold
    return consistent


def max_clique(adjacency: npt.NDArray[np.bool_]) -> list[int]:
    """A maximum clique (exact Bron-Kerbosch with pivoting; greedy by degree above EXACT_CLIQUE_LIMIT).

    Ties between cliques of equal size go to the one found first (lower indices first).
    """
    n = len(adjacency)
    neighbours = [set(np.flatnonzero(adjacency[i])) - {i} for i in range(n)]
    if n > EXACT_CLIQUE_LIMIT:
        clique: list[int] = []
        for v in sorted(range(n), key=lambda i: (-len(neighbours[i]), i)):
            if all(v in neighbours[u] for u in clique):
                clique.append(v)
        return sorted(clique)
    best: list[int] = []

    def expand(r: list[int], p: set[int], x: set[int]) -> None:
        nonlocal best
        if len(r) + len(p) <= len(best):
            return
        if not p and not x:
            best = sorted(r)
            return
        pivot = max(p | x, key=lambda u: len(neighbours[u] & p))
        for v in sorted(p - neighbours[pivot]):
            expand([*r, v], p & neighbours[v], x & neighbours[v])
            p = p - {v}
            x = x | {v}

    expand([], set(range(n)), set())
    return best


@dataclass(frozen=True)
class PcmResult:
    """Separators kept and rejected (in the graph's order), and the per-pair consistency matrices."""

    kept: tuple[Edge, ...]
    rejected: tuple[Edge, ...]
    consistency: dict[tuple[int, int], npt.NDArray[np.bool_]]

    def graph(self, graph: PoseGraph) -> PoseGraph:
        """``graph`` without the rejected separators."""
        rejected = {id(e) for e in self.rejected}
        return graph.with_edges(e for e in graph.edges if id(e) not in rejected)


def pcm(graph: PoseGraph, settings: PcmSettings | None = None, local: LocalMaps | None = None) -> PcmResult:
    """Pairwise consistency maximisation over each pair of robots' separators."""
    settings = settings or PcmSettings()
    local = local_estimates(graph) if local is None else local
    by_pair: dict[tuple[int, int], list[Edge]] = {}
    for edge in graph.separators():
        pair = tuple(sorted((graph.robot_of(edge.source), graph.robot_of(edge.target))))
        by_pair.setdefault((pair[0], pair[1]), []).append(edge)
    keep: set[int] = set()
    matrices = {}
    for pair, edges in sorted(by_pair.items()):
        matrix = pairwise_consistency(graph, edges, local, settings)
        matrices[pair] = matrix
        keep |= {id(edges[i]) for i in max_clique(matrix)}
    separators = graph.separators()
    return PcmResult(
        tuple(e for e in separators if id(e) in keep),
        tuple(e for e in separators if id(e) not in keep),
        matrices,
    )


@dataclass(frozen=True)
class GncResult:
    """gtsam GNC's estimate, each separator's final weight, and the rejected ones (weight < 1/2)."""

    poses: dict[int, Pose]
    weights: dict[int, float]  # index in graph.edges -> weight, separators only
    rejected: tuple[Edge, ...]


def gnc(graph: PoseGraph, *, probability: float = 0.99, anchor: int | None = None) -> GncResult:
    """Graduated non-convexity (truncated least squares) with the robots' own edges as known inliers."""
    anchor = graph.anchor_key() if anchor is None else anchor
    factors = gtsam_graph(graph)
    factors.add(
        gtsam.PriorFactorPose3(
            anchor, to_gtsam_pose(graph.poses[anchor]), gtsam.noiseModel.Isotropic.Sigma(6, ANCHOR_SIGMA)
        )
    )
    separator_index = [n for n, e in enumerate(graph.edges) if graph.is_separator(e)]
    known = [n for n in range(len(graph.edges)) if n not in set(separator_index)] + [len(graph.edges)]
    params = gtsam.GncLMParams(gtsam.LevenbergMarquardtParams())
    params.setLossType(gtsam.GncLossType.TLS)
    params.setKnownInliers(known)
    start = solve_two_stage(graph, anchor=anchor).poses
    optimizer = gtsam.GncLMOptimizer(factors, gtsam_values(start), params)
    optimizer.setInlierCostThresholdsAtProbability(probability)
    result = optimizer.optimize()
    weights = np.asarray(optimizer.getWeights(), dtype=np.float64)
    poses = {k: from_gtsam_pose(result.atPose3(k)) for k in graph.keys}
    separator_weights = {n: float(weights[n]) for n in separator_index}
    rejected = tuple(graph.edges[n] for n, w in separator_weights.items() if w < 0.5)
    return GncResult(poses, separator_weights, rejected)
