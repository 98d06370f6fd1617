"""The two linear problems (chordal rotations, linearised poses) against finite differences and references."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from swarmrec.slam.centralized import solve_centralized, solve_two_stage, to_gtsam_pose
from swarmrec.slam.graph import Edge
from swarmrec.slam.keys import pose_key
from swarmrec.slam.lie import Pose, so3_exp
from swarmrec.slam.two_stage import (
    chordal_weight,
    pose_jacobians,
    pose_residual,
    rotation_jacobians,
    rotation_residual,
)
from tests.slam_graphs import information, make_graph

RNG = np.random.default_rng(11)


def random_pose(rng: np.random.Generator, spread: float = 2.0) -> Pose:
    return Pose(so3_exp(rng.normal(0.0, 1.0, 3)), rng.normal(0.0, spread, 3))


def random_edge(rng: np.random.Generator) -> Edge:
    return Edge(pose_key(0, 0), pose_key(0, 1), random_pose(rng), information(0.1, 0.2))


def numeric_jacobian(function, size: int, h: float = 1e-6) -> np.ndarray:  # type: ignore[no-untyped-def]
    columns = []
    for k in range(size):
        step = np.zeros(size)
        step[k] = h
        columns.append((function(step) - function(-step)) / (2 * h))
    return np.stack(columns, axis=1)


def test_chordal_residual_is_linear_with_the_stated_blocks() -> None:
    edge = random_edge(RNG)
    a_source, a_target = rotation_jacobians(edge)
    x_source, x_target = RNG.normal(size=(3, 3)), RNG.normal(size=(3, 3))
    for column in range(3):

        def source_column(d: np.ndarray, column: int = column) -> np.ndarray:
            x = x_source.copy()
            x[:, column] += d
            return rotation_residual(edge, x, x_target)[:, column]

        def target_column(d: np.ndarray, column: int = column) -> np.ndarray:
            x = x_target.copy()
            x[:, column] += d
            return rotation_residual(edge, x_source, x)[:, column]

        assert numeric_jacobian(source_column, 3) == pytest.approx(a_source, abs=1e-8)
        assert numeric_jacobian(target_column, 3) == pytest.approx(a_target, abs=1e-8)
    # (R_i R_ij - R_j)^T with X = R^T
    r_i, r_j = so3_exp([0.1, 0.2, 0.3]), so3_exp([0.3, -0.1, 0.2])
    expected = (r_i @ edge.measurement.rotation - r_j).T
    assert rotation_residual(edge, r_i.T, r_j.T) == pytest.approx(expected)


def test_chordal_weight_matches_the_geodesic_cost_for_isotropic_information() -> None:
    # ||I - Exp(w)||_F^2 ~ 2 |w|^2, so w_ij = kappa / 2 for a rotation information kappa I.
    edge = Edge(pose_key(0, 0), pose_key(0, 1), Pose.identity(), np.diag([8.0, 8.0, 8.0, 1.0, 1.0, 1.0]))
    assert chordal_weight(edge) == 4.0


@pytest.mark.parametrize("frozen", [True, False])
@pytest.mark.parametrize("seed", range(3))
def test_pose_jacobians_match_finite_differences(frozen: bool, seed: int) -> None:
    rng = np.random.default_rng(seed)
    edge = random_edge(rng)
    lin_i, lin_j = random_pose(rng), random_pose(rng)
    j_i, j_j, r0 = pose_jacobians(edge, lin_i, lin_j, frozen=frozen)
    zero = np.zeros(6)
    assert r0 == pytest.approx(pose_residual(edge, lin_i, lin_j, zero, zero, frozen=frozen), abs=1e-12)
    numeric_i = numeric_jacobian(lambda d: pose_residual(edge, lin_i, lin_j, d, zero, frozen=frozen), 6)
    numeric_j = numeric_jacobian(lambda d: pose_residual(edge, lin_i, lin_j, zero, d, frozen=frozen), 6)
    assert j_i == pytest.approx(numeric_i, abs=1e-6)
    assert j_j == pytest.approx(numeric_j, abs=1e-6)


def test_pose_residual_is_gtsams_error_when_the_rotation_error_is_zero() -> None:
    # With R_j = R_i R_ij the SE(3) log's V^-1 is the identity: both residuals coincide.
    edge = random_edge(RNG)
    x_i = random_pose(RNG)
    x_j = Pose(x_i.rotation @ edge.measurement.rotation, RNG.normal(0.0, 2.0, 3))
    factor = gtsam.BetweenFactorPose3(
        edge.source, edge.target, to_gtsam_pose(edge.measurement), gtsam.noiseModel.Unit.Create(6)
    )
    values = gtsam.Values()
    values.insert(edge.source, to_gtsam_pose(x_i))
    values.insert(edge.target, to_gtsam_pose(x_j))
    expected = factor.unwhitenedError(values)
    for frozen in (True, False):
        got = pose_residual(edge, x_i, x_j, np.zeros(6), np.zeros(6), frozen=frozen)
        assert got == pytest.approx(expected, abs=1e-9)
    # ... and the rotation part is gtsam's for any poses.
    x_j = random_pose(RNG)
    values.update(edge.target, to_gtsam_pose(x_j))
    got = pose_residual(edge, x_i, x_j, np.zeros(6), np.zeros(6), frozen=False)
    assert got[:3] == pytest.approx(factor.unwhitenedError(values)[:3], abs=1e-9)


def test_centralized_chordal_rotations_solve_the_stacked_least_squares() -> None:
    graph, _ = make_graph(2, 4, sigma_r=0.1, sigma_t=0.1, seed=3)
    anchor = graph.anchor_key()
    result = solve_two_stage(graph)
    # The same problem written row by row, independently: unknowns vec(R_k) (row-major) for free keys.
    free = [k for k in graph.keys if k != anchor]
    col = {k: 9 * n for n, k in enumerate(free)}
    rows, rhs = [], []
    r_anchor = graph.poses[anchor].rotation
    for edge in graph.edges:
        w = np.sqrt(chordal_weight(edge))
        for a in range(3):
            for b in range(3):
                # (R_i R_ij - R_j)[a, b] = sum_c R_i[a, c] R_ij[c, b] - R_j[a, b]
                row = np.zeros(9 * len(free))
                constant = 0.0
                for c in range(3):
                    if edge.source == anchor:
                        constant += r_anchor[a, c] * edge.measurement.rotation[c, b]
                    else:
                        row[col[edge.source] + 3 * a + c] += edge.measurement.rotation[c, b]
                if edge.target == anchor:
                    constant -= r_anchor[a, b]
                else:
                    row[col[edge.target] + 3 * a + b] -= 1.0
                rows.append(w * row)
                rhs.append(-w * constant)
    solution = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)[0]
    for key in free:
        assert result.relaxed_rotations[key] == pytest.approx(
            solution[col[key] : col[key] + 9].reshape(3, 3), abs=1e-9
        )


def test_two_stage_recovers_noise_free_ground_truth_exactly() -> None:
    graph, truth = make_graph(3, 5, initial_noise=0.3)
    # The anchor must sit at its true pose for the solution to be the truth itself.
    anchor = graph.anchor_key()
    graph = graph.with_poses({**graph.poses, anchor: truth[anchor]})
    poses = solve_two_stage(graph).poses
    for key, pose in truth.items():
        assert poses[key].rotation == pytest.approx(pose.rotation, abs=1e-9)
        assert poses[key].translation == pytest.approx(pose.translation, abs=1e-9)


def test_centralized_gauss_newton_and_levenberg_marquardt_agree_and_beat_two_stage() -> None:
    graph, _ = make_graph(2, 5, sigma_r=0.1, sigma_t=0.2, seed=5, initial_noise=0.1)
    gn = solve_centralized(graph)
    lm = solve_centralized(graph, method="levenberg-marquardt", initial="graph")
    for key in graph.keys:
        assert gn.poses[key].translation == pytest.approx(lm.poses[key].translation, abs=1e-5)
    assert gn.cost == pytest.approx(lm.cost, rel=1e-6)
    assert gn.cost <= graph.cost(solve_two_stage(graph).poses) + 1e-12
    assert gn.poses[graph.anchor_key()].translation == pytest.approx(
        graph.poses[graph.anchor_key()].translation
    )
