"""Same place from poses, and recall@k / AUC on hand-made descriptors."""

from __future__ import annotations

import numpy as np
import pytest

from swarmrec.vpr.places import (
    PlaceThresholds,
    eligible_pairs,
    retrieval_metrics,
    same_place,
    view_directions,
)


def test_the_identity_quaternion_looks_along_z() -> None:
    np.testing.assert_allclose(view_directions(np.array([[0.0, 0.0, 0.0, 1.0]])), [[0.0, 0.0, 1.0]])


def test_same_place_needs_near_cameras_similar_views_and_frames_apart() -> None:
    positions = np.array([[0.0, 0, 0], [0.4, 0, 0], [0.6, 0, 0], [0.0, 0, 0]])
    c, s = np.cos(np.radians(40)), np.sin(np.radians(40))
    directions = np.array([[1.0, 0, 0], [1.0, 0, 0], [1.0, 0, 0], [c, s, 0]])
    frames = np.array([0, 200, 400, 600])
    closures = same_place(positions, directions, frames, PlaceThresholds(0.5, 30.0, 100))
    # 0-1: 0.4 m, same view -> yes. 0-2: 0.6 m -> no. 0-3: 40 deg -> no. 1-2: 0.2 m -> yes.
    expected = np.zeros((4, 4), bool)
    expected[0, 1] = expected[1, 0] = expected[1, 2] = expected[2, 1] = True
    np.testing.assert_array_equal(closures, expected)
    near_in_time = same_place(
        positions, directions, np.array([0, 50, 400, 600]), PlaceThresholds(0.5, 30.0, 100)
    )
    assert not near_in_time[0, 1]  # 50 frames apart: the same moment, not a loop closure


def _circle(degrees: list[float]) -> np.ndarray:
    """Unit 2-D descriptors at these angles: squared distance 2 - 2 cos grows with the angle between."""
    angles = np.radians(degrees)
    return np.stack([np.cos(angles), np.sin(angles)], axis=1)


def test_recall_at_k_and_auc_on_five_frames_by_hand() -> None:
    closures = np.zeros((5, 5), bool)
    closures[0, 3] = closures[3, 0] = True  # frames 0 and 3 show the same place
    closures[1, 2] = closures[2, 1] = True  # so do 1 and 2; frame 4 matches nothing
    pairs = eligible_pairs(np.arange(5), 0)
    # At 0, 20, 90, 60, 180 deg, each true match is 2nd or 3rd nearest:
    # 0: [1, 3, ...], 1: [0, 3, 2, ...], 2: [3, 1, ...], 3: [2, 1, 0, ...].
    metrics, curve = retrieval_metrics(_circle([0, 20, 90, 60, 180]), closures, pairs)
    assert (metrics.queries, metrics.queries_with_match) == (5, 4)
    assert metrics.recall_at_1 == 0.0 and metrics.recall_at_5 == 1.0
    assert curve.auc == 0.0  # every best match is wrong
    # At 0, 25, 90, 10, 180 deg: 0 -> 3 (10 deg, hit), 3 -> 0 (10, hit), 1 -> 3 (15, miss),
    # 2 -> 1 (65, hit), 4 -> 2 (90, no true match). Walk: TP TP FP TP FP over 4 relevant queries:
    # precision 1, 1, 2/3, 3/4, 3/5 at recall 1/4, 1/2, 1/2, 3/4, 3/4.
    metrics, curve = retrieval_metrics(_circle([0, 25, 90, 10, 180]), closures, pairs)
    assert metrics.recall_at_1 == pytest.approx(3 / 4)
    np.testing.assert_allclose(curve.precision, [1, 1, 2 / 3, 3 / 4, 3 / 5], atol=1e-9)
    np.testing.assert_allclose(curve.recall, [1 / 4, 1 / 2, 1 / 2, 3 / 4, 3 / 4], atol=1e-9)
    assert curve.auc == pytest.approx(0.25 * 1.0 + 0.25 * (2 / 3 + 3 / 4) / 2)
