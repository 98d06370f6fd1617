"""The detector stage: RGB-D frame -> YOLO detections -> one 3D point per object.

An image goes through :class:`OnnxDetector` (letterbox, ONNX model, decode of
the v5 or v8 output layout, confidence threshold, class-aware NMS) to
:class:`Detection` boxes in the image's own pixels; :func:`object_points`
turns the boxes and the depth image into the constellation's points;
:class:`RgbdPipeline` does both for a frame and gives its constellation.
"""

from swarmrec.detection.decode import Candidates, Layout, decode_output, detect_layout
from swarmrec.detection.errors import DetectionError, ModelError, OutputLayoutError
from swarmrec.detection.letterbox import PAD_VALUE, Letterbox, letterbox
from swarmrec.detection.loader import DEFAULT_CONF_THRESHOLD, conf_threshold_for, load_detector, model_path
from swarmrec.detection.nms import non_max_suppression
from swarmrec.detection.pipeline import FrameObjects, RgbdPipeline
from swarmrec.detection.points import CameraIntrinsics, ObjectPoints, object_points, transform_points
from swarmrec.detection.yolo import Detection, DetectorSettings, OnnxDetector

__all__ = [
    "DEFAULT_CONF_THRESHOLD",
    "PAD_VALUE",
    "CameraIntrinsics",
    "Candidates",
    "Detection",
    "DetectionError",
    "DetectorSettings",
    "FrameObjects",
    "Layout",
    "Letterbox",
    "ModelError",
    "ObjectPoints",
    "OnnxDetector",
    "OutputLayoutError",
    "RgbdPipeline",
    "conf_threshold_for",
    "decode_output",
    "detect_layout",
    "letterbox",
    "load_detector",
    "model_path",
    "non_max_suppression",
    "object_points",
    "transform_points",
]
