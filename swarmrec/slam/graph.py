"""The multi-robot pose graph: vertices (poses of robots and objects), relative-pose edges, partition.

An :class:`Edge` from key ``i`` to key ``j`` measures ``x_i^-1 x_j`` with a 6x6
information matrix in gtsam's tangent order (rotation, then translation); its
cost is gtsam's ``BetweenFactorPose3`` error. The graph is partitioned by
robot through the keys (:mod:`swarmrec.slam.keys`): an edge whose two keys
belong to different robots is a *separator*, the only kind of edge two robots
have to talk about.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np
import numpy.typing as npt

from swarmrec.slam.errors import GraphError
from swarmrec.slam.keys import describe_key, robot_of_key, symbol_chr
from swarmrec.slam.lie import FloatArray, Pose

__all__ = [
    "SYMMETRY_TOLERANCE",
    "Edge",
    "PoseGraph",
    "information_problem",
    "is_landmark_key",
]

# Information matrices read from text carry about 6 significant digits; a
# relative asymmetry above this is not rounding.
SYMMETRY_TOLERANCE = 1e-6


def information_problem(information: npt.ArrayLike) -> str | None:
    """Why a matrix cannot be an information matrix (None when it can).

    It must be 6x6, finite, symmetric (to ``SYMMETRY_TOLERANCE`` relative to its
    largest entry) and positive definite: a zero eigenvalue means a direction
    the measurement says nothing about (singular), a negative one a negative
    variance.
    """
    m = np.asarray(information, dtype=np.float64)
    if m.shape != (6, 6):
        return f"information matrix has shape {m.shape}, expected (6, 6)"
    if not np.all(np.isfinite(m)):
        return "information matrix has a non-finite entry"
    scale = float(np.max(np.abs(m)))
    if scale == 0.0:
        return "information matrix is zero (singular)"
    asymmetry = float(np.max(np.abs(m - m.T)))
    if asymmetry > SYMMETRY_TOLERANCE * scale:
        return f"information matrix is not symmetric (largest |M - M^T| entry {asymmetry:.3g})"
    eigenvalues = np.linalg.eigvalsh(0.5 * (m + m.T))
    smallest = float(eigenvalues[0])
    if smallest < -1e-12 * scale:
        return f"information matrix is not positive definite (eigenvalue {smallest:.3g})"
    if smallest <= 1e-12 * scale:
        return f"information matrix is singular (smallest eigenvalue {smallest:.3g})"
    return None


def is_landmark_key(key: int) -> bool:
    """True for the key of an object (an upper-case Symbol character)."""
    character = symbol_chr(key)
    return character.isascii() and character.isupper()


@dataclass(frozen=True, eq=False)
class Edge:
    """A relative-pose measurement ``measurement ~ x_source^-1 x_target``.

    ``information`` is the 6x6 inverse covariance in (rotation, translation)
    order; it is checked on construction (:func:`information_problem`).
    """

    source: int
    target: int
    measurement: Pose
    information: FloatArray

    def __post_init__(self) -> None:
        if self.source == self.target:
            raise GraphError(f"edge from {describe_key(self.source)} to itself")
        problem = information_problem(self.information)
        if problem is not None:
            raise GraphError(f"edge {describe_key(self.source)}-{describe_key(self.target)}: {problem}")

    @property
    def keys(self) -> tuple[int, int]:
        return (self.source, self.target)

    def other(self, key: int) -> int:
        """The key at the other end from ``key``."""
        return self.target if key == self.source else self.source

    def residual(self, source: Pose, target: Pose) -> FloatArray:
        """gtsam's between-factor error ``Log(z^-1 x_source^-1 x_target)`` (rotation, translation)."""
        return self.measurement.inverse().compose(source.between(target)).log()

    def cost(self, source: Pose, target: Pose) -> float:
        """gtsam's factor error ``1/2 e^T Omega e``."""
        e = self.residual(source, target)
        return 0.5 * float(e @ self.information @ e)


@dataclass(frozen=True, eq=False)
class PoseGraph:
    """Vertices (an estimate for every key) and edges; partitioned by robot through the keys."""

    poses: Mapping[int, Pose]
    edges: tuple[Edge, ...]
    _robot_of: Mapping[int, int | None] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        poses = MappingProxyType(dict(self.poses))
        object.__setattr__(self, "poses", poses)
        object.__setattr__(self, "edges", tuple(self.edges))
        for edge in self.edges:
            for key in edge.keys:
                if key not in poses:
                    raise GraphError(
                        f"edge {describe_key(edge.source)}-{describe_key(edge.target)} "
                        f"uses {describe_key(key)}, which has no vertex"
                    )
        object.__setattr__(self, "_robot_of", MappingProxyType({k: robot_of_key(k) for k in poses}))

    @property
    def keys(self) -> tuple[int, ...]:
        return tuple(sorted(self.poses))

    def robot_of(self, key: int) -> int:
        """The robot owning ``key``; a :class:`GraphError` for a key of no robot (a plain integer)."""
        robot = self._robot_of.get(key)
        if robot is None:
            raise GraphError(f"key {describe_key(key)} belongs to no robot (not a robot Symbol)")
        return robot

    @property
    def robots(self) -> tuple[int, ...]:
        """The robots owning at least one vertex, ascending (empty when no key is a robot Symbol)."""
        return tuple(sorted({r for r in self._robot_of.values() if r is not None}))

    def robot_keys(self, robot: int) -> tuple[int, ...]:
        return tuple(sorted(k for k, r in self._robot_of.items() if r == robot))

    def is_separator(self, edge: Edge) -> bool:
        return self.robot_of(edge.source) != self.robot_of(edge.target)

    def separators(self) -> tuple[Edge, ...]:
        return tuple(e for e in self.edges if self.is_separator(e))

    def robot_edges(self, robot: int) -> tuple[Edge, ...]:
        """Every edge touching ``robot``: its own (odometry, object) edges and its separators."""
        return tuple(e for e in self.edges if robot in (self.robot_of(e.source), self.robot_of(e.target)))

    def separator_counts(self) -> dict[tuple[int, int], int]:
        """Separators between each pair of robots ``(a, b)``, ``a < b``."""
        counts: dict[tuple[int, int], int] = {}
        for edge in self.separators():
            a, b = sorted((self.robot_of(edge.source), self.robot_of(edge.target)))
            counts[(a, b)] = counts.get((a, b), 0) + 1
        return counts

    def anchor_key(self) -> int:
        """The key the gauge is fixed at: the lowest robot's first pose (robot 0's, ``a0``, usually).

        The public distributed Gauss-Seidel puts its prior on the first key of
        robot 0's sorted values; objects (upper-case keys, which sort first)
        are skipped so the anchor is a robot pose. For plain keys, the smallest key.
        """
        robots = self.robots
        candidates = self.robot_keys(robots[0]) if robots else self.keys
        candidates = tuple(k for k in candidates if not is_landmark_key(k)) or candidates
        if not candidates:
            raise GraphError("the graph has no vertex to anchor")
        return candidates[0]

    def with_poses(self, poses: Mapping[int, Pose]) -> PoseGraph:
        """The same edges with other vertex estimates (every key must be given)."""
        missing = set(self.poses) - set(poses)
        if missing:
            raise GraphError(f"no estimate for {len(missing)} keys, e.g. {describe_key(min(missing))}")
        return PoseGraph({k: poses[k] for k in self.poses}, self.edges)

    def with_edges(self, edges: Iterable[Edge]) -> PoseGraph:
        return PoseGraph(self.poses, tuple(edges))

    def cost(self, poses: Mapping[int, Pose] | None = None) -> float:
        """gtsam's nonlinear cost ``sum 1/2 e^T Omega e`` over the edges (no prior) at ``poses``."""
        at = self.poses if poses is None else poses
        return float(sum(e.cost(at[e.source], at[e.target]) for e in self.edges))

    def is_connected(self) -> bool:
        """Whether every vertex is reachable from every other through the edges."""
        keys = list(self.poses)
        if not keys:
            return True
        adjacency: dict[int, list[int]] = {k: [] for k in keys}
        for edge in self.edges:
            adjacency[edge.source].append(edge.target)
            adjacency[edge.target].append(edge.source)
        seen = {keys[0]}
        stack = [keys[0]]
        while stack:
            for nxt in adjacency[stack.pop()]:
                if nxt not in seen:
                    seen.add(nxt)
                    stack.append(nxt)
        return len(seen) == len(keys)
