"""Run a YOLO-style ONNX detector on one image: letterbox -> model -> decode -> NMS.

Any exported YOLO model with one image input ``[1, 3, H, W]`` (RGB, 0..1)
and a first output in the v5 or v8 layout (:mod:`swarmrec.detection.decode`)
works; it runs on onnxruntime's CPU provider, so a robot needs no GPU stack.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt

from swarmrec.detection.decode import Layout, decode_output, detect_layout
from swarmrec.detection.errors import DetectionError, ModelError, OutputLayoutError
from swarmrec.detection.letterbox import letterbox
from swarmrec.detection.nms import non_max_suppression
from swarmrec.errors import ConfigError
from swarmrec.inference import onnx_session, static_dim

__all__ = ["Detection", "DetectorSettings", "OnnxDetector"]

ImageArray = npt.NDArray[np.uint8]

_INPUT_TYPES = {"tensor(float)": np.float32, "tensor(float16)": np.float16}


@dataclass(frozen=True)
class DetectorSettings:
    """How detections are made from the model's output.

    ``conf_threshold`` defaults to 0.0, as in the constellation paper: every
    box goes to NMS. ``input_hw`` is only used when the model's input size is
    dynamic; a static size in the model always wins, since the model was
    exported for it. ``intra_op_threads`` is 1 by default because the detector
    shares the robot's cores with the other services (0: onnxruntime decides).
    """

    n_classes: int = 80
    conf_threshold: float = 0.0
    iou_threshold: float = 0.45
    max_detections: int = 300
    layout: Layout | None = None
    input_hw: tuple[int, int] = (640, 640)
    intra_op_threads: int = 1

    def __post_init__(self) -> None:
        if self.n_classes < 1:
            raise ConfigError(f"n_classes must be at least 1, got {self.n_classes}")
        if not 0.0 <= self.conf_threshold <= 1.0:
            raise ConfigError(f"conf_threshold must be in [0, 1], got {self.conf_threshold}")
        if not 0.0 < self.iou_threshold <= 1.0:
            raise ConfigError(f"iou_threshold must be in (0, 1], got {self.iou_threshold}")
        if self.max_detections < 1:
            raise ConfigError(f"max_detections must be at least 1, got {self.max_detections}")
        if len(self.input_hw) != 2 or min(self.input_hw) < 1:
            raise ConfigError(f"input_hw must be two positive sizes (height, width), got {self.input_hw}")
        if self.intra_op_threads < 0:
            raise ConfigError(f"intra_op_threads must be 0 (automatic) or more, got {self.intra_op_threads}")


@dataclass(frozen=True)
class Detection:
    """One detected object: class index, confidence, box in original image pixels."""

    class_id: int
    score: float
    x1: float
    y1: float
    x2: float
    y2: float

    @property
    def box(self) -> tuple[float, float, float, float]:
        """``(x1, y1, x2, y2)``, the form :func:`swarmrec.detection.points.object_points` takes."""
        return (self.x1, self.y1, self.x2, self.y2)


class OnnxDetector:
    """A YOLO-style ONNX model, ready to detect objects in BGR images.

    Everything that can be checked without an image (one 4-D float input with
    3 channels; an output that fits one layout when its shape is static) is
    checked here, so a wrong model fails at start-up rather than on the first frame.
    """

    def __init__(self, model: str | Path, settings: DetectorSettings | None = None) -> None:
        self.settings = settings or DetectorSettings()
        self.model = str(model)
        # (onnxruntime's own choice of inter-op threads, as the detector has always had.)
        self._session = onnx_session(
            model, ModelError, intra_op_threads=self.settings.intra_op_threads, inter_op_threads=None
        )
        inputs = self._session.get_inputs()
        if len(inputs) != 1:
            raise ModelError(self.model, f"expected one image input, the model has {len(inputs)}")
        image_input = inputs[0]
        if image_input.type not in _INPUT_TYPES:
            raise ModelError(self.model, f"expected a float image input, got {image_input.type}")
        shape = list(image_input.shape)
        if len(shape) != 4:
            raise ModelError(self.model, f"expected an input [1, 3, H, W], got {shape}")
        batch, channels, height, width = (static_dim(d) for d in shape)
        if batch not in (None, 1) or channels not in (None, 3):
            raise ModelError(self.model, f"expected an input [1, 3, H, W], got {shape}")
        self._input_name = image_input.name
        self._input_dtype = _INPUT_TYPES[image_input.type]
        self.input_hw = (height or self.settings.input_hw[0], width or self.settings.input_hw[1])
        output = self._session.get_outputs()[0]
        self._output_name = output.name
        self.layout = self.settings.layout
        out_shape = [static_dim(d) for d in output.shape]
        if all(d is not None for d in out_shape):
            try:
                self.layout = detect_layout(
                    tuple(int(d) for d in out_shape if d is not None), self.settings.n_classes, self.layout
                )
            except OutputLayoutError as exc:
                raise ModelError(self.model, str(exc)) from exc

    def detect(self, image: ImageArray) -> list[Detection]:
        """Objects in a BGR ``uint8`` image (as ``cv2.imread`` gives), best score first."""
        if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
            raise DetectionError(f"expected a BGR uint8 image (h, w, 3), got {image.dtype} {image.shape}")
        padded, placement = letterbox(image, self.input_hw)
        blob = cv2.dnn.blobFromImage(padded, scalefactor=1 / 255.0, swapRB=True)
        feed = {self._input_name: blob.astype(self._input_dtype, copy=False)}
        try:
            output = self._session.run([self._output_name], feed)[0]
        # As at load: onnxruntime's run-time errors (e.g. a shape the graph rejects) have no common base.
        except Exception as exc:
            raise ModelError(self.model, f"inference failed: {exc}") from exc
        try:
            candidates = decode_output(output, self.settings.n_classes, self.layout)
        except OutputLayoutError as exc:
            raise ModelError(self.model, str(exc)) from exc
        s = self.settings
        keep = non_max_suppression(candidates, s.conf_threshold, s.iou_threshold, s.max_detections)
        boxes = placement.to_original(candidates.boxes[keep])
        detections = []
        for (x1, y1, x2, y2), score, class_id in zip(
            boxes.tolist(), candidates.scores[keep].tolist(), candidates.class_ids[keep].tolist(), strict=True
        ):
            # A box that lies wholly in the padding is clipped to nothing: it shows no part of the image.
            if x2 > x1 and y2 > y1:
                detections.append(Detection(class_id, score, x1, y1, x2, y2))
        return detections
