"""The YOLO detector's letterbox, output decoding, NMS and ONNX runner, on tiny ONNX
graphs built here whose outputs are known constants or simple functions of the input.
Every expected box is worked out by hand from the letterbox geometry."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

import swarmrec.detection as detection
from swarmrec.detection import (
    PAD_VALUE,
    Candidates,
    Detection,
    DetectionError,
    DetectorSettings,
    Layout,
    ModelError,
    OnnxDetector,
    OutputLayoutError,
    decode_output,
    detect_layout,
    letterbox,
    non_max_suppression,
)
from swarmrec.errors import ConfigError

Dims = Sequence[int | str]


def _save(
    path: Path,
    nodes: list[onnx.NodeProto],
    inputs: list[onnx.ValueInfoProto],
    output_dims: Dims,
    output_type: int = TensorProto.FLOAT,
) -> Path:
    graph = helper.make_graph(
        nodes, "test", inputs, [helper.make_tensor_value_info("output", output_type, list(output_dims))]
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, path)
    return path


def _image_input(dims: Dims = (1, 3, 640, 640), elem_type: int = TensorProto.FLOAT) -> onnx.ValueInfoProto:
    return helper.make_tensor_value_info("images", elem_type, list(dims))


def _constant_model(path: Path, output: npt.ArrayLike, input_dims: Dims = (1, 3, 640, 640)) -> Path:
    """A model that ignores its image and always outputs ``output``."""
    value = np.asarray(output, dtype=np.float32)
    node = helper.make_node("Constant", [], ["output"], value=numpy_helper.from_array(value))
    return _save(path, [node], [_image_input(input_dims)], value.shape)


def _v5(rows: list[list[float]]) -> npt.NDArray[np.float32]:
    """A v5 output [1, N, 5 + C] from rows ``cx cy w h obj cls...``."""
    return np.array([rows], dtype=np.float32)


def _v8(rows: list[list[float]]) -> npt.NDArray[np.float32]:
    """A v8 output [1, 4 + C, N] from per-box rows ``cx cy w h cls...``."""
    return np.array([rows], dtype=np.float32).transpose(0, 2, 1).copy()


def _pixel_probe_model(path: Path, size: int) -> Path:
    """A v8 model with one class and one fixed box whose score is the model input's
    first channel at pixel (0, 0): it shows what the detector fed the model there."""
    nodes = [
        helper.make_node("Constant", [], ["starts"], value=numpy_helper.from_array(np.zeros(4, np.int64))),
        helper.make_node("Constant", [], ["ends"], value=numpy_helper.from_array(np.ones(4, np.int64))),
        helper.make_node("Slice", ["images", "starts", "ends"], ["pixel"]),
        helper.make_node("Constant", [], ["shape"], value=numpy_helper.from_array(np.array([1, 1, 1]))),
        helper.make_node("Reshape", ["pixel", "shape"], ["score"]),
        helper.make_node(
            "Constant",
            [],
            ["box"],
            value=numpy_helper.from_array(np.array([[[32.0], [32.0], [4.0], [4.0]]], np.float32)),
        ),
        helper.make_node("Concat", ["box", "score"], ["output"], axis=1),
    ]
    return _save(path, nodes, [_image_input((1, 3, size, size))], [1, 5, 1])


def _bgr(height: int, width: int, value: int = 0) -> npt.NDArray[np.uint8]:
    return np.full((height, width, 3), value, dtype=np.uint8)


def _boxes(detections: list[Detection]) -> list[tuple[float, float, float, float]]:
    return [d.box for d in detections]


def test_package_all_names_exist() -> None:
    assert sorted(detection.__all__) == sorted(set(detection.__all__))
    for name in detection.__all__:
        assert hasattr(detection, name), name


# --- letterbox -------------------------------------------------------------------------------


def test_letterbox_pads_a_tum_frame_top_and_bottom_with_grey() -> None:
    padded, placement = letterbox(_bgr(480, 640, 7), (640, 640))
    assert padded.shape == (640, 640, 3)
    assert (placement.scale_x, placement.scale_y, placement.pad_x, placement.pad_y) == (1.0, 1.0, 0, 80)
    assert (padded[:80] == PAD_VALUE).all() and (padded[560:] == PAD_VALUE).all()
    assert (padded[80:560] == 7).all()


def test_letterbox_puts_the_odd_padding_pixel_at_the_bottom() -> None:
    # 7 x 5 (h x w) into 10 x 10: gain min(10/7, 10/5) = 10/7, so 10 x 7 (h x w): 3 columns of padding.
    padded, placement = letterbox(_bgr(7, 5, 0), (10, 10))
    assert (placement.pad_x, placement.pad_y) == (1, 0)
    assert (padded[:, 0] == PAD_VALUE).all() and (padded[:, 8:] == PAD_VALUE).all()
    assert (padded[:, 1:8] == 0).all()


def test_letterbox_maps_boxes_back_through_the_scale_and_padding() -> None:
    # 960 x 1280 into 640 x 640: gain 0.5, resized 480 x 640, 80 rows of padding on top.
    _, placement = letterbox(_bgr(960, 1280), (640, 640))
    assert (placement.scale_x, placement.scale_y, placement.pad_y) == (0.5, 0.5, 80)
    back = placement.to_original([[100.0, 180.0, 300.0, 380.0]])
    assert back.tolist() == [[200.0, 200.0, 600.0, 600.0]]


def test_letterbox_clips_boxes_that_reach_into_the_padding() -> None:
    _, placement = letterbox(_bgr(480, 640), (640, 640))
    back = placement.to_original([[-5.0, 10.0, 700.0, 630.0]])
    assert back.tolist() == [[0.0, 0.0, 640.0, 480.0]]


def test_letterbox_rejects_an_image_without_channels() -> None:
    with pytest.raises(DetectionError, match="shape"):
        letterbox(np.zeros((4, 4), np.uint8), (8, 8))


# --- decoding --------------------------------------------------------------------------------


def test_v5_output_decodes_to_corner_boxes_and_objectness_times_class_score() -> None:
    out = _v5(
        [
            [50, 60, 20, 10, 0.5, 0.2, 0.8],  # class 1, 0.5 * 0.8
            [10, 10, 4, 6, 1.0, 0.9, 0.1],  # class 0, 1.0 * 0.9
        ]
    )
    c = decode_output(out, n_classes=2)
    assert c.boxes.tolist() == [[40, 55, 60, 65], [8, 7, 12, 13]]
    assert c.class_ids.tolist() == [1, 0]
    assert c.scores == pytest.approx([np.float32(0.5) * np.float32(0.8), np.float32(0.9)], rel=1e-12)


def test_v8_output_decodes_with_the_best_class_score_and_no_objectness() -> None:
    out = _v8([[50, 60, 20, 10, 0.2, 0.7, 0.1], [10, 10, 4, 6, 0.3, 0.0, 0.6]])
    assert out.shape == (1, 7, 2)
    c = decode_output(out, n_classes=3)
    assert c.boxes.tolist() == [[40, 55, 60, 65], [8, 7, 12, 13]]
    assert c.class_ids.tolist() == [1, 2]
    assert c.scores.tolist() == [float(np.float32(0.7)), float(np.float32(0.6))]


def test_layout_is_detected_from_the_shape_and_the_class_count() -> None:
    assert detect_layout((1, 25200, 85), 80) is Layout.V5
    assert detect_layout((1, 84, 8400), 80) is Layout.V8


def test_a_shape_that_fits_both_layouts_needs_the_layout_set() -> None:
    # [1, 4 + C, 5 + C]: six v5 boxes or seven v8 boxes.
    with pytest.raises(OutputLayoutError, match="both"):
        detect_layout((1, 6, 7), 2)
    out = np.zeros((1, 6, 7), np.float32)
    assert len(decode_output(out, 2, Layout.V5)) == 6
    assert len(decode_output(out, 2, Layout.V8)) == 7


def test_a_shape_that_fits_no_layout_is_an_error_naming_the_shape() -> None:
    with pytest.raises(OutputLayoutError, match=r"\[1, 10, 10\].*fits neither") as info:
        detect_layout((1, 10, 10), 80)
    assert info.value.shape == (1, 10, 10) and info.value.n_classes == 80


def test_a_forced_layout_that_does_not_fit_the_shape_is_an_error() -> None:
    with pytest.raises(OutputLayoutError, match="v8 layout needs"):
        detect_layout((1, 25200, 85), 80, Layout.V8)


@pytest.mark.parametrize("shape", [(2, 84, 10), (84, 10), (1, 1, 84, 10)])
def test_outputs_that_are_not_one_batch_of_three_axes_are_rejected(shape: tuple[int, ...]) -> None:
    with pytest.raises(OutputLayoutError, match="batch of one"):
        detect_layout(shape, 80)


# --- threshold and NMS -----------------------------------------------------------------------


def _candidates(boxes: list[list[float]], scores: list[float], classes: list[int]) -> Candidates:
    return Candidates(np.array(boxes, float), np.array(scores, float), np.array(classes, np.int64))


def test_threshold_zero_keeps_boxes_whose_score_is_exactly_zero() -> None:
    c = _candidates([[0, 0, 10, 10], [50, 50, 60, 60]], [0.0, 0.0], [0, 0])
    assert non_max_suppression(c, 0.0, 0.45, 300).tolist() == [0, 1]


def test_threshold_keeps_scores_equal_to_it_and_drops_lower_ones() -> None:
    c = _candidates([[0, 0, 10, 10], [20, 0, 30, 10], [40, 0, 50, 10]], [0.25, 0.5, 0.24], [0, 0, 0])
    assert non_max_suppression(c, 0.25, 0.45, 300).tolist() == [1, 0]


def test_nms_suppresses_overlaps_of_one_class_but_not_across_classes() -> None:
    # IoU of the two boxes: 9 x 10 / (100 + 100 - 90) = 0.818.
    boxes = [[0, 0, 10, 10], [1, 0, 11, 10]]
    same = _candidates(boxes, [0.9, 0.8], [3, 3])
    other = _candidates(boxes, [0.9, 0.8], [3, 4])
    assert non_max_suppression(same, 0.0, 0.45, 300).tolist() == [0]
    assert non_max_suppression(other, 0.0, 0.45, 300).tolist() == [0, 1]
    assert non_max_suppression(same, 0.0, 0.85, 300).tolist() == [0, 1]


def test_max_detections_counts_boxes_kept_after_nms() -> None:
    # OpenCV's top_k would cut before NMS and return only box 0 here.
    c = _candidates([[0, 0, 10, 10], [1, 0, 11, 10], [50, 50, 60, 60]], [0.9, 0.8, 0.7], [0, 0, 0])
    assert non_max_suppression(c, 0.0, 0.45, 2).tolist() == [0, 2]
    assert non_max_suppression(c, 0.0, 0.45, 1).tolist() == [0]


def test_nms_drops_degenerate_and_non_finite_boxes() -> None:
    c = _candidates(
        [[0, 0, 0, 10], [0, 0, 10, -1], [np.nan, 0, 10, 10], [0, 0, 10, 10], [20, 20, 30, 30]],
        [0.9, 0.9, 0.9, np.nan, 0.5],
        [0, 0, 0, 0, 0],
    )
    assert non_max_suppression(c, 0.0, 0.45, 300).tolist() == [4]


def test_nms_of_nothing_is_nothing() -> None:
    assert non_max_suppression(_candidates([], [], []), 0.0, 0.45, 10).tolist() == []


def test_class_aware_nms_agrees_with_opencv_batched_nms() -> None:
    rng = np.random.default_rng(7)
    n = 400
    xy = rng.uniform(0, 200, (n, 2))
    boxes = np.hstack([xy, xy + rng.uniform(5, 60, (n, 2))])
    scores = rng.permutation(np.arange(1, n + 1)) / n  # distinct and positive: OpenCV's own rules apply
    classes = rng.integers(0, 5, n)
    wh = boxes[:, 2:] - boxes[:, :2]
    expected = cv2.dnn.NMSBoxesBatched(
        np.hstack([boxes[:, :2], wh]), scores.astype(np.float32), classes.astype(np.int32), 0.0, 0.5
    )
    got = non_max_suppression(Candidates(boxes, scores, classes.astype(np.int64)), 0.0, 0.5, n)
    assert got.tolist() == np.asarray(expected).reshape(-1).tolist()


# --- the ONNX detector -----------------------------------------------------------------------


def test_detector_maps_v5_boxes_back_to_a_tum_frame(tmp_path: Path) -> None:
    # 480 x 640 into 640 x 640: gain 1, 80 rows of padding on top.
    out = _v5([[200, 280, 200, 200, 0.9, 0.1, 0.8], [500, 400, 40, 20, 0.5, 0.6, 0.2]])
    model = _constant_model(tmp_path / "v5.onnx", out)
    detector = OnnxDetector(model, DetectorSettings(n_classes=2))
    assert detector.input_hw == (640, 640) and detector.layout is Layout.V5
    dets = detector.detect(_bgr(480, 640))
    assert [d.class_id for d in dets] == [1, 0]
    assert _boxes(dets) == [(100.0, 100.0, 300.0, 300.0), (480.0, 310.0, 520.0, 330.0)]
    assert dets[0].score == pytest.approx(0.9 * 0.8, rel=1e-6)
    assert dets[1].score == pytest.approx(0.5 * 0.6, rel=1e-6)


def test_detector_maps_v8_boxes_back_through_an_upscale(tmp_path: Path) -> None:
    # 240 x 320 into 640 x 640: gain 2, resized 480 x 640, 80 rows of padding on top.
    # Box cx 320 cy 320 w 200 h 100 -> model (220, 270, 420, 370) -> image (110, 95, 210, 145).
    model = _constant_model(tmp_path / "v8.onnx", _v8([[320, 320, 200, 100, 0.1, 0.7]]))
    detector = OnnxDetector(model, DetectorSettings(n_classes=2))
    assert detector.layout is Layout.V8
    (det,) = detector.detect(_bgr(240, 320))
    assert det.box == (110.0, 95.0, 210.0, 145.0)
    assert det.class_id == 1 and det.score == pytest.approx(0.7, rel=1e-6)


def test_detector_applies_class_aware_nms_threshold_and_max_detections(tmp_path: Path) -> None:
    # Boxes 0 and 1 overlap with IoU 19 x 20 / (800 - 380) = 0.905 (same class: 1 goes);
    # box 2 overlaps 0 but is another class (kept); box 3 scores below the threshold.
    out = _v8(
        [
            [100, 100, 20, 20, 0.9, 0.0],
            [101, 100, 20, 20, 0.8, 0.0],
            [100, 100, 20, 20, 0.0, 0.7],
            [300, 300, 20, 20, 0.1, 0.0],
        ]
    )
    model = _constant_model(tmp_path / "nms.onnx", out)
    dets = OnnxDetector(model, DetectorSettings(n_classes=2, conf_threshold=0.2)).detect(_bgr(640, 640))
    assert [(d.class_id, d.box) for d in dets] == [
        (0, (90.0, 90.0, 110.0, 110.0)),
        (1, (90.0, 90.0, 110.0, 110.0)),
    ]
    everything = OnnxDetector(model, DetectorSettings(n_classes=2)).detect(_bgr(640, 640))
    assert [d.class_id for d in everything] == [0, 1, 0]
    one = OnnxDetector(model, DetectorSettings(n_classes=2, max_detections=1)).detect(_bgr(640, 640))
    assert len(one) == 1 and one[0].score == pytest.approx(0.9, rel=1e-6)


def test_detector_drops_boxes_wholly_in_the_padding(tmp_path: Path) -> None:
    # Rows 0..80 of the model input are padding for a 480 x 640 frame.
    out = _v8([[320, 40, 100, 40, 0.9], [320, 320, 100, 40, 0.5]])
    model = _constant_model(tmp_path / "pad.onnx", out)
    dets = OnnxDetector(model, DetectorSettings(n_classes=1)).detect(_bgr(480, 640))
    assert _boxes(dets) == [(270.0, 220.0, 370.0, 260.0)]


def test_detector_feeds_the_model_rgb_scaled_to_one(tmp_path: Path) -> None:
    model = _pixel_probe_model(tmp_path / "probe.onnx", 64)
    image = _bgr(64, 64)
    image[..., 0] = 255  # blue
    image[..., 2] = 51  # red: the model's first channel when the detector swaps BGR to RGB
    (det,) = OnnxDetector(model, DetectorSettings(n_classes=1)).detect(image)
    assert det.score == pytest.approx(51 / 255, rel=1e-6)


def test_detector_pads_with_grey_where_the_image_does_not_reach(tmp_path: Path) -> None:
    model = _pixel_probe_model(tmp_path / "probe.onnx", 64)
    (det,) = OnnxDetector(model, DetectorSettings(n_classes=1)).detect(_bgr(32, 64, 255))
    assert det.score == pytest.approx(PAD_VALUE / 255, rel=1e-6)


def test_detector_runs_a_half_precision_model(tmp_path: Path) -> None:
    value = _v8([[320, 320, 200, 100, 0.5]]).astype(np.float16)
    node = helper.make_node("Constant", [], ["output"], value=numpy_helper.from_array(value))
    inputs = [_image_input(elem_type=TensorProto.FLOAT16)]
    model = _save(tmp_path / "half.onnx", [node], inputs, value.shape, TensorProto.FLOAT16)
    (det,) = OnnxDetector(model, DetectorSettings(n_classes=1)).detect(_bgr(640, 640))
    assert det.box == (220.0, 270.0, 420.0, 370.0) and det.score == 0.5


def test_detector_reads_a_static_input_size_from_the_model(tmp_path: Path) -> None:
    model = _constant_model(tmp_path / "m.onnx", _v8([[1, 1, 1, 1, 1]]), input_dims=(1, 3, 320, 256))
    detector = OnnxDetector(model, DetectorSettings(n_classes=1, input_hw=(640, 640)))
    assert detector.input_hw == (320, 256)


def test_detector_uses_the_configured_size_for_a_dynamic_input(tmp_path: Path) -> None:
    model = _constant_model(
        tmp_path / "m.onnx", _v8([[200, 200, 100, 100, 1]]), input_dims=("batch", 3, "height", "width")
    )
    detector = OnnxDetector(model, DetectorSettings(n_classes=1, input_hw=(416, 416)))
    assert detector.input_hw == (416, 416)
    # 208 x 416 into 416 x 416: gain 1, 104 rows on top: (150, 150, 250, 250) -> (150, 46, 250, 146).
    assert _boxes(detector.detect(_bgr(208, 416))) == [(150.0, 46.0, 250.0, 146.0)]


def test_detector_honours_a_forced_layout_for_an_ambiguous_output(tmp_path: Path) -> None:
    out = np.zeros((1, 6, 7), np.float32)
    model = _constant_model(tmp_path / "m.onnx", out)
    with pytest.raises(ModelError, match="both"):
        OnnxDetector(model, DetectorSettings(n_classes=2))
    assert OnnxDetector(model, DetectorSettings(n_classes=2, layout=Layout.V8)).layout is Layout.V8


def test_detector_rejects_a_model_with_the_wrong_class_count_at_load(tmp_path: Path) -> None:
    model = _constant_model(tmp_path / "m.onnx", np.zeros((1, 84, 10), np.float32))
    with pytest.raises(ModelError, match=r"m\.onnx.*fits neither"):
        OnnxDetector(model, DetectorSettings(n_classes=20))


def test_detector_rejects_a_dynamic_output_of_the_wrong_layout_when_it_runs(tmp_path: Path) -> None:
    shape = helper.make_node("Constant", [], ["shape"], value=numpy_helper.from_array(np.array([1, 3, -1])))
    reshape = helper.make_node("Reshape", ["images", "shape"], ["output"])
    model = _save(tmp_path / "m.onnx", [shape, reshape], [_image_input((1, 3, "h", "w"))], [1, 3, "n"])
    detector = OnnxDetector(model, DetectorSettings(n_classes=80, input_hw=(32, 32)))
    with pytest.raises(ModelError, match="fits neither"):
        detector.detect(_bgr(32, 32))


def test_detector_reports_a_missing_or_unreadable_model(tmp_path: Path) -> None:
    with pytest.raises(ModelError, match="no such model file"):
        OnnxDetector(tmp_path / "absent.onnx")
    garbage = tmp_path / "garbage.onnx"
    garbage.write_bytes(b"not a model")
    with pytest.raises(ModelError, match="cannot load"):
        OnnxDetector(garbage)


@pytest.mark.parametrize(
    ("dims", "elem_type", "reason"),
    [
        ((1, 1, 64, 64), TensorProto.FLOAT, "input"),
        ((2, 3, 64, 64), TensorProto.FLOAT, "input"),
        ((1, 3, 64), TensorProto.FLOAT, "input"),
        ((1, 3, 64, 64), TensorProto.INT32, "float image input"),
    ],
)
def test_detector_rejects_inputs_that_are_not_one_rgb_float_image(
    tmp_path: Path, dims: Dims, elem_type: int, reason: str
) -> None:
    node = helper.make_node(
        "Constant", [], ["output"], value=numpy_helper.from_array(np.zeros((1, 5, 2), np.float32))
    )
    model = _save(tmp_path / "m.onnx", [node], [_image_input(dims, elem_type)], [1, 5, 2])
    with pytest.raises(ModelError, match=reason):
        OnnxDetector(model, DetectorSettings(n_classes=1))


def test_detector_rejects_a_model_with_two_inputs(tmp_path: Path) -> None:
    node = helper.make_node(
        "Constant", [], ["output"], value=numpy_helper.from_array(np.zeros((1, 5, 2), np.float32))
    )
    extra = helper.make_tensor_value_info("extra", TensorProto.FLOAT, [1])
    model = _save(tmp_path / "m.onnx", [node], [_image_input(), extra], [1, 5, 2])
    with pytest.raises(ModelError, match="one image input"):
        OnnxDetector(model, DetectorSettings(n_classes=1))


@pytest.mark.parametrize(
    "image",
    [np.zeros((64, 64), np.uint8), np.zeros((64, 64, 4), np.uint8), np.zeros((64, 64, 3), np.float32)],
)
def test_detector_rejects_images_that_are_not_bgr_uint8(
    tmp_path: Path, image: npt.NDArray[np.generic]
) -> None:
    model = _constant_model(tmp_path / "m.onnx", _v8([[1, 1, 1, 1, 1]]))
    detector = OnnxDetector(model, DetectorSettings(n_classes=1))
    with pytest.raises(DetectionError, match="BGR uint8"):
        detector.detect(image)  # type: ignore[arg-type]  # wrong on purpose


@pytest.mark.parametrize(
    "changes",
    [
        {"n_classes": 0},
        {"conf_threshold": -0.1},
        {"conf_threshold": 1.5},
        {"iou_threshold": 0.0},
        {"max_detections": 0},
        {"input_hw": (0, 640)},
        {"intra_op_threads": -1},
    ],
)
def test_settings_out_of_range_are_config_errors(changes: dict[str, object]) -> None:
    with pytest.raises(ConfigError):
        DetectorSettings(**changes)  # type: ignore[arg-type]  # wrong on purpose
