"""The one ONNX loader the three models share (swarmrec.inference): every failure is the
caller's own error naming the file, and the image models' input is checked alike."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pytest

from swarmrec.inference import image_input_size, onnx_session, static_dim
from swarmrec.models import DESCRIPTOR_MODEL, DETECTOR_MODEL, LANDMARK_MODEL, shipped_model


@dataclass
class Refused(Exception):
    model: str
    reason: str


def test_a_missing_file_is_the_callers_error_naming_it(tmp_path: Path) -> None:
    with pytest.raises(Refused) as e:
        onnx_session(tmp_path / "none.onnx", Refused, intra_op_threads=1)
    assert e.value.model == str(tmp_path / "none.onnx") and e.value.reason == "no such model file"


def test_a_file_onnxruntime_cannot_load_says_so(tmp_path: Path) -> None:
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"not a model")
    with pytest.raises(Refused) as e:
        onnx_session(bad, Refused, intra_op_threads=1)
    assert e.value.reason.startswith("onnxruntime cannot load it: ")


def test_the_image_models_take_a_fixed_size_batch_of_any_length() -> None:
    for model, size in ((DESCRIPTOR_MODEL, None), (LANDMARK_MODEL, (64, 64))):
        path = shipped_model(model)
        session = onnx_session(path, Refused, intra_op_threads=1)
        image, _output, height, width = image_input_size(session, str(path), Refused)
        assert image.type == "tensor(float)" and height > 0 and width > 0
        if size is not None:
            assert (height, width) == size


def test_a_model_with_a_fixed_batch_is_refused_for_an_image_batch() -> None:
    # The detector's export takes one image ([1, 3, H, W]): not an image-batch model.
    path = shipped_model(DETECTOR_MODEL)
    session = onnx_session(path, Refused, intra_op_threads=1)
    shape = session.get_inputs()[0].shape
    with pytest.raises(Refused) as e:
        image_input_size(session, str(path), Refused)
    assert shape == [1, 3, 384, 512]
    assert e.value.reason == f"the batch dimension must be dynamic, got {shape}"


def test_static_dims() -> None:
    assert [static_dim(d) for d in (3, "N", None, 0, -1)] == [3, None, None, None, None]
