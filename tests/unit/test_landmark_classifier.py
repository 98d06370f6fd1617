"""The landmark classifier: the committed ONNX model on fresh renders, and the errors for
wrong models and wrong images (on tiny ONNX graphs built here)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from swarmrec.errors import ConfigError, SwarmrecError
from swarmrec.fusion.classifier import (
    ClassifierError,
    ClassifierModelError,
    LandmarkClassifier,
    default_model_path,
)
from swarmrec.fusion.facades import render_dataset

REPO = Path(__file__).resolve().parents[2]
MODEL_DIR = REPO / "models" / "landmarks"
#: Not among the training, validation and test seeds (models/landmarks/metrics.json).
FRESH_SEED = 20_260_917


@pytest.fixture(scope="module")
def classifier() -> LandmarkClassifier:
    return LandmarkClassifier()


@pytest.fixture(scope="module")
def fresh_views() -> tuple[np.ndarray, np.ndarray]:
    images, labels, _ = render_dataset(10, seed=FRESH_SEED)
    return images, labels


def _toy_model(
    path: Path,
    *,
    n_out: int = 19,
    softmax: bool = True,
    input_dims: tuple[int | str, ...] = ("N", 3, 64, 64),
    elem_type: int = TensorProto.FLOAT,
) -> Path:
    """image -> mean colour per channel -> linear map to ``n_out`` scores (-> softmax)."""
    channels, dtype = int(input_dims[1]), helper.tensor_dtype_to_np_dtype(elem_type)
    weights = np.linspace(-1, 1, channels * n_out, dtype=dtype).reshape(channels, n_out)
    nodes = [
        helper.make_node("ReduceMean", ["image", "axes"], ["colour"], keepdims=0),
        helper.make_node("MatMul", ["colour", "w"], ["scores" if softmax else "probabilities"]),
    ]
    if softmax:
        nodes.append(helper.make_node("Softmax", ["scores"], ["probabilities"], axis=1))
    axes = numpy_helper.from_array(np.array([2, 3], np.int64), "axes")
    graph = helper.make_graph(
        nodes,
        "toy",
        [helper.make_tensor_value_info("image", elem_type, list(input_dims))],
        [helper.make_tensor_value_info("probabilities", elem_type, ["N", n_out])],
        initializer=[numpy_helper.from_array(weights, "w"), axes],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, path)
    return path


def test_the_committed_model_is_found_and_small() -> None:
    path = default_model_path()
    assert path == MODEL_DIR / "landmark_cnn.onnx"
    assert path.stat().st_size < 2_000_000


def test_the_committed_model_gives_a_probability_vector_over_19_landmarks_per_view(
    classifier: LandmarkClassifier, fresh_views: tuple[np.ndarray, np.ndarray]
) -> None:
    images, _ = fresh_views
    probabilities = classifier.classify(images[:7])
    assert probabilities.shape == (7, 19) and probabilities.dtype == np.float64
    assert (probabilities >= 0).all()
    np.testing.assert_allclose(probabilities.sum(axis=1), 1.0, atol=1e-12)
    one = classifier.classify(images[3])
    assert one.shape == (1, 19)
    np.testing.assert_allclose(one[0], probabilities[3], atol=1e-6)


def test_the_committed_model_recognises_fresh_views_far_above_chance(
    classifier: LandmarkClassifier, fresh_views: tuple[np.ndarray, np.ndarray]
) -> None:
    seeds = json.loads((MODEL_DIR / "metrics.json").read_text())["settings"]["data_seeds"]
    assert FRESH_SEED not in seeds
    images, labels = fresh_views
    accuracy = float((classifier.classify(images).argmax(axis=1) == labels).mean())
    # Chance is 1/19 (5 %); the held-out test set gives about 85 % (metrics.json), so
    # 190 fresh views land well above 60 % unless the model or its input convention broke.
    assert accuracy > 0.6, accuracy


def test_an_empty_batch_gives_no_rows(classifier: LandmarkClassifier) -> None:
    assert classifier.classify(np.zeros((0, 64, 64, 3), np.uint8)).shape == (0, 19)


@pytest.mark.parametrize(
    ("images", "message"),
    [
        (np.zeros((2, 64, 64, 3), np.float32), "uint8"),
        ([[0, 1, 2]], "uint8"),
        (np.zeros((2, 32, 32, 3), np.uint8), r"\[N, 64, 64, 3\]"),
        (np.zeros((2, 3, 64, 64), np.uint8), r"got \(2, 3, 64, 64\)"),
        (np.zeros((64, 64), np.uint8), r"got \(64, 64\)"),
        (np.zeros((1, 1, 64, 64, 3), np.uint8), "got"),
    ],
)
def test_wrong_images_are_refused_with_the_expected_form(
    classifier: LandmarkClassifier, images: object, message: str
) -> None:
    with pytest.raises(ClassifierError, match=message) as info:
        classifier.classify(images)  # type: ignore[arg-type]  # deliberately wrong types
    assert isinstance(info.value, SwarmrecError) and isinstance(info.value, ValueError)


def test_a_missing_or_broken_model_file_fails_at_load(tmp_path: Path) -> None:
    with pytest.raises(ClassifierModelError, match="no such model file"):
        LandmarkClassifier(tmp_path / "absent.onnx")
    garbage = tmp_path / "garbage.onnx"
    garbage.write_bytes(b"not a model")
    with pytest.raises(ClassifierModelError, match=r"garbage\.onnx: onnxruntime cannot load it"):
        LandmarkClassifier(garbage)


def test_a_model_of_the_right_form_loads_and_its_image_size_is_used(tmp_path: Path) -> None:
    model = LandmarkClassifier(_toy_model(tmp_path / "toy.onnx", input_dims=("N", 3, 32, 48)))
    assert model.image_size == (32, 48)
    assert model.classify(np.zeros((3, 32, 48, 3), np.uint8)).shape == (3, 19)
    with pytest.raises(ClassifierError, match=r"\[N, 32, 48, 3\]"):
        model.classify(np.zeros((3, 64, 64, 3), np.uint8))


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"n_out": 10}, r"expected an output \[N, 19\]"),
        ({"softmax": False}, "not a softmax"),
        ({"input_dims": ("N", 3, "h", "w")}, "fixed size"),
        ({"input_dims": ("N", 1, 64, 64)}, r"\[N, 3, H, W\]"),
        ({"input_dims": (1, 3, 64, 64)}, "batch dimension must be dynamic"),
        ({"elem_type": TensorProto.DOUBLE}, "float32"),
    ],
)
def test_a_model_that_is_not_a_19_way_classifier_fails_at_load(
    tmp_path: Path, kwargs: dict[str, object], message: str
) -> None:
    path = _toy_model(tmp_path / "wrong.onnx", **kwargs)  # type: ignore[arg-type]  # parametrised
    with pytest.raises(ClassifierModelError, match=message):
        LandmarkClassifier(path)


def test_negative_threads_or_fewer_than_two_classes_are_config_errors() -> None:
    with pytest.raises(ConfigError, match="intra_op_threads"):
        LandmarkClassifier(intra_op_threads=-1)
    with pytest.raises(ConfigError, match="n_classes"):
        LandmarkClassifier(n_classes=1)


# --- the classify endpoint's view: its size is read before it is decoded ----------------


def _png_header(width: int, height: int) -> bytes:
    """A PNG whose IHDR claims ``width x height`` RGB pixels, with a tiny zlib stream."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(b"\0" * 64))
        + chunk(b"IEND", b"")
    )


@pytest.mark.parametrize(("ext", "progressive"), [(".png", False), (".jpg", False), (".jpg", True)])
def test_a_views_size_is_read_from_its_png_or_jpeg_header(ext: str, progressive: bool) -> None:
    import cv2

    from swarmrec.services.detector.classifier import decode_view, view_size

    image = np.random.default_rng(0).integers(0, 255, (37, 53, 3), np.uint8)
    ok, data = cv2.imencode(ext, image, [cv2.IMWRITE_JPEG_PROGRESSIVE, 1] if progressive else [])
    assert ok
    assert view_size(data.tobytes()) == (53, 37)
    assert decode_view(data.tobytes(), max_pixels=53 * 37).shape == (37, 53, 3)


def test_a_view_claiming_more_pixels_than_allowed_is_refused_before_it_is_decoded() -> None:
    from swarmrec.errors import ErrorCode, LimitExceededError
    from swarmrec.services.detector.classifier import decode_view

    bomb = _png_header(30_000, 30_000)  # 2.7 GB decoded, from 100 bytes
    assert len(bomb) < 200
    with pytest.raises(
        LimitExceededError, match=r"30000 x 30000\): 900000000, more than the limit of 4194304"
    ) as e:
        decode_view(bomb, max_pixels=1 << 22)
    assert e.value.code == ErrorCode.TOO_LARGE


@pytest.mark.parametrize(
    ("data", "match"),
    [
        (b"GIF89a....", "as a PNG or a JPEG"),
        (b"\x89PNG\r\n\x1a\n\0\0", "without its IHDR"),
        (b"\xff\xd8\xff", "JPEG without"),
    ],
)
def test_a_view_that_is_not_a_png_or_a_jpeg_is_refused(data: bytes, match: str) -> None:
    from swarmrec.services.detector.classifier import decode_view

    with pytest.raises(ValueError, match=match):
        decode_view(data, max_pixels=1 << 22)
