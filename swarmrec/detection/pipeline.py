"""One RGB-D frame to one constellation: detect, then one point per box.

:class:`RgbdPipeline` is the detector service's work on a frame, without any
I/O: the BGR image goes through the ONNX model (:class:`OnnxDetector`), each
kept box gets the median 3D point of its valid depth pixels
(:func:`object_points`), and the constellation is the boxes that got a point,
best score first (the order the paper's data association breaks ties by),
each labelled with its class index: for a COCO model that is the line of
``coco.names``, the label list the swarm uses.

A box whose depth pixels are all invalid (no reading, or beyond ``max_depth``)
has no point: it is dropped and counted, never given a made-up position.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from swarmrec.core.types import Constellation
from swarmrec.detection.errors import DetectionError
from swarmrec.detection.points import CameraIntrinsics, object_points
from swarmrec.detection.yolo import Detection, OnnxDetector

__all__ = ["FrameObjects", "RgbdPipeline"]

ImageArray = npt.NDArray[np.uint8]


@dataclass(frozen=True, eq=False)
class FrameObjects:
    """What one frame gave.

    ``constellation`` holds the boxes of ``detections`` that had valid depth,
    in the detections' order; ``dropped_no_depth`` counts the others.
    ``seconds`` is the time of the ``detect`` and ``points`` stages.
    """

    constellation: Constellation
    detections: tuple[Detection, ...]
    dropped_no_depth: int
    seconds: dict[str, float] = field(default_factory=dict)


class RgbdPipeline:
    """A detector and a depth camera: RGB-D frames in, constellations out."""

    def __init__(
        self, detector: OnnxDetector, camera: CameraIntrinsics | None = None, max_depth: float | None = None
    ) -> None:
        self.detector = detector
        self.camera = camera or CameraIntrinsics()
        self.max_depth = max_depth

    def run(self, rgb: ImageArray, depth: npt.ArrayLike) -> FrameObjects:
        """The constellation of one frame: BGR ``uint8`` image and its depth image (same size)."""
        d = np.asarray(depth)
        if d.shape != rgb.shape[:2]:
            raise DetectionError(f"depth of shape {d.shape} does not fit an image of shape {rgb.shape}")
        t0 = time.perf_counter()
        detections = tuple(self.detector.detect(rgb))
        t1 = time.perf_counter()
        boxes = np.array([det.box for det in detections], dtype=np.float64).reshape(-1, 4)
        points = object_points(d, boxes, self.camera, self.max_depth)
        labels = np.array([detections[k].class_id for k in points.kept.tolist()], dtype=np.int64)
        t2 = time.perf_counter()
        return FrameObjects(
            Constellation(labels, points.points),
            detections,
            points.n_dropped,
            {"detect": t1 - t0, "points": t2 - t1},
        )
