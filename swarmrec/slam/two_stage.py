"""The two linear least-squares problems of two-stage pose graph optimisation.

Stage 1, rotations by chordal relaxation. For every edge ``(i, j)`` with
measured rotation ``R_ij``, ``R_j = R_i R_ij`` is linear in the nine entries of
the rotations; dropping the constraint that they be rotations gives

    min  sum_ij  w_ij || R_i R_ij - R_j ||_F^2 ,   w_ij = trace(Omega_ij^rot) / 6

(``w`` makes the chordal cost match the geodesic one, ``||R_a - R_b||_F^2 ~ 2 theta^2``,
for an isotropic rotation information). Writing ``X_i = R_i^T`` the residual is
``R_ij^T X_i - X_j`` (3x3), so the three columns of ``X`` (the rows of ``R``) are
three independent problems with one and the same normal matrix: one
factorisation, three right-hand sides. The estimate is projected to SO(3)
afterwards (:func:`~swarmrec.slam.lie.project_to_so3`).

Stage 2, full poses, linearised once around the stage-1 rotations ``R^_i`` and
translations ``t^_i``. Each pose moves by ``delta_i = (theta_i, dt_i)``:
``R_i = R^_i Exp(theta_i)``, ``t_i = t^_i + dt_i`` (a global translation update),
and each edge's residual, weighted by its full information matrix, is

    r_rot   = Log( R_ij^T R_i^T R_j )
    r_trans = (R^_i R_ij)^T ( t_j - t_i - R_i t_ij )

``r_rot`` is gtsam's rotation error; ``r_trans`` is its translation error with
the frame that rotates it frozen at the linearisation point (exactly gtsam's
when the rotation error is zero), which keeps the translation linear. So the
stage-2 solution is exact in the translations whatever ``t^`` is (zero, as in the
public implementation), and the rotations get one Gauss-Newton correction that
accounts for the translation measurements.

:class:`BlockSystem` holds either problem restricted to some *free* keys, the
other keys (a neighbour's, or the anchor) entering only the right-hand side:
the centralized solve frees every key but the anchor, a distributed agent its
own keys. Its normal matrix does not change between Gauss-Seidel iterations,
so it is factorised once.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from swarmrec.slam.errors import GraphError
from swarmrec.slam.graph import Edge
from swarmrec.slam.keys import describe_key
from swarmrec.slam.lie import FloatArray, Pose, hat, project_to_so3, right_jacobian_inverse, so3_exp, so3_log

__all__ = [
    "POSE_SIZE",
    "ROTATION_SIZE",
    "BlockSystem",
    "chordal_weight",
    "pose_jacobians",
    "pose_residual",
    "pose_system",
    "retract",
    "rotation_jacobians",
    "rotation_residual",
    "rotation_system",
    "rotation_vector",
    "rotations_from_vectors",
    "solve_pose_updates",
    "solve_rotations",
]

ROTATION_SIZE = 9  # floats per rotation estimate (row-major R)
POSE_SIZE = 6  # floats per pose update (theta, dt)


def chordal_weight(edge: Edge) -> float:
    """``w_ij``: the chordal weight of an edge from the rotation block of its information."""
    return float(np.trace(edge.information[:3, :3])) / 6.0


def rotation_residual(edge: Edge, x_source: FloatArray, x_target: FloatArray) -> FloatArray:
    """The chordal residual ``R_ij^T X_i - X_j`` (``X = R^T``), equal to ``(R_i R_ij - R_j)^T``."""
    out: FloatArray = edge.measurement.rotation.T @ x_source - x_target
    return out


def rotation_jacobians(edge: Edge) -> tuple[FloatArray, FloatArray]:
    """The (constant) 3x3 blocks of :func:`rotation_residual` for each column of ``X_i`` and ``X_j``."""
    return edge.measurement.rotation.T.copy(), -np.eye(3)


def pose_residual(
    edge: Edge,
    lin_source: Pose,
    lin_target: Pose,
    delta_source: FloatArray,
    delta_target: FloatArray,
    *,
    frozen: bool = True,
) -> FloatArray:
    """The stage-2 residual (rotation, translation) of an edge at ``lin (+) delta`` (see the module doc).

    ``frozen`` keeps the frame of the translation residual at the linearisation
    point (the first pass, from zero translations); without it the frame moves
    with ``R_i`` (the later, relinearised passes: the separable SO(3) x R^3 cost).
    """
    r_i = lin_source.rotation @ so3_exp(delta_source[:3])
    r_j = lin_target.rotation @ so3_exp(delta_target[:3])
    t_i = lin_source.translation + delta_source[3:]
    t_j = lin_target.translation + delta_target[3:]
    z = edge.measurement
    frame = (lin_source.rotation if frozen else r_i) @ z.rotation
    return np.concatenate([so3_log(z.rotation.T @ r_i.T @ r_j), frame.T @ (t_j - t_i - r_i @ z.translation)])


def pose_jacobians(
    edge: Edge, lin_source: Pose, lin_target: Pose, *, frozen: bool = True
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``(J_i, J_j, r0)``: :func:`pose_residual` ~ ``r0 + J_i delta_i + J_j delta_j`` near zero."""
    z = edge.measurement
    m = lin_source.rotation.T @ lin_target.rotation
    e0 = so3_log(z.rotation.T @ m)
    jr_inv = right_jacobian_inverse(e0)
    frame = lin_source.rotation @ z.rotation
    j_i = np.zeros((6, 6))
    j_j = np.zeros((6, 6))
    j_i[:3, :3] = -jr_inv @ m.T
    if frozen:
        # d/dtheta of -F^T R^ Exp(theta) t_ij, F frozen
        j_i[3:, :3] = z.rotation.T @ hat(z.translation)
    else:
        # d/dtheta of R_ij^T Exp(-theta) R^_i^T (t_j - t_i)
        j_i[3:, :3] = z.rotation.T @ hat(
            lin_source.rotation.T @ (lin_target.translation - lin_source.translation)
        )
    j_i[3:, 3:] = -frame.T
    j_j[:3, :3] = jr_inv
    j_j[3:, 3:] = frame.T
    r0 = np.concatenate(
        [
            e0,
            frame.T @ (lin_target.translation - lin_source.translation - lin_source.rotation @ z.translation),
        ]
    )
    return j_i, j_j, r0


def rotation_vector(rotation: FloatArray) -> FloatArray:
    """The 9 floats of a (relaxed) rotation as sent between robots: ``R`` row by row."""
    return np.asarray(rotation, dtype=np.float64).reshape(9).copy()


def rotations_from_vectors(vectors: Mapping[int, FloatArray]) -> dict[int, FloatArray]:
    """Relaxed rotations (9 floats each) projected to SO(3)."""
    return {k: project_to_so3(np.asarray(v, dtype=np.float64).reshape(3, 3)) for k, v in vectors.items()}


def retract(linearisation: Mapping[int, Pose], deltas: Mapping[int, FloatArray]) -> dict[int, Pose]:
    """``R^ Exp(theta)``, ``t^ + dt`` for every key of ``deltas``."""
    return {
        k: Pose(linearisation[k].rotation @ so3_exp(d[:3]), linearisation[k].translation + d[3:])
        for k, d in deltas.items()
    }


@dataclass(frozen=True)
class _Coupling:
    row: int  # block index of the free key
    key: int  # the fixed key whose value enters
    matrix: FloatArray  # rhs[row] += matrix @ value[key]


class BlockSystem:
    """``H x = b0 + sum C y_fixed`` over free block variables (``block`` rows, ``columns`` right-hand sides).

    Built by :func:`rotation_system` or :func:`pose_system`; :meth:`solve` takes
    the values of the fixed keys it couples to and returns the free keys' values.
    """

    def __init__(self, keys: Sequence[int], block: int, columns: int) -> None:
        self.keys = tuple(keys)
        self.block = block
        self.columns = columns
        self._index = {k: n for n, k in enumerate(self.keys)}
        self._rows: list[np.ndarray] = []
        self._cols: list[np.ndarray] = []
        self._vals: list[np.ndarray] = []
        self._rhs = np.zeros((len(self.keys) * block, columns))
        self._couplings: list[_Coupling] = []
        self._factor: spla.SuperLU | None = None

    @property
    def fixed_keys(self) -> frozenset[int]:
        """The keys whose values :meth:`solve` needs."""
        return frozenset(c.key for c in self._couplings)

    def _add_block(self, a: int, b: int, value: FloatArray) -> None:
        base_r = np.arange(self.block) + a * self.block
        base_c = np.arange(self.block) + b * self.block
        rr, cc = np.meshgrid(base_r, base_c, indexing="ij")
        self._rows.append(rr.ravel())
        self._cols.append(cc.ravel())
        self._vals.append(np.asarray(value, dtype=np.float64).ravel())

    def add_residual(
        self,
        source: int,
        target: int,
        j_source: FloatArray,
        j_target: FloatArray,
        r0: FloatArray,
        weight: FloatArray,
    ) -> None:
        """Add ``|| r0 + J_s y_s + J_t y_t ||^2_W``; keys not in this system are fixed (right-hand side)."""
        r0 = r0.reshape(len(r0), -1)
        terms = [(self._index.get(source), source, j_source), (self._index.get(target), target, j_target)]
        for row, _, jac in terms:
            if row is None:
                continue
            jw = jac.T @ weight
            self._rhs[row * self.block : (row + 1) * self.block] -= jw @ r0
            for col, key, other in terms:
                if col is None:
                    self._couplings.append(_Coupling(row, key, -(jw @ other)))
                else:
                    self._add_block(row, col, jw @ other)
        self._factor = None

    def _factorised(self) -> spla.SuperLU:
        if self._factor is None:
            n = len(self.keys) * self.block
            if n == 0:
                raise GraphError("a system with no free variable")
            rows = np.concatenate(self._rows) if self._rows else np.zeros(0, int)
            cols = np.concatenate(self._cols) if self._cols else np.zeros(0, int)
            vals = np.concatenate(self._vals) if self._vals else np.zeros(0)
            hessian = sp.csc_matrix((vals, (rows, cols)), shape=(n, n))
            try:
                self._factor = spla.splu(hessian)
            except RuntimeError:
                raise GraphError(self._singular_message()) from None
        return self._factor

    def _singular_message(self) -> str:
        first = describe_key(self.keys[0]) if self.keys else "?"
        return (
            f"the linear system over {len(self.keys)} keys (first {first}) is singular: part of the "
            "graph is tied to nothing known (no anchor, no estimated neighbour)"
        )

    def solve(self, fixed: Mapping[int, FloatArray]) -> FloatArray:
        """The free keys' values, shape ``(len(keys), block, columns)``."""
        rhs = self._rhs.copy()
        for coupling in self._couplings:
            value = fixed.get(coupling.key)
            if value is None:
                raise GraphError(f"no value for the fixed key {describe_key(coupling.key)}")
            start = coupling.row * self.block
            rhs[start : start + self.block] += coupling.matrix @ value.reshape(-1, self.columns)
        x = self._factorised().solve(rhs)
        if not np.all(np.isfinite(x)):
            raise GraphError(self._singular_message())
        return np.asarray(x, dtype=np.float64).reshape(len(self.keys), self.block, self.columns)


def rotation_system(free: Iterable[int], edges: Iterable[Edge]) -> BlockSystem:
    """The chordal relaxation over ``free`` keys (solve it with :func:`solve_rotations`)."""
    system = BlockSystem(sorted(free), 3, 3)
    for edge in edges:
        a_s, a_t = rotation_jacobians(edge)
        system.add_residual(
            edge.source, edge.target, a_s, a_t, np.zeros((3, 3)), chordal_weight(edge) * np.eye(3)
        )
    return system


def pose_system(
    free: Iterable[int], edges: Iterable[Edge], linearisation: Mapping[int, Pose], *, frozen: bool = True
) -> BlockSystem:
    """The stage-2 system over ``free`` keys around ``linearisation``; other keys' deltas enter at solve."""
    system = BlockSystem(sorted(free), 6, 1)
    for edge in edges:
        j_s, j_t, r0 = pose_jacobians(
            edge, linearisation[edge.source], linearisation[edge.target], frozen=frozen
        )
        system.add_residual(edge.source, edge.target, j_s, j_t, r0, edge.information)
    return system


def solve_rotations(system: BlockSystem, fixed: Mapping[int, FloatArray]) -> dict[int, FloatArray]:
    """Relaxed rotations (3x3, not yet projected) of the free keys, given the fixed keys' rotations."""
    x = system.solve({k: r.T for k, r in fixed.items()})
    return {k: x[n].T.copy() for n, k in enumerate(system.keys)}


def solve_pose_updates(system: BlockSystem, fixed: Mapping[int, FloatArray]) -> dict[int, FloatArray]:
    """Pose updates ``(theta, dt)`` of the free keys, given the fixed keys' updates."""
    x = system.solve(fixed)
    return {k: x[n, :, 0].copy() for n, k in enumerate(system.keys)}
