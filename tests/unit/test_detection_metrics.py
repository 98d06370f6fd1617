"""mAP@0.5 (swarmrec.detection.metrics) on cases worked out by hand: perfect detections, a false
positive ranked first, a missed object, duplicates, the IoU threshold, wrong classes, ignored
("difficult") objects, the mean over classes, and operating points across classes."""

from __future__ import annotations

import numpy as np
import pytest

from swarmrec.detection.metrics import (
    GroundTruth,
    Outcome,
    Predictions,
    average_precision,
    box_iou,
    evaluate_detections,
    match_frame,
)
from swarmrec.errors import ConfigError

pytestmark = pytest.mark.unit

A = [0.0, 0.0, 10.0, 10.0]
B = [20.0, 20.0, 30.0, 40.0]
C = [50.0, 0.0, 60.0, 10.0]
FAR = [100.0, 100.0, 110.0, 110.0]


def truth(boxes: list[list[float]], classes: list[int], ignore: list[bool] | None = None) -> GroundTruth:
    flags = None if ignore is None else np.array(ignore)
    return GroundTruth(np.array(boxes).reshape(-1, 4), np.array(classes), flags)


def found(*dets: tuple[list[float], float, int]) -> Predictions:
    if not dets:
        return Predictions.empty()
    boxes, scores, classes = zip(*dets, strict=True)
    return Predictions(np.array(boxes), np.array(scores), np.array(classes))


def test_box_iou_by_hand() -> None:
    iou = box_iou([A, [5.0, 0.0, 15.0, 10.0], [0.0, 0.0, 0.0, 0.0]], [A, [5.0, 5.0, 10.0, 10.0]])
    np.testing.assert_allclose(
        iou,
        [
            [1.0, 25 / 100],  # a quarter of A
            [50 / 150, 25 / 100],  # half of A, union 150
            [0.0, 0.0],  # a box without area overlaps nothing
        ],
    )
    assert box_iou(np.zeros((0, 4)), [A]).shape == (0, 1)


def test_perfect_detections_give_ap_one_for_every_class() -> None:
    truths = [truth([A, B], [1, 2]), truth([C], [1])]
    dets = [found((A, 0.9, 1), (B, 0.8, 2)), found((C, 0.7, 1))]
    result = evaluate_detections(dets, truths)
    assert result.per_class[1].ap == 1.0 and result.per_class[2].ap == 1.0
    assert result.mean_ap == 1.0
    assert result.evaluated_classes == [1, 2]
    assert result.per_class[1].n_truth == 2 and result.per_class[1].true_positives == 2


def test_a_false_positive_ranked_first_halves_the_precision_of_the_single_object() -> None:
    # Ranking FP (0.9), TP (0.8): precision 0, 1/2 at recall 0, 1 -> interpolated 1/2 over [0, 1].
    result = evaluate_detections([found((FAR, 0.9, 1), (A, 0.8, 1))], [truth([A], [1])])
    assert result.per_class[1].ap == pytest.approx(0.5)
    # A false positive ranked after the last true positive costs nothing.
    result = evaluate_detections([found((A, 0.9, 1), (FAR, 0.8, 1))], [truth([A], [1])])
    assert result.per_class[1].ap == pytest.approx(1.0)


def test_a_missed_object_caps_recall() -> None:
    result = evaluate_detections([found((A, 0.9, 1))], [truth([A, B], [1, 1])])
    assert result.per_class[1].ap == pytest.approx(0.5)
    assert result.per_class[1].max_recall == pytest.approx(0.5)


def test_the_textbook_ranking_tp_fp_tp_fp_tp() -> None:
    # 3 objects in 3 images; ranked TP FP TP FP TP: recall 1/3 1/3 2/3 2/3 1, precision 1 1/2 2/3 1/2 3/5;
    # interpolated precision 1 on (0, 1/3], 2/3 on (1/3, 2/3], 3/5 on (2/3, 1].
    truths = [truth([A], [4]), truth([B], [4]), truth([C], [4])]
    dets = [
        found((A, 0.9, 4), (FAR, 0.8, 4)),
        found((B, 0.7, 4), (FAR, 0.6, 4)),
        found((C, 0.5, 4)),
    ]
    result = evaluate_detections(dets, truths)
    assert result.per_class[4].ap == pytest.approx((1 + 2 / 3 + 3 / 5) / 3)
    np.testing.assert_allclose(result.per_class[4].precision, [1, 1 / 2, 2 / 3, 1 / 2, 3 / 5])
    np.testing.assert_allclose(result.per_class[4].recall, [1 / 3, 1 / 3, 2 / 3, 2 / 3, 1])


def test_average_precision_all_point_interpolation() -> None:
    assert average_precision([], []) == 0.0
    assert average_precision([0.5, 1.0], [1.0, 1.0]) == pytest.approx(1.0)
    assert average_precision([0.25, 0.5], [0.5, 1.0]) == pytest.approx(0.5)  # precision 1 up to recall 0.5
    with pytest.raises(ValueError, match="differ"):
        average_precision([0.5], [1.0, 0.5])


def test_a_second_detection_of_one_object_is_a_false_positive() -> None:
    outcome = match_frame(found(([0.0, 0.0, 10.0, 9.0], 0.6, 1), (A, 0.9, 1)), truth([A], [1]))
    # The better-scored one takes the object, whatever the order given.
    assert outcome.tolist() == [Outcome.FALSE_POSITIVE, Outcome.TRUE_POSITIVE]
    result = evaluate_detections([found((A, 0.9, 1), ([0.0, 0.0, 10.0, 9.0], 0.95, 1))], [truth([A], [1])])
    assert result.per_class[1].ap == pytest.approx(1.0)  # the duplicate comes after full recall


def test_iou_exactly_at_the_threshold_matches_and_just_below_does_not() -> None:
    half = [0.0, 0.0, 10.0, 5.0]  # IoU with A: 50 / 100
    assert match_frame(found((half, 0.9, 1)), truth([A], [1])).tolist() == [Outcome.TRUE_POSITIVE]
    less = [0.0, 0.0, 10.0, 4.99]
    assert match_frame(found((less, 0.9, 1)), truth([A], [1])).tolist() == [Outcome.FALSE_POSITIVE]
    assert match_frame(found((less, 0.9, 1)), truth([A], [1]), iou_threshold=0.4).tolist() == [
        Outcome.TRUE_POSITIVE
    ]


def test_a_wrong_class_is_a_false_positive_of_its_class_and_a_miss_of_the_true_one() -> None:
    result = evaluate_detections([found((A, 0.9, 2))], [truth([A], [1])])
    assert result.per_class[1].ap == 0.0 and result.per_class[1].n_detections == 0
    assert result.per_class[2].ap is None and result.per_class[2].n_detections == 1
    assert result.evaluated_classes == [1]
    assert result.mean_ap == 0.0


def test_a_detection_of_an_ignored_object_is_neither_right_nor_wrong() -> None:
    gt = truth([A, B], [1, 1], ignore=[False, True])
    outcome = match_frame(found((B, 0.95, 1), (A, 0.9, 1)), gt)
    assert outcome.tolist() == [Outcome.IGNORED, Outcome.TRUE_POSITIVE]
    result = evaluate_detections([found((B, 0.95, 1), (A, 0.9, 1))], [gt])
    assert result.per_class[1].ap == 1.0
    assert result.per_class[1].n_truth == 1 and result.per_class[1].n_ignored_truth == 1
    # Not finding the ignored object costs nothing either.
    assert evaluate_detections([found((A, 0.9, 1))], [gt]).per_class[1].ap == 1.0
    # A class whose only objects are ignored has no AP and stays out of the mean.
    only_ignored = evaluate_detections([found((A, 0.9, 1))], [truth([A, C], [1, 3], [False, True])])
    assert only_ignored.per_class[3].ap is None and only_ignored.evaluated_classes == [1]


def test_the_mean_is_over_classes_with_objects() -> None:
    truths = [truth([A, B], [1, 2]), truth([C], [3])]
    dets = [found((A, 0.9, 1), (FAR, 0.9, 2), (B, 0.8, 2), (FAR, 0.5, 7)), found()]
    result = evaluate_detections(dets, truths)
    # class 1: 1.0; class 2: FP then TP -> 0.5; class 3: missed -> 0.0; class 7: no objects, not counted.
    assert [result.per_class[c].ap for c in (1, 2, 3)] == pytest.approx([1.0, 0.5, 0.0])
    assert result.per_class[7].ap is None
    assert result.mean_ap == pytest.approx(0.5)
    assert result.n_truth == 3


def test_no_images_or_no_detections() -> None:
    empty = evaluate_detections([], [])
    assert empty.mean_ap == 0.0 and empty.evaluated_classes == [] and empty.n_frames == 0
    nothing = evaluate_detections([found()], [truth([A], [1])])
    assert nothing.per_class[1].ap == 0.0 and nothing.per_class[1].max_recall == 0.0


def test_operating_points_pool_every_class() -> None:
    truths = [truth([A, B], [1, 2]), truth([C], [1], [True])]
    dets = [found((A, 0.9, 1), (FAR, 0.6, 2), (B, 0.3, 2)), found((C, 0.8, 1))]
    result = evaluate_detections(dets, truths)
    high = result.at_threshold(0.7)  # A (TP) and C (ignored)
    assert (high.true_positives, high.false_positives, high.ignored) == (1, 0, 1)
    assert (high.precision, high.recall) == (1.0, 0.5)
    assert high.detections_per_frame == 1.0
    low = result.at_threshold(0.3)  # + FAR (FP) and B (TP)
    assert (low.true_positives, low.false_positives) == (2, 1)
    assert low.precision == pytest.approx(2 / 3) and low.recall == 1.0
    assert low.f1 == pytest.approx(0.8)
    assert low.detections_per_frame == 2.0
    best = result.best_f1([0.3, 0.7, 0.95])
    assert best.threshold == 0.3  # F1 0.8 against 2/3 at 0.7 and 0 at 0.95
    assert result.at_threshold(0.95).precision == 1.0  # nothing kept: no wrong detection


def test_malformed_input_is_refused() -> None:
    with pytest.raises(ValueError, match=r"\(n, 4\)"):
        GroundTruth(np.zeros((2, 3)), np.zeros(2, np.int64))
    with pytest.raises(ValueError, match="2 entries for 1 boxes"):
        Predictions(np.zeros((1, 4)), np.zeros(2), np.zeros(1, np.int64))
    with pytest.raises(ValueError, match="images"):
        evaluate_detections([found()], [])
    with pytest.raises(ConfigError, match="iou_threshold"):
        evaluate_detections([found()], [truth([A], [1])], iou_threshold=0.0)
