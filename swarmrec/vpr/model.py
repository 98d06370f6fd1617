"""The place descriptor model: a camera frame -> one unit 128-d vector, on onnxruntime.

The model is trained apart, with torch (``models/descriptor/train.py``), and ships as ONNX,
so a robot runs it on onnxruntime's CPU provider and needs no torch. It takes float32
``[N, 3, H, W]`` RGB in 0..1 (96 x 128 for the shipped model; its normalisation is inside
the graph) and gives ``[N, d]`` unit rows. Everything the rest of the package relies on is
checked when the model loads: one input of that form with a free batch dimension, one
output ``[N, d]``, and unit, finite, image-dependent rows on two probe images, so a
detector or classifier file given by mistake fails at start-up with the reason.

``describe_frames`` takes camera frames of any size (BGR, as OpenCV and the renderer give
them) and area-averages them to the model's input, as the training did.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt

from swarmrec.errors import ConfigError
from swarmrec.inference import image_input_size, onnx_session, static_dim
from swarmrec.models import DESCRIPTOR_MODEL, ModelNotFound, shipped_model
from swarmrec.vpr.errors import DescriptorError, DescriptorModelError

__all__ = ["DescriptorModel", "default_model_path"]

ImageArray = npt.NDArray[np.uint8]
Float32Array = npt.NDArray[np.float32]

#: Images per onnxruntime call.
_CHUNK = 256
#: How far a row's norm may be from 1 (float32 normalisation) before the model is not taken
#: for a unit-descriptor model.
NORM_TOLERANCE = 1e-3


def default_model_path() -> Path:
    """The shipped descriptor (:data:`swarmrec.models.DESCRIPTOR_MODEL`), or DescriptorModelError."""
    try:
        return shipped_model(DESCRIPTOR_MODEL)
    except ModelNotFound as e:
        raise DescriptorModelError(str(e.model), str(e)) from None


class DescriptorModel:
    """An ONNX full-image descriptor on onnxruntime's CPU provider.

    ``dimension``: the descriptor length the caller expects (128 for the shipped model).
    ``intra_op_threads`` is 1 by default: the model shares a robot's cores with its other
    services (0: onnxruntime decides). onnxruntime sessions may be run from several threads
    at once, so one instance can serve a thread pool.
    """

    def __init__(
        self, model: str | Path | None = None, *, dimension: int = 128, intra_op_threads: int = 1
    ) -> None:
        if intra_op_threads < 0:
            raise ConfigError(f"intra_op_threads must be 0 (automatic) or more, got {intra_op_threads}")
        if dimension < 2:
            raise ConfigError(f"dimension must be at least 2, got {dimension}")
        path = default_model_path() if model is None else Path(model)
        self.model = str(path)
        self.dimension = dimension
        self._session = onnx_session(path, DescriptorModelError, intra_op_threads=intra_op_threads)
        image, descriptor, height, width = image_input_size(self._session, self.model, DescriptorModelError)
        out_shape = [static_dim(d) for d in descriptor.shape]
        if descriptor.type != "tensor(float)" or len(out_shape) != 2 or out_shape[1] != dimension:
            raise DescriptorModelError(
                self.model,
                f"expected a float32 output [N, {dimension}], got {descriptor.type} {descriptor.shape}",
            )
        self._input_name, self._output_name = image.name, descriptor.name
        #: The (height, width) the model takes.
        self.image_hw = (height, width)
        # A classifier's softmax or an un-normalised embedding has the right shapes; probing shows
        # it. Two different images: a model that ignores its input cannot recognise places.
        # Probes of different mean colour too, so even a model of the mean colour tells them apart.
        rows = np.linspace(0, 255, height, dtype=np.float64)[:, None] * np.ones((1, width))
        cols = np.linspace(0, 255, width, dtype=np.float64)[None, :] * np.ones((height, 1))
        pattern = np.stack([rows, cols, np.full((height, width), 200.0)], axis=2).astype(np.uint8)
        probe = self._run(np.stack([np.full((height, width, 3), 64, np.uint8), pattern]))
        if np.allclose(probe[0], probe[1], atol=1e-6):
            raise DescriptorModelError(self.model, "it gives the same descriptor for two different images")

    def describe(self, images: ImageArray) -> Float32Array:
        """Unit descriptors ``[N, d]`` (float32) of RGB ``uint8`` images ``[N, H, W, 3]`` at the
        model's size, or of one image ``[H, W, 3]`` (then N = 1)."""
        if not isinstance(images, np.ndarray) or images.dtype != np.uint8:
            kind = images.dtype if isinstance(images, np.ndarray) else type(images).__name__
            raise DescriptorError(f"expected RGB uint8 images, got {kind}")
        batch = images[None] if images.ndim == 3 else images
        h, w = self.image_hw
        if batch.ndim != 4 or batch.shape[1:] != (h, w, 3):
            raise DescriptorError(
                f"expected RGB images [N, {h}, {w}, 3] or one [{h}, {w}, 3], got {images.shape}"
            )
        if len(batch) == 0:
            return np.zeros((0, self.dimension), np.float32)
        # Bounded chunks: a whole sequence at once would hold every activation in memory.
        return np.concatenate([self._run(batch[i : i + _CHUNK]) for i in range(0, len(batch), _CHUNK)])

    def describe_frames(self, frames: ImageArray) -> Float32Array:
        """Descriptors of BGR camera frames ``[N, H, W, 3]`` (or one) of any size: each is
        area-averaged to the model's input and turned to RGB, as in training."""
        if not isinstance(frames, np.ndarray) or frames.dtype != np.uint8 or frames.ndim not in (3, 4):
            raise DescriptorError("expected BGR uint8 frames [N, H, W, 3] or one [H, W, 3]")
        batch = frames[None] if frames.ndim == 3 else frames
        if batch.shape[-1] != 3:
            raise DescriptorError(f"expected 3 colour channels, got shape {frames.shape}")
        h, w = self.image_hw
        resized = [cv2.resize(f, (w, h), interpolation=cv2.INTER_AREA)[:, :, ::-1] for f in batch]
        return self.describe(
            np.ascontiguousarray(np.stack(resized)) if resized else np.zeros((0, h, w, 3), np.uint8)
        )

    def _run(self, batch: ImageArray) -> Float32Array:
        feed = np.ascontiguousarray(batch.transpose(0, 3, 1, 2), np.float32) / np.float32(255.0)
        try:
            raw = self._session.run([self._output_name], {self._input_name: feed})[0]
        # As at load: onnxruntime's run-time errors have no common base.
        except Exception as exc:
            raise DescriptorModelError(self.model, f"inference failed: {exc}") from exc
        out = np.asarray(raw, np.float32)
        if out.shape != (len(batch), self.dimension):
            raise DescriptorModelError(self.model, f"output of shape {out.shape} for {len(batch)} images")
        if not np.isfinite(out).all():
            raise DescriptorModelError(self.model, "its output holds NaN or inf")
        norms = np.linalg.norm(out.astype(np.float64), axis=1)
        if np.any(np.abs(norms - 1.0) > NORM_TOLERANCE):
            raise DescriptorModelError(
                self.model,
                f"its output rows are not L2-normalised (norms {norms.min():.4g}..{norms.max():.4g})",
            )
        return out
