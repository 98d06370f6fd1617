"""The committed office detector (models/detector/office_detector.onnx) in OnnxDetector, without
torch: it loads with the YOLOv8 layout, and on frames of a world rendered here that no split of
its training used, it finds most true objects at the recommended threshold, with boxes inside
the image and classes of the office."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from swarmrec.detection import DetectorSettings, Layout, OnnxDetector
from swarmrec.detection.metrics import GroundTruth, Outcome, Predictions, evaluate_detections, match_frame
from swarmrec.synthetic import OfficeConfig, generate_office
from swarmrec.synthetic.render import SequenceRenderer

pytestmark = pytest.mark.unit

REPO = Path(__file__).resolve().parents[2]
MODEL_DIR = REPO / "models" / "detector"
MODEL = MODEL_DIR / "office_detector.onnx"
#: Not among the worlds of the training, validation and test splits (models/detector/metrics.json).
FRESH_SEED = 20_260_917
FRAMES = (150, 600, 1050, 1500, 1950, 2400)


@pytest.fixture(scope="module")
def metrics() -> dict[str, Any]:
    data: dict[str, Any] = json.loads((MODEL_DIR / "metrics.json").read_text())
    return data


@pytest.fixture(scope="module")
def detector(metrics: dict[str, Any]) -> OnnxDetector:
    settings = DetectorSettings(conf_threshold=metrics["recommended_conf_threshold"], intra_op_threads=2)
    return OnnxDetector(MODEL, settings)


@pytest.fixture(scope="module")
def fresh(metrics: dict[str, Any]) -> list[tuple[np.ndarray, GroundTruth]]:
    """Frames of a fresh default office, with their true objects marked as the training script does."""
    assert all(FRESH_SEED not in seeds for seeds in metrics["worlds"].values())
    rule = metrics["ground_truth"]
    renderer = SequenceRenderer(generate_office(OfficeConfig(seed=FRESH_SEED)))
    frames = []
    for i in FRAMES:
        frame = renderer.render(i)
        boxes = frame.boxes.astype(np.float64)
        sides = np.minimum(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1])
        kept = (sides >= rule["min_side_px"]) & (frame.visible_fraction >= rule["min_visible_fraction"])
        frames.append((frame.rgb, GroundTruth(boxes, frame.labels, ~kept)))
    return frames


def _predictions(detector: OnnxDetector, image: np.ndarray) -> Predictions:
    found = detector.detect(image)
    return Predictions(
        np.array([d.box for d in found]).reshape(-1, 4),
        np.array([d.score for d in found]),
        np.array([d.class_id for d in found], np.int64),
    )


def test_the_committed_model_is_small_and_a_static_v8_detector(
    detector: OnnxDetector, metrics: dict[str, Any]
) -> None:
    assert MODEL.stat().st_size < 2_000_000
    assert MODEL.stat().st_size == metrics["model_bytes"]
    assert detector.layout is Layout.V8
    assert list(detector.input_hw) == metrics["input"]["shape"][2:]
    assert all(d % 32 == 0 for d in detector.input_hw)


def test_it_finds_most_true_objects_of_a_fresh_world(
    detector: OnnxDetector, fresh: list[tuple[np.ndarray, GroundTruth]], metrics: dict[str, Any]
) -> None:
    office = {c["class_id"] for c in metrics["classes"]}
    true_positives = false_positives = objects = 0
    for image, truth in fresh:
        found = _predictions(detector, image)
        assert set(found.class_ids.tolist()) <= office
        assert (
            (found.boxes[:, :2] >= 0).all()
            and (found.boxes[:, 2] <= 640).all()
            and (found.boxes[:, 3] <= 480).all()
        )
        assert (found.boxes[:, 2:] > found.boxes[:, :2]).all()
        assert ((found.scores >= metrics["recommended_conf_threshold"]) & (found.scores <= 1)).all()
        outcome = match_frame(found, truth)
        true_positives += int(np.sum(outcome == Outcome.TRUE_POSITIVE))
        false_positives += int(np.sum(outcome == Outcome.FALSE_POSITIVE))
        objects += int(truth.kept.sum())
    recall = true_positives / objects
    precision = true_positives / max(true_positives + false_positives, 1)
    measured = metrics["test_at_threshold"]
    # On the 500 held-out test frames: recall 0.64, precision 0.84 (metrics.json). These six frames
    # of another world give 0.62 and 0.84; six frames of five more worlds gave 0.63-0.73 and
    # 0.80-0.87, so the bounds sit 0.15 below the test figures: more than half the objects found.
    assert recall >= max(0.5, measured["recall"] - 0.15), (recall, measured["recall"])
    assert precision >= measured["precision"] - 0.15, (precision, measured["precision"])


def test_its_ap_on_a_fresh_world_is_near_the_reported_map(
    fresh: list[tuple[np.ndarray, GroundTruth]], metrics: dict[str, Any]
) -> None:
    low = OnnxDetector(MODEL, DetectorSettings(conf_threshold=metrics["evaluation"]["conf_threshold"]))
    result = evaluate_detections([_predictions(low, image) for image, _ in fresh], [t for _, t in fresh])
    # Six frames hold few objects of the rare classes (which have the lowest AP), so their mean
    # is noisy and above the test set's 0.49: 0.58 here, 0.53-0.67 on six frames of five more worlds.
    assert result.mean_ap >= metrics["test_map50"] - 0.1, (result.mean_ap, metrics["test_map50"])
