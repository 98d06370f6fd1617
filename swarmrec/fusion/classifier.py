"""The robots' landmark classifier: camera view -> probabilities over the 19 landmarks.

Each robot of the WNBC paper runs a shallow CNN on its view and broadcasts the class
probabilities, which :mod:`swarmrec.fusion.wnbc` fuses. The CNN is trained apart, in
its own environment with torch (``models/landmarks/train.py``), and ships as ONNX, so
a robot runs it on onnxruntime's CPU provider and needs no torch. The model takes
float32 ``[N, 3, 64, 64]`` RGB in 0..1 (its normalisation is inside the graph) and
gives a softmax ``[N, 19]``; both are checked when the model loads, so a wrong file
fails at start-up rather than on the first view.

Errors, in the project's hierarchy (:mod:`swarmrec.errors`)::

    SwarmrecError
    └── ClassifierError          images the classifier cannot take (shape, dtype)
        └── ClassifierModelError the ONNX file is missing, does not load or is not a 19-way classifier
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from swarmrec.errors import ConfigError, SwarmrecError
from swarmrec.fusion.wnbc import N_LANDMARKS
from swarmrec.inference import image_input_size, onnx_session, static_dim
from swarmrec.models import LANDMARK_MODEL, ModelNotFound, shipped_model

__all__ = ["ClassifierError", "ClassifierModelError", "LandmarkClassifier", "default_model_path"]

ImageArray = npt.NDArray[np.uint8]
FloatArray = npt.NDArray[np.float64]

#: How far a model's probabilities may sum from 1 (float32 softmax) before it is not taken for a softmax.
_SUM_TOLERANCE = 1e-3


class ClassifierError(SwarmrecError, ValueError):
    """The classifier cannot take these images (wrong shape or dtype)."""


@dataclass(eq=False)
class ClassifierModelError(ClassifierError):
    """The model file is missing, does not load, or its input/output is not a landmark classifier's."""

    model: str
    reason: str

    def __str__(self) -> str:
        return f"{self.model}: {self.reason}"


def default_model_path() -> Path:
    """The shipped landmark model (:data:`swarmrec.models.LANDMARK_MODEL`): from ``$SWARMREC_MODELS``
    (set in the container image) or the source checkout's ``models/``; ``ModelNotFound`` otherwise."""
    try:
        return shipped_model(LANDMARK_MODEL)
    except ModelNotFound as e:
        raise ClassifierModelError(str(e.model), str(e)) from None


class LandmarkClassifier:
    """An ONNX landmark classifier on onnxruntime's CPU provider.

    ``intra_op_threads`` is 1 by default because the classifier shares the robot's cores
    with its other services (0: onnxruntime decides).
    """

    def __init__(
        self, model: str | Path | None = None, *, intra_op_threads: int = 1, n_classes: int = N_LANDMARKS
    ) -> None:
        if intra_op_threads < 0:
            raise ConfigError(f"intra_op_threads must be 0 (automatic) or more, got {intra_op_threads}")
        if n_classes < 2:
            raise ConfigError(f"n_classes must be at least 2, got {n_classes}")
        path = default_model_path() if model is None else Path(model)
        self.model = str(path)
        self.n_classes = n_classes
        self._session = onnx_session(path, ClassifierModelError, intra_op_threads=intra_op_threads)
        image, probabilities, height, width = image_input_size(
            self._session, self.model, ClassifierModelError
        )
        out_shape = [static_dim(d) for d in probabilities.shape]
        if len(out_shape) != 2 or out_shape[1] != n_classes:
            raise ClassifierModelError(
                self.model, f"expected an output [N, {n_classes}], got {probabilities.shape}"
            )
        self._input_name, self._output_name = image.name, probabilities.name
        #: The (height, width) the model takes: views must be rendered or resized to it.
        self.image_size = (height, width)
        # A model exported without its softmax still has the right shapes; one probe shows it.
        self._run(np.full((1, *self.image_size, 3), 128, np.uint8))

    def classify(self, images: ImageArray) -> FloatArray:
        """Class probabilities ``[N, n_classes]`` (float64, each row summing to 1) of RGB
        ``uint8`` views ``[N, H, W, 3]``, or of one view ``[H, W, 3]`` (then N = 1), at the
        model's size (64 x 64 for the committed model)."""
        if not isinstance(images, np.ndarray) or images.dtype != np.uint8:
            kind = images.dtype if isinstance(images, np.ndarray) else type(images).__name__
            raise ClassifierError(f"expected RGB uint8 images, got {kind}")
        batch = images[None] if images.ndim == 3 else images
        h, w = self.image_size
        if batch.ndim != 4 or batch.shape[1:] != (h, w, 3):
            raise ClassifierError(
                f"expected RGB images [N, {h}, {w}, 3] or one [{h}, {w}, 3], got {images.shape}"
            )
        if len(batch) == 0:
            return np.zeros((0, self.n_classes), np.float64)
        return self._run(batch)

    def _run(self, batch: ImageArray) -> FloatArray:
        feed = np.ascontiguousarray(batch.transpose(0, 3, 1, 2), np.float32) / np.float32(255.0)
        try:
            raw = self._session.run([self._output_name], {self._input_name: feed})[0]
        # As at load: onnxruntime's run-time errors have no common base.
        except Exception as exc:
            raise ClassifierModelError(self.model, f"inference failed: {exc}") from exc
        probabilities = np.asarray(raw, np.float64)
        if probabilities.shape != (len(batch), self.n_classes):
            raise ClassifierModelError(
                self.model, f"output of shape {probabilities.shape} for {len(batch)} images"
            )
        sums = probabilities.sum(axis=1)
        valid = np.isfinite(probabilities).all() and (probabilities >= 0).all()
        if not valid or np.any(np.abs(sums - 1.0) > _SUM_TOLERANCE):
            raise ClassifierModelError(self.model, "its output is not a softmax (rows >= 0 summing to 1)")
        # float32 softmax rows sum to 1 within ~1e-7; renormalised in float64 they sum to 1 to
        # rounding, which the fusion's running products need.
        result: FloatArray = probabilities / sums[:, None]
        return result
