"""The detector service, RGB-D mode: objects detected in its robot's RGB-D frames.

The robot's block of a TUM-format sequence folder (``rgb.txt``, ``depth.txt``,
the images; :func:`swarmrec.datasets.tum_rgbd.read_tum_rgbd`) is played
frame by frame through :class:`swarmrec.detection.RgbdPipeline`: a YOLO-style
ONNX model on onnxruntime's CPU provider (any v5/v8 export of ``n_labels``
classes, or the project's own model), then the median 3D point of each box's
valid depth pixels, as the constellation paper made its constellations. The
constellation (camera frame, metres, best box first) goes to the descriptor
exactly as a replayed one does, with the same ``step`` and ``replay``
endpoints (:class:`swarmrec.services.detector.FrameDetector`).

Every frame is counted in ``swarmrec_detector_frames_total{outcome}``:

* ``detected``: a constellation with at least one object was sent;
* ``no_objects``: nothing detected (or no box had depth); the empty
  constellation is sent, as a recorded frame with no object would be;
* ``missing_image``, ``corrupt_image``, ``size_mismatch``: the frame's RGB or
  depth PNG is missing, does not decode (or the depth is not 16-bit), or RGB
  and depth differ in size; nothing is sent and the step answers with an
  error reply (``ERROR_CODE_NOT_FOUND`` for a missing file,
  ``ERROR_CODE_INVALID_ARGUMENT`` otherwise) naming the file;
* ``detector_error``: the model failed on the image (``ERROR_CODE_INTERNAL``).

Boxes without valid depth are counted in
``swarmrec_detector_boxes_dropped_total{reason="no_depth"}``; objects sent in
``swarmrec_detector_objects_total``; stage times in
``swarmrec_detector_stage_seconds{stage}``. With a ``data_dir``, each
constellation made is also written to ``<data_dir>/constellations/<frame id>.txt``
(the constellation format, so ``swarmrec evaluate`` reads it); the main job
builds its report from these.

A model that does not load or does not fit the label list, a missing
sequence folder or label list are start-up errors with a message naming the
file: the service does not start.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

from swarmrec.core.types import Constellation
from swarmrec.datasets.constellations import format_constellation
from swarmrec.datasets.tum_rgbd import RgbdFrame, RgbdImageError, load_rgbd, read_tum_rgbd
from swarmrec.detection import DetectionError, DetectorSettings, OnnxDetector, RgbdPipeline
from swarmrec.errors import ConfigError
from swarmrec.models import DETECTOR_MODEL, shipped_model
from swarmrec.services.config import ServiceSettings
from swarmrec.services.detector import FrameDetector, label_names, robot_block
from swarmrec.services.runner import RequestError, ServiceContext
from swarmrec.wire import messages as pb

__all__ = [
    "DEFAULT_CONF_THRESHOLD",
    "SKIP_OUTCOMES",
    "DetectorRgbd",
    "FrameResult",
    "conf_threshold_of",
    "frame_id_of",
    "load_detector",
    "model_path_of",
    "process_frame",
]

#: Confidence threshold of a user's model when none is set: Ultralytics' own default.
#: (The paper's zero threshold keeps hundreds of boxes a frame with today's exports.)
DEFAULT_CONF_THRESHOLD = 0.25

#: The outcomes of a frame that is skipped (nothing sent), by image problem.
SKIP_OUTCOMES = {"missing": "missing_image", "corrupt": "corrupt_image", "size_mismatch": "size_mismatch"}


def model_path_of(settings: ServiceSettings) -> Path:
    """``detector_model``, or the project's shipped detector when it is empty."""
    if settings.detector_model:
        return Path(settings.detector_model)
    return shipped_model(DETECTOR_MODEL)


def conf_threshold_of(settings: ServiceSettings) -> float:
    """``conf_threshold``; unset: the shipped model's recommended one (its ``metrics.json``)
    for the project's model, :data:`DEFAULT_CONF_THRESHOLD` for a user's."""
    if settings.conf_threshold is not None:
        return settings.conf_threshold
    if not settings.detector_model:
        recommended = _recommended_threshold(model_path_of(settings).parent / "metrics.json")
        if recommended is not None:
            return recommended
    return DEFAULT_CONF_THRESHOLD


def _recommended_threshold(path: Path) -> float | None:
    """``recommended_conf_threshold`` of a model card's metrics (models/detector/train.py writes it)."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict):
        return None
    value = data.get("recommended_conf_threshold")
    if isinstance(value, int | float) and not isinstance(value, bool) and 0.0 <= value <= 1.0:
        return float(value)
    return None


def load_detector(settings: ServiceSettings) -> OnnxDetector:
    """The ONNX detector the settings describe; ModelError / ModelNotFound name the file."""
    return OnnxDetector(
        model_path_of(settings),
        DetectorSettings(
            n_classes=settings.n_labels,
            conf_threshold=conf_threshold_of(settings),
            iou_threshold=settings.iou_threshold,
            intra_op_threads=settings.detector_threads,
        ),
    )


@dataclass(frozen=True, eq=False)
class FrameResult:
    """What became of one frame.

    ``outcome`` is ``detected`` or ``no_objects`` when a constellation was
    made, else why the frame is skipped (``missing_image``, ``corrupt_image``,
    ``size_mismatch``, ``detector_error``): then ``constellation`` is None,
    ``reason`` names the file and the problem and ``code`` is the ErrorCode
    the step answers with. ``seconds`` holds the time of each stage run.
    """

    outcome: str
    constellation: Constellation | None
    dropped_no_depth: int = 0
    reason: str = ""
    code: int = pb.ErrorCode.ERROR_CODE_UNSPECIFIED
    seconds: dict[str, float] = field(default_factory=dict)


def process_frame(pipeline: RgbdPipeline, frame: RgbdFrame) -> FrameResult:
    """Decode a frame's images and make its constellation; a bad frame is a skip, never an exception."""
    t0 = time.perf_counter()
    try:
        rgb, depth = load_rgbd(frame.rgb_path, frame.depth_path)
    except RgbdImageError as e:
        missing = e.problem == "missing"
        code = pb.ErrorCode.ERROR_CODE_NOT_FOUND if missing else pb.ErrorCode.ERROR_CODE_INVALID_ARGUMENT
        return FrameResult(SKIP_OUTCOMES[e.problem], None, reason=str(e), code=code)
    decode_s = time.perf_counter() - t0
    try:
        result = pipeline.run(rgb, depth)
    except DetectionError as e:
        internal = pb.ErrorCode.ERROR_CODE_INTERNAL
        return FrameResult("detector_error", None, reason=str(e), code=internal, seconds={"decode": decode_s})
    c = result.constellation
    return FrameResult(
        "detected" if len(c) else "no_objects",
        c,
        dropped_no_depth=result.dropped_no_depth,
        seconds={"decode": decode_s, **result.seconds},
    )


def frame_id_of(frame: RgbdFrame) -> str:
    """A frame's id: its RGB timestamp with TUM's six decimals (the constellation files' names)."""
    return f"{frame.timestamp:.6f}"


class DetectorRgbd(FrameDetector):
    """Detects objects in its robot's block of a TUM-format RGB-D folder."""

    def __init__(self, ctx: ServiceContext) -> None:
        super().__init__(ctx)
        s = ctx.settings
        if not s.dataset:
            raise ConfigError(
                "the rgbd detector reads a TUM RGB-D folder: set --dataset (with rgb.txt, depth.txt)"
            )
        self.names = label_names(s)
        seq = read_tum_rgbd(s.dataset, max_dt=s.rgbd_max_dt)
        self.frames: list[RgbdFrame] = [seq.frames[g] for g in robot_block(len(seq), s)]
        self.frame_ids = [frame_id_of(f) for f in self.frames]
        detector = load_detector(s)
        self.pipeline = RgbdPipeline(detector, s.camera())
        self.out_dir = s.data_dir / "constellations" if s.data_dir else None
        if self.out_dir is not None:
            self.out_dir.mkdir(parents=True, exist_ok=True)
        m = ctx.metrics
        self.frames_total = m.detector_frames
        self.dropped = m.detector_boxes_dropped.labels("no_depth")
        self.objects = m.detector_objects
        self.stage = {name: m.detector_stage_seconds.labels(name) for name in ("decode", "detect", "points")}
        ctx.log.info(
            "sequence and model loaded",
            extra={
                "fields": {
                    "dataset": s.dataset,
                    "frames": len(self.frames),
                    "model": detector.model,
                    "layout": str(detector.layout),
                    "input_hw": list(detector.input_hw),
                    "conf_threshold": detector.settings.conf_threshold,
                }
            },
        )

    def constellation(self, t: int) -> Constellation:
        result = process_frame(self.pipeline, self.frames[t])
        self.frames_total.labels(result.outcome).inc()
        for name, seconds in result.seconds.items():
            self.stage[name].observe(seconds)
        if result.constellation is None:
            fields = {"frame": t, "frame_id": self.frame_ids[t], "outcome": result.outcome}
            self.ctx.log.warning("frame skipped", extra={"fields": fields | {"reason": result.reason}})
            raise RequestError(
                result.code, f"frame {t} ({self.frame_ids[t]}) skipped, {result.outcome}: {result.reason}"
            )
        c = result.constellation
        self.dropped.inc(result.dropped_no_depth)
        self.objects.inc(len(c))
        if self.out_dir is not None:
            path = self.out_dir / f"{self.frame_ids[t]}.txt"
            path.write_text(format_constellation(c, self.names), encoding="utf-8")
        return c
