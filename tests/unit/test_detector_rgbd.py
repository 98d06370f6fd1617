"""The RGB-D detector's logic without a bus: a frame's boxes to a constellation, bad
frames to counted skips with the error the step answers, the model and threshold
settings, and the main job's side (the RGB-D folder it prepares, the sequence it reads
back). Models are tiny ONNX graphs whose boxes are known (tests/detector_models.py)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt
import pytest

from swarmrec.datasets.constellations import format_constellation
from swarmrec.datasets.labels import COCO_NAMES
from swarmrec.datasets.tum_rgbd import RgbdImageError, frame_id_of, load_rgbd, read_tum_rgbd
from swarmrec.detection import (
    DEFAULT_CONF_THRESHOLD,
    CameraIntrinsics,
    DetectionError,
    ModelError,
    OnnxDetector,
    RgbdPipeline,
    conf_threshold_for,
    load_detector,
    model_path,
)
from swarmrec.errors import ConfigError
from swarmrec.evaluation.source import DatasetSource
from swarmrec.experiments.places.pixels import detected_sequence, prepare_pixels
from swarmrec.experiments.places.settings import PixelSettings, PlacesSettings
from swarmrec.models import MODELS_ENV
from swarmrec.services.detector.rgbd import process_frame
from swarmrec.services.settings import DetectorSettings, RgbdSettings
from swarmrec.wire import messages as pb
from tests.detector_models import constant_v8_model

H, W = 480, 640
PAD = 80  # a 640x480 frame sits 80 px below the top of a 640x640 model input
CAM = CameraIntrinsics()
CUP, LAPTOP, BOOK = COCO_NAMES.index("cup"), COCO_NAMES.index("laptop"), COCO_NAMES.index("book")


def _input_box(x1: float, y1: float, x2: float, y2: float) -> tuple[float, float, float, float]:
    """A box in frame pixels as the model sees it (letterboxed)."""
    return (x1, y1 + PAD, x2, y2 + PAD)


@pytest.fixture
def two_box_model(tmp_path: Path) -> Path:
    """A cup at frame pixels [100, 200) x [50, 90) and a laptop at [300, 400) x [200, 260)."""
    return constant_v8_model(
        tmp_path / "two.onnx",
        [(CUP, 0.9, *_input_box(100, 50, 200, 90)), (LAPTOP, 0.6, *_input_box(300, 200, 400, 260))],
    )


def _depth(*regions: tuple[int, int, int, int, int]) -> npt.NDArray[np.uint16]:
    """A depth image, 0 (no reading) except ``(x1, y1, x2, y2, value)`` rectangles."""
    depth = np.zeros((H, W), np.uint16)
    for x1, y1, x2, y2, value in regions:
        depth[y1:y2, x1:x2] = value
    return depth


def _median_point(x1: int, y1: int, x2: int, y2: int, z: float) -> list[float]:
    """The median 3D point of a box of constant depth ``z`` metres, from the pinhole model."""
    u, v = np.meshgrid(np.arange(x1, x2), np.arange(y1, y2))
    return [
        float(np.median((u - CAM.cx) * z / CAM.fx)),
        float(np.median((v - CAM.cy) * z / CAM.fy)),
        z,
    ]


def _write_frames(root: Path, depths: list[npt.NDArray[np.uint16]], start: float = 1.0) -> Path:
    """A TUM folder with one grey RGB image per depth image, 1/30 s apart."""
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rgb_lines, depth_lines = [], []
    for k, depth in enumerate(depths):
        t = f"{start + k / 30:.6f}"
        cv2.imwrite(str(root / "rgb" / f"{t}.png"), np.full((H, W, 3), 90, np.uint8))
        cv2.imwrite(str(root / "depth" / f"{t}.png"), depth)
        rgb_lines.append(f"{t} rgb/{t}.png")
        depth_lines.append(f"{t} depth/{t}.png")
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    return root


# --- one frame to one constellation -------------------------------------------------------


def test_each_box_becomes_its_label_at_the_median_point_of_its_valid_depth(two_box_model: Path) -> None:
    pipeline = RgbdPipeline(OnnxDetector(two_box_model), CAM)
    rgb = np.full((H, W, 3), 90, np.uint8)
    result = pipeline.run(rgb, _depth((100, 50, 200, 90, 5000), (300, 200, 400, 260, 12500)))
    c = result.constellation
    assert c.labels.tolist() == [CUP, LAPTOP]  # best score first, as detected
    assert np.allclose(c.positions[0], _median_point(100, 50, 200, 90, 1.0))
    assert np.allclose(c.positions[1], _median_point(300, 200, 400, 260, 2.5))
    assert result.dropped_no_depth == 0 and len(result.detections) == 2
    assert set(result.seconds) == {"detect", "points"}


def test_a_box_without_valid_depth_is_dropped_and_counted(two_box_model: Path) -> None:
    pipeline = RgbdPipeline(OnnxDetector(two_box_model), CAM)
    result = pipeline.run(np.zeros((H, W, 3), np.uint8), _depth((300, 200, 400, 260, 10000)))
    assert result.constellation.labels.tolist() == [LAPTOP]
    assert result.dropped_no_depth == 1


def test_the_background_inside_a_box_does_not_move_its_point_when_most_pixels_are_the_object(
    two_box_model: Path,
) -> None:
    # The cup fills 3/4 of its box at 1 m, a wall 4 m away shows through the rest.
    depth = _depth((100, 50, 200, 90, 20000), (100, 50, 175, 90, 5000))
    result = RgbdPipeline(OnnxDetector(two_box_model), CAM).run(np.zeros((H, W, 3), np.uint8), depth)
    assert result.constellation.positions[0, 2] == pytest.approx(1.0)


def test_a_depth_image_that_does_not_fit_the_rgb_image_is_refused(two_box_model: Path) -> None:
    pipeline = RgbdPipeline(OnnxDetector(two_box_model), CAM)
    with pytest.raises(DetectionError, match="does not fit"):
        pipeline.run(np.zeros((H, W, 3), np.uint8), np.zeros((H // 2, W // 2), np.uint16))


# --- frames the service skips, and what the step answers -----------------------------------


def test_bad_frames_are_skips_with_their_cause_and_good_frames_constellations(
    tmp_path: Path, two_box_model: Path
) -> None:
    good = _depth((100, 50, 200, 90, 5000), (300, 200, 400, 260, 10000))
    seq = read_tum_rgbd(_write_frames(tmp_path / "seq", [good] * 5 + [_depth()]))
    frames = seq.frames
    frames[1].depth_path.unlink()
    frames[2].rgb_path.write_bytes(b"\x89PNG\r\n\x1a\n cut short")
    cv2.imwrite(str(frames[3].depth_path), np.zeros((H // 2, W // 2), np.uint16))
    cv2.imwrite(str(frames[4].depth_path), np.zeros((H, W), np.uint8))
    pipeline = RgbdPipeline(OnnxDetector(two_box_model), CAM)

    results = [process_frame(pipeline, f) for f in frames]

    assert [r.outcome for r in results] == [
        "detected",
        "missing_image",
        "corrupt_image",
        "size_mismatch",
        "corrupt_image",  # an 8-bit depth PNG would give wrong metres
        "no_objects",  # both boxes over "no reading"
    ]
    assert results[0].constellation is not None and len(results[0].constellation) == 2
    assert set(results[0].seconds) == {"decode", "detect", "points"}
    assert results[5].constellation is not None and len(results[5].constellation) == 0
    assert results[5].dropped_no_depth == 2
    for r in results[1:5]:
        assert r.constellation is None
    assert results[1].code == pb.ErrorCode.ERROR_CODE_NOT_FOUND
    assert {r.code for r in results[2:5]} == {pb.ErrorCode.ERROR_CODE_INVALID_ARGUMENT}
    # The reason names the file the user has to look at.
    assert str(frames[1].depth_path) in results[1].reason and "missing" in results[1].reason
    assert str(frames[2].rgb_path) in results[2].reason
    assert "depth is 320x240 but its RGB image" in results[3].reason


def test_a_model_that_fails_on_the_image_is_a_detector_error_skip(tmp_path: Path) -> None:
    # The image reshaped to [1, 84, -1]: the load-time checks pass (dynamic sizes), but a
    # 3 x 640 x 640 input does not divide by 84, so onnxruntime fails on every image.
    from onnx import TensorProto, helper, numpy_helper, save

    shape = numpy_helper.from_array(np.array([1, 84, -1], np.int64))
    graph = helper.make_graph(
        [
            helper.make_node("Constant", [], ["shape"], value=shape),
            helper.make_node("Reshape", ["images", "shape"], ["output"]),
        ],
        "bad",
        [helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, "h", "w"])],
        [helper.make_tensor_value_info("output", TensorProto.FLOAT, [1, 84, "n"])],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    save(model, tmp_path / "bad.onnx")
    seq = read_tum_rgbd(_write_frames(tmp_path / "seq", [_depth()]))

    result = process_frame(RgbdPipeline(OnnxDetector(tmp_path / "bad.onnx"), CAM), seq.frames[0])

    assert result.outcome == "detector_error" and result.constellation is None
    assert result.code == pb.ErrorCode.ERROR_CODE_INTERNAL
    assert "inference failed" in result.reason


def test_image_errors_carry_their_problem(tmp_path: Path) -> None:
    seq = read_tum_rgbd(_write_frames(tmp_path / "seq", [_depth()] * 2))
    seq.frames[0].rgb_path.unlink()
    with pytest.raises(RgbdImageError) as info:
        load_rgbd(seq.frames[0].rgb_path, seq.frames[0].depth_path)
    assert info.value.problem == "missing" and info.value.source == seq.frames[0].rgb_path
    cv2.imwrite(str(seq.frames[1].depth_path), np.zeros((H, W + 2), np.uint16))
    with pytest.raises(RgbdImageError) as info:
        load_rgbd(seq.frames[1].rgb_path, seq.frames[1].depth_path)
    assert info.value.problem == "size_mismatch"


def test_a_frame_id_is_its_timestamp_with_six_decimals(tmp_path: Path) -> None:
    seq = read_tum_rgbd(_write_frames(tmp_path / "seq", [_depth()], start=1305031102.175304))
    assert frame_id_of(seq.frames[0]) == "1305031102.175304"


# --- model and threshold settings ---------------------------------------------------------


def _shipped(root: Path, metrics: object | None) -> Path:
    """A models folder laid out like the repository's, with the detector and its metrics."""
    folder = root / "detector"
    folder.mkdir(parents=True)
    constant_v8_model(folder / "office_detector.onnx", [(CUP, 0.9, 10, 10, 50, 50)])
    if metrics is not None:
        (folder / "metrics.json").write_text(json.dumps(metrics))
    return root


def test_the_project_model_is_the_shipped_one_with_its_recommended_threshold(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv(MODELS_ENV, str(_shipped(tmp_path / "models", {"recommended_conf_threshold": 0.31})))
    assert model_path() == tmp_path / "models" / "detector" / "office_detector.onnx"
    assert conf_threshold_for() == 0.31
    assert load_detector(n_classes=80).settings.conf_threshold == 0.31
    assert conf_threshold_for("", 0.05) == 0.05  # a set threshold wins


@pytest.mark.parametrize("metrics", [None, {"test_map50": 0.8}, {"recommended_conf_threshold": "high"}, [1]])
def test_without_a_usable_recommendation_the_threshold_is_the_default(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, metrics: object
) -> None:
    monkeypatch.setenv(MODELS_ENV, str(_shipped(tmp_path / "models", metrics)))
    assert conf_threshold_for() == DEFAULT_CONF_THRESHOLD


def test_a_users_model_gets_the_default_threshold_not_the_shipped_recommendation(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, two_box_model: Path
) -> None:
    monkeypatch.setenv(MODELS_ENV, str(_shipped(tmp_path / "models", {"recommended_conf_threshold": 0.31})))
    assert model_path(str(two_box_model)) == two_box_model
    assert conf_threshold_for(str(two_box_model)) == DEFAULT_CONF_THRESHOLD


def test_a_missing_model_file_is_a_model_error_naming_it(tmp_path: Path) -> None:
    with pytest.raises(ModelError, match=r"nothing\.onnx: no such model file"):
        load_detector(str(tmp_path / "nothing.onnx"), n_classes=80)


def test_a_model_with_another_number_of_classes_than_the_label_list_is_refused(two_box_model: Path) -> None:
    with pytest.raises(ModelError, match="19 classes"):
        load_detector(two_box_model, n_classes=19)


def test_detector_settings_are_validated_together() -> None:
    with pytest.raises(ConfigError, match="detector_mode"):
        DetectorSettings(detector_mode="yolo")  # type: ignore[arg-type]
    with pytest.raises(ConfigError) as info:
        RgbdSettings(
            conf_threshold=1.5,
            iou_threshold=0.0,
            detector_threads=-1,
            camera_fx=0.0,
            camera_cy=float("nan"),
            depth_scale=-1.0,
            rgbd_max_dt=0.0,
        )
    text = str(info.value)
    for name in (
        "conf_threshold",
        "iou_threshold",
        "detector_threads",
        "camera_fx",
        "camera_cx, camera_cy",
        "depth_scale",
        "rgbd_max_dt",
    ):
        assert name in text, name


def test_the_camera_of_the_settings_defaults_to_tum_freiburg3() -> None:
    assert RgbdSettings().camera() == CameraIntrinsics()
    s = RgbdSettings(camera_fx=500.0, camera_fy=501.0, camera_cx=300.0, camera_cy=200.0, depth_scale=1e3)
    assert s.camera() == CameraIntrinsics(500.0, 501.0, 300.0, 200.0, 1000.0)


# --- the main job's side ----------------------------------------------------------------------


def pixels_run(out: Path, frames: int | None = None, **pixels: object) -> PlacesSettings:
    return PlacesSettings(source=DatasetSource(frames=frames), out=out, pixels=PixelSettings(**pixels))  # type: ignore[arg-type]


def test_a_run_from_pixels_needs_one_source() -> None:
    with pytest.raises(ConfigError, match="pick one"):
        PixelSettings(from_pixels=True, rgbd=Path("x"))
    with pytest.raises(ConfigError, match="--rgbd DIR"):
        PlacesSettings(source=DatasetSource("some/folder"), pixels=PixelSettings(from_pixels=True))
    with pytest.raises(ConfigError, match="replaces --dataset"):
        PlacesSettings(source=DatasetSource("some/folder"), pixels=PixelSettings(rgbd=Path("x")))
    with pytest.raises(ConfigError, match="conf_threshold"):
        PixelSettings(rgbd=Path("x"), conf_threshold=-0.1)
    assert PixelSettings(rgbd=Path("x")).enabled and PixelSettings(from_pixels=True).enabled
    assert not PixelSettings().enabled


def test_a_recording_is_prepared_with_its_camera_ground_truth_and_first_frames(
    tmp_path: Path, two_box_model: Path
) -> None:
    folder = _write_frames(tmp_path / "rec", [_depth()] * 6)
    stamps = [1.0 + k / 30 for k in range(6)]
    (folder / "groundtruth.txt").write_text("".join(f"{t:.6f} 0 0 {t} 0 0 0 1\n" for t in stamps))
    camera = {"fx": 500.0, "fy": 501.0, "cx": 300.0, "cy": 200.0, "depth_scale": 1000.0}
    (folder / "boxes.json").write_text(json.dumps({"camera": camera}))
    settings = pixels_run(tmp_path / "run", frames=4, rgbd=folder, model=str(two_box_model))

    src = prepare_pixels(settings)

    assert len(src) == 4 and src.frame_ids[0] == "1.000000"
    assert src.camera == CameraIntrinsics(500.0, 501.0, 300.0, 200.0, 1000.0)
    assert src.model == two_box_model.resolve() and src.conf_threshold == DEFAULT_CONF_THRESHOLD
    assert src.trajectory is not None and len(src.trajectory) == 6
    # The detectors read a folder listing the first 4 frames only, paired as in the recording.
    subset = read_tum_rgbd(src.folder)
    assert src.folder == tmp_path / "run" / "rgbd-subset"
    assert [f.rgb_path for f in subset] == [f.rgb_path for f in src.frames]
    assert [frame_id_of(f) for f in subset] == list(src.frame_ids)
    # An explicit camera wins over the folder's.
    explicit = pixels_run(tmp_path, rgbd=folder, model=str(two_box_model), camera=(1.0, 2.0, 3.0, 4.0))
    assert prepare_pixels(explicit).camera == CameraIntrinsics(1.0, 2.0, 3.0, 4.0, CAM.depth_scale)


def test_a_model_that_does_not_load_stops_the_run_before_anything_is_rendered(tmp_path: Path) -> None:
    (tmp_path / "broken.onnx").write_bytes(b"not a model")
    broken = pixels_run(tmp_path / "run", frames=3, from_pixels=True, model=str(tmp_path / "broken.onnx"))
    with pytest.raises(ModelError, match="cannot load it"):
        prepare_pixels(broken)
    assert not (tmp_path / "run" / "rgbd").exists()
    # The same run with a model that loads renders there: the check above is about something.
    good = pixels_run(
        tmp_path / "run",
        frames=3,
        from_pixels=True,
        model=str(constant_v8_model(tmp_path / "good.onnx", [(CUP, 0.9, 10, 10, 50, 50)])),
    )
    assert (
        prepare_pixels(good).folder == tmp_path / "run" / "rgbd"
        and len(read_tum_rgbd(tmp_path / "run" / "rgbd")) == 3
    )


def test_the_detected_sequence_is_read_back_in_frame_order_with_skipped_frames_empty(
    tmp_path: Path, two_box_model: Path
) -> None:
    folder = _write_frames(tmp_path / "rec", [_depth()] * 5)
    src = prepare_pixels(pixels_run(tmp_path / "run", rgbd=folder, model=str(two_box_model)))
    blocks = [range(0, 3), range(3, 5)]
    data = tmp_path / "data"
    from tests.conftest import make

    made = {
        0: make(("cup", 0.1, 0.2, 1.0)),
        1: make(),
        3: make(("laptop", 1.0, 0.0, 2.0), ("book", -1.0, 0.5, 3.0)),
        4: make(("cup", 0.0, 0.0, 1.5)),
    }
    for g, c in made.items():  # frame 2 was skipped by robot 0's detector
        robot = 0 if g < 3 else 1
        out = data / f"robot{robot}" / "detector" / "constellations"
        out.mkdir(parents=True, exist_ok=True)
        (out / f"{src.frame_ids[g]}.txt").write_text(format_constellation(c, COCO_NAMES))

    seq, missing = detected_sequence(src, data, blocks)

    assert missing == [2]
    assert [len(c) for c in seq.constellations] == [1, 0, 0, 2, 1]
    assert seq.constellations[3].labels.tolist() == [LAPTOP, BOOK]
    assert seq.frame_ids == src.frame_ids
    assert seq.timestamps.tolist() == [f.timestamp for f in src.frames]
