"""What the three training scripts share (``models/<name>/train.py``: landmarks, detector,
descriptor): images to the model's input, running a model in torch and in onnxruntime, the
ONNX export and its check against torch, the versions and the file a run writes, the
scripts' ``__main__``.

``models/`` is no package (each script runs as ``python models/<name>/train.py``), so a
script puts this folder on ``sys.path`` and imports this module by name. It needs the
training environment (``.venv-train``: torch, onnx, onnxruntime), never the services'.
"""

from __future__ import annotations

import json
import logging
import platform
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import numpy.typing as npt
import onnx
import onnxruntime as ort  # type: ignore[import-untyped]  # onnxruntime ships no type hints
import torch
from torch import nn

from swarmrec.errors import ConfigError

__all__ = [
    "OPSET",
    "check_export",
    "export_onnx",
    "log",
    "onnx_session",
    "run_onnx",
    "run_script",
    "run_torch",
    "to_input",
    "versions",
    "write_json",
]

ImageArray = npt.NDArray[np.uint8]
FloatArray = npt.NDArray[np.float64]
S = TypeVar("S")

#: The torch.export-based exporter's lowest opset, which every model of the repository uses.
OPSET = 18


def log(message: str) -> None:
    """One line of progress on stdout, at once (the runs take minutes to hours)."""
    print(message, flush=True)


def to_input(images: ImageArray) -> torch.Tensor:
    """uint8 ``(N, H, W, 3)`` RGB -> the model's float32 ``(N, 3, H, W)`` in 0..1."""
    return torch.from_numpy(images).permute(0, 3, 1, 2).float().div(255.0).contiguous()


def run_torch(
    model: nn.Module, images: ImageArray, batch_size: int = 256, *, as_float64: bool = True
) -> npt.NDArray[Any]:
    """torch's outputs for uint8 images, in eval mode, in batches (float64, or the model's float32)."""
    model.eval()
    with torch.no_grad():
        chunks = [model(to_input(images[i : i + batch_size])) for i in range(0, len(images), batch_size)]
    out = torch.cat(chunks)
    return out.double().numpy() if as_float64 else out.numpy()


def run_onnx(
    session: ort.InferenceSession,
    images: ImageArray,
    input_name: str,
    output_name: str,
    batch_size: int = 256,
) -> FloatArray:
    """onnxruntime's outputs (float64) for uint8 images, in batches."""
    chunks = [
        session.run([output_name], {input_name: to_input(images[i : i + batch_size]).numpy()})[0]
        for i in range(0, len(images), batch_size)
    ]
    return np.concatenate(chunks).astype(np.float64)


def onnx_session(path: Path, threads: int) -> ort.InferenceSession:
    """The exported file on onnxruntime's CPU provider, with ``threads`` intra-op threads."""
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    return ort.InferenceSession(str(path), sess_options=options, providers=["CPUExecutionProvider"])


def export_onnx(
    model: nn.Module,
    path: Path,
    example: torch.Tensor,
    *,
    input_name: str,
    output_name: str,
    dynamic_batch: str | None = None,
) -> None:
    """One self-contained .onnx file (weights inside), checked by onnx. ``dynamic_batch`` names
    the forward argument whose first dimension is left free (a batch of any size); None: the
    example's shape is fixed."""
    model.eval()
    # The exporter warns that torchvision's detection ops cannot be registered; the models use none.
    logging.getLogger("torch.onnx._internal.exporter._registration").setLevel(logging.ERROR)
    extra: dict[str, Any] = {}
    if dynamic_batch is not None:
        extra["dynamic_shapes"] = {dynamic_batch: {0: torch.export.Dim("batch")}}
    torch.onnx.export(
        model,
        (example,),
        str(path),
        dynamo=True,
        opset_version=OPSET,
        external_data=False,
        input_names=[input_name],
        output_names=[output_name],
        **extra,
        verbose=False,
    )
    onnx.checker.check_model(onnx.load(str(path)))


def check_export(max_diff: float, tolerance: float) -> None:
    """Refuse an export whose outputs differ from torch's by ``tolerance`` or more (each script
    says how it measures the difference); called after the metrics are written, so the numbers
    of a failed run can still be read."""
    if not max_diff < tolerance:
        raise RuntimeError(f"ONNX export differs from torch by {max_diff:.2e} >= {tolerance}")


def versions(**extra: str) -> dict[str, str]:
    """The versions a metrics file records (``extra`` after the common ones)."""
    return {
        "python": platform.python_version(),
        "torch": torch.__version__,
        "onnx": onnx.__version__,
        "onnxruntime": ort.__version__,
        "numpy": np.__version__,
        **extra,
    }


def write_json(path: Path, data: dict[str, Any]) -> Path:
    """``data`` as indented JSON (one space, a final newline), as every metrics.json is."""
    path.write_text(json.dumps(data, indent=1) + "\n")
    return path


def run_script(main: Callable[[S], object], parse_args: Callable[[], S]) -> None:
    """A script's ``__main__``: run ``main`` on the parsed flags; a bad setting is one line and exit 1."""
    try:
        main(parse_args())
    except ConfigError as exc:
        sys.exit(f"error: {exc}")
