"""Ground truth from poses and the precision-recall protocol, by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from swarmrec.core.types import ConstellationSequence, Trajectory
from swarmrec.evaluation.groundtruth import _distances, ground_truth, quaternion_to_matrix
from swarmrec.evaluation.pr import precision_recall
from tests.conftest import make

S45 = math.sin(math.pi / 4)
LOOK_PLUS_X = [0, S45, 0, S45]  # camera z axis -> world +x (90 degrees about y)
LOOK_MINUS_X = [0, -S45, 0, S45]
LOOK_PLUS_Z = [0, 0, 0, 1]


def test_quaternion_turns_the_camera_axis_as_expected() -> None:
    assert np.allclose(quaternion_to_matrix(np.array(LOOK_PLUS_X))[:, 2], [1, 0, 0])
    assert np.allclose(quaternion_to_matrix(np.array(LOOK_MINUS_X))[:, 2], [-1, 0, 0])


def _sequence(depths: list[float]) -> ConstellationSequence:
    frames = tuple(make(("cup", 0, 0, z), ("book", 0, 0, z)) for z in depths)
    n = len(frames)
    names = tuple(str(i) for i in range(80))
    return ConstellationSequence(tuple(map(str, range(n))), np.arange(n, dtype=float), frames, names)


def test_cameras_facing_the_same_scene_point_are_a_closure() -> None:
    # A at the origin looking +x, B at x = 4 looking -x, both 2 m from their
    # objects: both scene points are (2, 0, 0). C looks +z: its point (0, 0, 2)
    # is sqrt(8) = 2.83 m from (2, 0, 0), beyond the 2 m threshold.
    seq = _sequence([2.0, 2.0, 2.0])
    traj = Trajectory(
        np.arange(3, dtype=float),
        np.array([[0, 0, 0], [4, 0, 0], [0, 0, 0]], float),
        np.array([LOOK_PLUS_X, LOOK_MINUS_X, LOOK_PLUS_Z], float),
    )
    gt = ground_truth(seq, traj, exclusion=0)
    assert np.allclose(gt.scene, [[2, 0, 0], [2, 0, 0], [0, 0, 2]])
    assert gt.distances[0, 1] == pytest.approx(0.0, abs=1e-12)
    assert gt.distances[0, 2] == pytest.approx(math.sqrt(8))
    assert gt.closures[0, 1] and gt.closures[1, 0] and not gt.closures[0, 2]
    assert not gt.closures[0, 0]  # a frame is never its own closure


def test_frames_within_the_exclusion_window_are_never_closures() -> None:
    seq = _sequence([2.0, 2.0, 2.0])
    traj = Trajectory(np.arange(3, dtype=float), np.zeros((3, 3)), np.tile(LOOK_PLUS_Z, (3, 1)))
    gt = ground_truth(seq, traj, exclusion=1)
    assert gt.closures[0, 2] and not gt.closures[0, 1] and not gt.closures[1, 2]


def test_fr3_rules_separate_the_two_sides_of_the_desks() -> None:
    # Same scene point, cameras at y = +1 and y = -1: opposite sides.
    seq = _sequence([1.0, 1.0])
    traj = Trajectory(
        np.arange(2, dtype=float),
        np.array([[0, 1, 0], [0, -1, 0]], float),
        np.array([[0.7071068, 0, 0, 0.7071068], [-0.7071068, 0, 0, 0.7071068]]),
    )
    plain = ground_truth(seq, traj, exclusion=0)
    ruled = ground_truth(seq, traj, exclusion=0, rules="tum-fr3-office")
    assert plain.closures[0, 1]
    assert not ruled.closures[0, 1] and not ruled.closures[1, 0]


# Scores of 4 frames (-1 on the diagonal as the exclusion), true closures
# (0,1) and (0,2). Best matches: 0->1 (0.9, true), 1->0 (0.9, true),
# 2->3 (0.3, false), 3->1 (0.4, false). Walk 0.9, 0.9, 0.4, 0.3:
# TP 1 2 2 2, FP 0 0 1 2; relevant frames 0, 1, 2 -> 3.
# precision 1, 1, 2/3, 1/2; recall 1/3, 2/3, 2/3, 2/3; AUC = 1/3 (trapezoid from recall 1/3).
SCORES = np.array([[-1, 0.9, 0.2, 0.0], [0.9, -1, 0.1, 0.4], [0.2, 0.1, -1, 0.3], [0.0, 0.4, 0.3, -1]])
TRUTH = np.zeros((4, 4), bool)
TRUTH[0, 1] = TRUTH[1, 0] = TRUTH[0, 2] = TRUTH[2, 0] = True


def test_precision_recall_walks_the_best_matches_in_score_order() -> None:
    curve = precision_recall(SCORES, TRUTH)
    assert curve.best_match.tolist() == [1, 0, 3, 1]
    assert curve.relevant == 3
    assert curve.precision == pytest.approx([1, 1, 2 / 3, 1 / 2])
    assert curve.recall == pytest.approx([1 / 3, 2 / 3, 2 / 3, 2 / 3])
    assert curve.auc == pytest.approx(1 / 3)


def test_closures_with_an_ignored_frame_are_not_missed_closures() -> None:
    scores = SCORES.copy()
    scores[2, :] = scores[:, 2] = -2.0  # frame 2 had too few objects
    scores[2, 2] = -1.0
    curve = precision_recall(scores, TRUTH)
    assert curve.relevant == 2  # frame 2's closure with 0 no longer counts


@pytest.mark.parametrize("n", [1, 255, 256, 257, 1300])
def test_distances_by_blocks_of_rows_are_the_whole_matrix_expressions_doubles(n: int) -> None:
    rng = np.random.default_rng(n)
    scene = rng.normal(size=(n, 3)) * rng.uniform(0.1, 30.0, size=(n, 1))
    diff = scene[:, None, :] - scene[None, :, :]
    whole = np.sqrt((diff * diff).sum(-1))
    assert _distances(scene).tobytes() == whole.tobytes()
