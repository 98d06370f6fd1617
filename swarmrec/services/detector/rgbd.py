"""The detector service, RGB-D mode: objects detected in its robot's RGB-D frames.

The robot's block of a TUM-format sequence folder (``rgb.txt``, ``depth.txt``,
the images; :func:`swarmrec.datasets.tum_rgbd.read_tum_rgbd`) is played
frame by frame through :class:`swarmrec.detection.RgbdPipeline`: a YOLO-style
ONNX model on onnxruntime's CPU provider (any v5/v8 export of ``n_labels``
classes, or the project's own model), then the median 3D point of each box's
valid depth pixels, as the constellation paper made its constellations. The
constellation (camera frame, metres, best box first) goes to the descriptor
exactly as a replayed one does, with the same ``step`` and ``replay``
endpoints (:class:`swarmrec.services.detector.frames.FramePlayer`).

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

With ``place_method`` dvpr (full-image place recognition, docs/vpr.md) each frame's
RGB image is also described by the full-image descriptor model
(:class:`swarmrec.vpr.model.DescriptorModel`, stage ``describe``), and with a
``data_dir`` the float32 descriptor is written to ``<data_dir>/descriptors/<frame id>.npy``
(what the main job checks the owners' answers against).

A model that does not load or does not fit the label list (or, for dvpr, a
descriptor model that is not one), a missing sequence folder or label list are
start-up errors with a message naming the file: the service does not start.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from swarmrec.core.types import Constellation
from swarmrec.datasets.constellations import format_constellation
from swarmrec.datasets.labels import label_names
from swarmrec.datasets.tum_rgbd import RgbdFrame, RgbdImageError, frame_id_of, load_rgbd, read_tum_rgbd
from swarmrec.detection import DetectionError, RgbdPipeline, load_detector
from swarmrec.errors import ConfigError, ErrorCode, RequestError
from swarmrec.runtime import ServiceContext
from swarmrec.runtime.settings import StorageSettings
from swarmrec.services.detector.frames import robot_block
from swarmrec.services.metrics import DetectorMetrics
from swarmrec.services.settings import DetectorSettings, PlaceSettings, RgbdSettings, VprSettings
from swarmrec.vpr.errors import VprError
from swarmrec.vpr.model import DescriptorModel

__all__ = ["SKIP_OUTCOMES", "FrameResult", "RgbdSource", "process_frame"]

#: The outcomes of a frame that is skipped (nothing sent), by image problem.
SKIP_OUTCOMES = {"missing": "missing_image", "corrupt": "corrupt_image", "size_mismatch": "size_mismatch"}


@dataclass(frozen=True, eq=False)
class FrameResult:
    """What became of one frame.

    ``outcome`` is ``detected`` or ``no_objects`` when a constellation was
    made, else why the frame is skipped (``missing_image``, ``corrupt_image``,
    ``size_mismatch``, ``detector_error``): then ``constellation`` is None,
    ``reason`` names the file and the problem and ``code`` is the ErrorCode
    the step answers with. ``seconds`` holds the time of each stage run;
    ``descriptor`` the full-image descriptor when a describer was given.
    """

    outcome: str
    constellation: Constellation | None
    dropped_no_depth: int = 0
    reason: str = ""
    code: ErrorCode = ErrorCode.UNSPECIFIED
    seconds: dict[str, float] = field(default_factory=dict)
    descriptor: npt.NDArray[np.float32] | None = None


def process_frame(
    pipeline: RgbdPipeline, frame: RgbdFrame, describer: DescriptorModel | None = None
) -> FrameResult:
    """Decode a frame's images and make its constellation (and, with ``describer``, its
    full-image descriptor); a bad frame is a skip, never an exception."""
    t0 = time.perf_counter()
    try:
        rgb, depth = load_rgbd(frame.rgb_path, frame.depth_path)
    except RgbdImageError as e:
        missing = e.problem == "missing"
        code = ErrorCode.NOT_FOUND if missing else ErrorCode.INVALID_ARGUMENT
        return FrameResult(SKIP_OUTCOMES[e.problem], None, reason=str(e), code=code)
    decode_s = time.perf_counter() - t0
    try:
        result = pipeline.run(rgb, depth)
    except DetectionError as e:
        return FrameResult(
            "detector_error", None, reason=str(e), code=ErrorCode.INTERNAL, seconds={"decode": decode_s}
        )
    c = result.constellation
    seconds = {"decode": decode_s, **result.seconds}
    descriptor = None
    if describer is not None:
        t1 = time.perf_counter()
        try:
            descriptor = describer.describe_frames(rgb)[0]
        except VprError as e:
            code = ErrorCode.INTERNAL
            return FrameResult("detector_error", None, reason=str(e), code=code, seconds=seconds)
        seconds["describe"] = time.perf_counter() - t1
    return FrameResult(
        "detected" if len(c) else "no_objects",
        c,
        dropped_no_depth=result.dropped_no_depth,
        seconds=seconds,
        descriptor=descriptor,
    )


class RgbdSource:
    """Detects objects in its robot's block of a TUM-format RGB-D folder."""

    def __init__(self, ctx: ServiceContext) -> None:
        self.ctx = ctx
        detector, rgbd = ctx.settings(DetectorSettings), ctx.settings(RgbdSettings)
        if not detector.dataset:
            raise ConfigError(
                "the rgbd detector reads a TUM RGB-D folder: set --dataset (with rgb.txt, depth.txt)"
            )
        n_labels = ctx.settings(PlaceSettings).n_labels
        self.names = label_names(detector.labels_file, n_labels)
        seq = read_tum_rgbd(detector.dataset, max_dt=rgbd.rgbd_max_dt)
        self.frames: list[RgbdFrame] = [seq.frames[g] for g in robot_block(len(seq), ctx.bus, detector)]
        self.frame_ids = [frame_id_of(f) for f in self.frames]
        model = load_detector(
            rgbd.detector_model,
            n_classes=n_labels,
            conf_threshold=rgbd.conf_threshold,
            iou_threshold=rgbd.iou_threshold,
            threads=rgbd.detector_threads,
        )
        self.pipeline = RgbdPipeline(model, rgbd.camera())
        vpr = ctx.settings(VprSettings)
        self.describer: DescriptorModel | None = None
        if vpr.place_method == "dvpr":
            # A file that is not a descriptor model is refused here, before the service serves.
            model_path = vpr.descriptor_model or None
            self.describer = DescriptorModel(model_path, intra_op_threads=vpr.descriptor_threads)
        storage = ctx.settings(StorageSettings)
        self.out_dir = storage.data_dir / "constellations" if storage.data_dir else None
        if self.out_dir is not None:
            self.out_dir.mkdir(parents=True, exist_ok=True)
        self.descriptor_dir = None
        if storage.data_dir and self.describer is not None:
            self.descriptor_dir = storage.data_dir / "descriptors"
            self.descriptor_dir.mkdir(parents=True, exist_ok=True)
        m = ctx.metric_set(DetectorMetrics)
        self.frames_total = m.frames
        self.dropped = m.boxes_dropped.labels("no_depth")
        self.objects = m.objects
        stages = ("decode", "detect", "points") + (("describe",) if self.describer is not None else ())
        self.stage = {name: m.stage_seconds.labels(name) for name in stages}
        fields = {
            "dataset": detector.dataset,
            "frames": len(self.frames),
            "model": model.model,
            "layout": str(model.layout),
            "input_hw": list(model.input_hw),
            "conf_threshold": model.settings.conf_threshold,
            "descriptor_model": self.describer.model if self.describer is not None else None,
        }
        ctx.log.info("sequence and model loaded", extra={"fields": fields})

    def constellation(self, t: int) -> Constellation:
        return self.observe(t)[0]

    def place_frame(self, t: int) -> tuple[Constellation, npt.NDArray[np.float32]]:
        """Frame ``t``'s constellation and full-image descriptor (place_method dvpr)."""
        c, descriptor = self.observe(t)
        if descriptor is None:
            raise ConfigError("this detector has no descriptor model: set place_method dvpr")
        return c, descriptor

    def observe(self, t: int) -> tuple[Constellation, npt.NDArray[np.float32] | None]:
        """What frame ``t`` gives: its constellation and (dvpr) its descriptor, both written to
        the data folder; RequestError for a frame that is skipped."""
        result = process_frame(self.pipeline, self.frames[t], self.describer)
        self.frames_total.labels(result.outcome).inc()
        for name, seconds in result.seconds.items():
            self.stage[name].observe(seconds)
        if result.constellation is None:
            fields = {"frame": t, "frame_id": self.frame_ids[t], "outcome": result.outcome}
            self.ctx.log.warning("frame skipped", extra={"fields": fields | {"reason": result.reason}})
            raise RequestError(
                f"frame {t} ({self.frame_ids[t]}) skipped, {result.outcome}: {result.reason}",
                code=result.code,
            )
        c = result.constellation
        self.dropped.inc(result.dropped_no_depth)
        self.objects.inc(len(c))
        if self.out_dir is not None:
            path = self.out_dir / f"{self.frame_ids[t]}.txt"
            path.write_text(format_constellation(c, self.names), encoding="utf-8")
        if self.descriptor_dir is not None and result.descriptor is not None:
            np.save(self.descriptor_dir / f"{self.frame_ids[t]}.npy", result.descriptor)
        return c, result.descriptor
