"""Tiny YOLO-style ONNX models for the detector's tests, built here with onnx.

They are real models that onnxruntime runs; their output does not depend on
the image, so each test knows every box it will get: a box drawn where the
test put an object in the depth image, or at a place of a rendered frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

#: A box of a constant model: class id, score, and ``x1 y1 x2 y2`` in model input pixels.
Box = tuple[int, float, float, float, float, float]


def constant_v8_model(
    path: Path, boxes: Sequence[Box], n_classes: int = 80, input_hw: tuple[int, int] = (640, 640)
) -> Path:
    """A v8-layout model (``[1, 4 + C, N]``) that outputs ``boxes`` for every image."""
    out = np.zeros((1, 4 + n_classes, max(len(boxes), 1)), np.float32)
    for i, (class_id, score, x1, y1, x2, y2) in enumerate(boxes):
        out[0, :4, i] = ((x1 + x2) / 2, (y1 + y2) / 2, x2 - x1, y2 - y1)
        out[0, 4 + class_id, i] = score
    node = helper.make_node("Constant", [], ["output"], value=numpy_helper.from_array(out))
    image = helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, *input_hw])
    result = helper.make_tensor_value_info("output", TensorProto.FLOAT, list(out.shape))
    model = helper.make_model(
        helper.make_graph([node], "constant", [image], [result]), opset_imports=[helper.make_opsetid("", 17)]
    )
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, path)
    return path


#: Five boxes spread over a 640x480 frame letterboxed into 640x640 (80 px of padding above):
#: a chair, a cup, a laptop, a book and a keyboard, as a detector might find on the desks.
OFFICE_BOXES: tuple[Box, ...] = (
    (56, 0.9, 40.0, 300.0, 200.0, 500.0),
    (41, 0.8, 300.0, 250.0, 340.0, 300.0),
    (63, 0.7, 400.0, 150.0, 560.0, 280.0),
    (73, 0.6, 100.0, 120.0, 180.0, 200.0),
    (66, 0.5, 250.0, 400.0, 450.0, 470.0),
)
