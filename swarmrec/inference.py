"""One way to open an ONNX model: onnxruntime's CPU provider, a bounded thread count,
and every way the file can fail said as the caller's own error.

The detector (:mod:`swarmrec.detection.yolo`), the place descriptor
(:mod:`swarmrec.vpr.model`) and the landmark classifier
(:mod:`swarmrec.fusion.classifier`) each check their model's inputs and outputs
their own way, but open it alike: a missing file, a file onnxruntime cannot load,
and (for the two image models that take any batch) an input that is not
``float32 [N, 3, H, W]`` of a fixed size are refused at start-up, naming the file,
never on the first frame.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import onnxruntime as ort  # type: ignore[import-untyped]  # onnxruntime ships no type hints

__all__ = ["ModelProblem", "image_input_size", "onnx_session", "static_dim"]

#: Builds the caller's error from the model's path and what is wrong with it.
ModelProblem = Callable[[str, str], Exception]


def static_dim(dim: object) -> int | None:
    """A dimension's size, or None when the model leaves it dynamic (a name or nothing)."""
    return dim if isinstance(dim, int) and dim > 0 else None


def onnx_session(
    model: str | Path, problem: ModelProblem, *, intra_op_threads: int, inter_op_threads: int | None = 1
) -> Any:
    """An onnxruntime session of ``model`` on the CPU provider. ``intra_op_threads``: threads
    for one run (0: onnxruntime decides); a robot gives 1, its cores are shared with its other
    services. A missing or unloadable file raises ``problem(path, why)``."""
    path = str(model)
    if not Path(model).is_file():
        raise problem(path, "no such model file")
    options = ort.SessionOptions()
    options.intra_op_num_threads = intra_op_threads
    if inter_op_threads is not None:
        options.inter_op_num_threads = inter_op_threads
    try:
        return ort.InferenceSession(path, sess_options=options, providers=["CPUExecutionProvider"])
    # onnxruntime's errors share no base class below Exception (Fail, InvalidProtobuf, ...).
    except Exception as exc:
        raise problem(path, f"onnxruntime cannot load it: {exc}") from exc


def image_input_size(session: Any, model: str, problem: ModelProblem) -> tuple[Any, Any, int, int]:
    """``(input, output, height, width)`` of a model taking one ``float32 [N, 3, H, W]`` image
    batch of a fixed size, with N left dynamic, and giving one output; ``problem`` otherwise."""
    inputs, outputs = session.get_inputs(), session.get_outputs()
    if len(inputs) != 1 or len(outputs) != 1:
        raise problem(model, f"expected one input and one output, got {len(inputs)} and {len(outputs)}")
    image = inputs[0]
    shape = [static_dim(d) for d in image.shape]
    height, width = (shape[2], shape[3]) if len(shape) == 4 else (None, None)
    if image.type != "tensor(float)" or len(shape) != 4 or shape[1] != 3 or not (height and width):
        raise problem(
            model, f"expected a float32 input [N, 3, H, W] of fixed size, got {image.type} {image.shape}"
        )
    if shape[0] is not None:
        # A robot runs one image, an evaluation thousands: the export must leave N free.
        raise problem(model, f"the batch dimension must be dynamic, got {image.shape}")
    assert height is not None and width is not None
    return image, outputs[0], height, width
