"""The detector service: feeds its robot's frames, one constellation each, into
the robot's descriptor service.

``detector_mode`` picks where the constellations come from
(:func:`make_detector`):

* ``replay`` (:class:`DetectorReplay`): recorded constellations, a folder or
  zip of constellation files;
* ``rgbd`` (:class:`swarmrec.services.detector_rgbd.DetectorRgbd`): RGB-D
  frames of a TUM-format folder through a YOLO-style ONNX model and the
  depth image, as the constellation paper made them (docs/detector.md);
* ``classifier`` (:class:`swarmrec.services.detector_classifier.DetectorClassifier`):
  camera views to landmark probabilities for the robot's fusion round.

The dataset is cut into ``n_robots`` consecutive sub-trajectories, as the
paper's evaluation cuts it (``frames_per_robot`` overrides the even split);
this robot plays block ``robot``. Frames are sent as requests to the
descriptor (``descriptor/<robot>/process``), so the replay waits for each
query to finish: a slow swarm slows the replay rather than losing frames.

Endpoints of the replay and rgbd modes (the same, so the main job drives both alike):

* ``step``: :class:`StepRequest` -> :class:`StepReply`. Lock-step replay:
  the main job asks every detector for step t and waits for all before t + 1.
  A frame the detector cannot make a constellation of is answered with an
  error reply that says why; the service goes on with the next step.
* ``replay``: :class:`ReplayRequest` -> :class:`ReplayReply`. Free replay of
  the whole block at ``rate_hz`` (0: as fast as the swarm answers), in the
  background; reports appear on ``events/query/<robot>``.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Sequence

from swarmrec.core.split import split_frames
from swarmrec.core.types import Constellation
from swarmrec.datasets.constellations import read_constellations
from swarmrec.datasets.labels import COCO_NAMES, read_label_names
from swarmrec.errors import ConfigError, WireError
from swarmrec.services import keys
from swarmrec.services.common import invalid
from swarmrec.services.config import ServiceSettings
from swarmrec.services.rpc import CallError
from swarmrec.services.runner import Endpoint, RequestContext, RequestError, Service, ServiceContext
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import constellation_to_proto

__all__ = ["DetectorReplay", "FrameDetector", "label_names", "make_detector", "robot_block"]


def robot_block(n_frames: int, settings: ServiceSettings) -> range:
    """The frames (indices into the whole sequence) that robot ``settings.robot`` plays."""
    if settings.frames_per_robot:
        per = settings.frames_per_robot
        return range(min(settings.robot * per, n_frames), min((settings.robot + 1) * per, n_frames))
    return split_frames(n_frames, settings.n_robots)[settings.robot]


def label_names(settings: ServiceSettings) -> tuple[str, ...]:
    """The label list of ``labels_file`` (COCO by default), checked against ``n_labels``."""
    names = read_label_names(settings.labels_file) if settings.labels_file else COCO_NAMES
    if len(names) != settings.n_labels:
        raise ConfigError(f"the label list has {len(names)} labels, the swarm {settings.n_labels}")
    return names


class FrameDetector:
    """The ``step`` and ``replay`` endpoints, for any source of constellations.

    A subclass sets ``frame_ids`` (one per frame of this robot's block) and
    implements :meth:`constellation`, which may raise :class:`RequestError`
    for a frame it cannot make (counted and logged by the subclass).
    """

    frame_ids: list[str]

    def __init__(self, ctx: ServiceContext) -> None:
        s = ctx.settings
        self.ctx = ctx
        self.lock = threading.Lock()
        self.replaying: threading.Thread | None = None
        self.key = keys.endpoint(s.swarm, "descriptor", s.robot, "process")
        # A frame's query holds several nested requests; give it their time and some.
        self.timeout_s = 4 * s.request_timeout_s

    def constellation(self, t: int) -> Constellation:
        """The constellation of this robot's frame ``t``."""
        raise NotImplementedError

    def endpoints(self) -> Sequence[Endpoint]:
        return [
            Endpoint("step", pb.StepRequest, self.step),
            Endpoint("replay", pb.ReplayRequest, self.replay),
        ]

    def member_info(self) -> pb.MemberInfo:
        return pb.MemberInfo()

    def _send(self, t: int) -> pb.QueryReport:
        s = self.ctx.settings
        c = self.constellation(t)
        try:
            wire = constellation_to_proto(c, s.robot, t, self.frame_ids[t])
        except WireError as e:
            # A frame the detector cannot put on the wire (NaN position): counted, skipped.
            self.ctx.metrics.rejected.labels("frame", "ERROR_CODE_INVALID_ARGUMENT").inc()
            self.ctx.log.warning("frame not sent", extra={"fields": {"frame": t, "reason": str(e)}})
            raise RequestError(pb.ErrorCode.ERROR_CODE_INVALID_ARGUMENT, f"frame {t}: {e}") from None
        return self.ctx.caller.call(
            self.key, wire, pb.QueryReport, target_robot=s.robot, endpoint="process", timeout_s=self.timeout_s
        )

    def step(self, req: pb.StepRequest, _ctx: RequestContext) -> pb.StepReply:
        robot = self.ctx.settings.robot
        if req.step >= len(self.frame_ids):
            return pb.StepReply(robot_id=robot, step=req.step, finished=True)
        with self.lock:  # steps of one robot run in order
            try:
                report = self._send(req.step)
            except CallError as e:
                raise RequestError(pb.ErrorCode.ERROR_CODE_UNAVAILABLE, f"descriptor: {e}") from None
        return pb.StepReply(robot_id=robot, step=req.step, report=report)

    def replay(self, req: pb.ReplayRequest, _ctx: RequestContext) -> pb.ReplayReply:
        if not (math.isfinite(req.rate_hz) and req.rate_hz >= 0):
            raise invalid(f"rate_hz must be >= 0, got {req.rate_hz}")
        with self.lock:
            if self.replaying is not None and self.replaying.is_alive():
                raise RequestError(pb.ErrorCode.ERROR_CODE_UNAVAILABLE, "a replay is already running")
            self.replaying = threading.Thread(target=self._replay, args=(req.rate_hz,), daemon=True)
            self.replaying.start()
        return pb.ReplayReply(robot_id=self.ctx.settings.robot, n_frames=len(self.frame_ids))

    def _replay(self, rate_hz: float) -> None:
        period = 1.0 / rate_hz if rate_hz > 0 else 0.0
        # Robots are not synchronised: each starts at its own phase of the period,
        # or all ten would query at the same instant, every time.
        settings = self.ctx.settings
        start = time.perf_counter() + period * settings.robot / settings.n_robots
        for t in range(len(self.frame_ids)):
            if self.ctx.stop.is_set():
                return
            if period:
                delay = start + t * period - time.perf_counter()
                if delay > 0 and self.ctx.stop.wait(delay):
                    return
            try:
                self._send(t)
            except (CallError, RequestError) as e:
                self.ctx.log.warning("frame failed", extra={"fields": {"frame": t, "reason": str(e)}})
        self.ctx.log.info("replay finished", extra={"fields": {"frames": len(self.frame_ids)}})

    def close(self) -> None:
        if self.replaying is not None:
            self.replaying.join(timeout=5.0)


class DetectorReplay(FrameDetector):
    """Replays its robot's block of a constellation dataset (folder or zip)."""

    def __init__(self, ctx: ServiceContext) -> None:
        super().__init__(ctx)
        s = ctx.settings
        if not s.dataset:
            raise ConfigError("the detector replays a dataset: set --dataset (a folder or .zip)")
        names = read_label_names(s.labels_file) if s.labels_file else COCO_NAMES
        seq = read_constellations(s.dataset, names)
        if seq.n_labels != s.n_labels:
            raise ConfigError(f"the dataset's label list has {seq.n_labels} labels, the swarm {s.n_labels}")
        block = robot_block(len(seq), s)
        self.frames: list[Constellation] = [seq.constellations[g] for g in block]
        self.frame_ids = [seq.frame_ids[g] for g in block]
        ctx.log.info("dataset loaded", extra={"fields": {"dataset": s.dataset, "frames": len(self.frames)}})

    def constellation(self, t: int) -> Constellation:
        return self.frames[t]


def make_detector(ctx: ServiceContext) -> Service:
    """The detector of ``ctx.settings.detector_mode`` (the ``detector`` kind's factory)."""
    mode = ctx.settings.detector_mode
    if mode == "replay":
        return DetectorReplay(ctx)
    if mode == "rgbd":
        from swarmrec.services.detector_rgbd import DetectorRgbd

        return DetectorRgbd(ctx)
    from swarmrec.services.detector_classifier import DetectorClassifier

    return DetectorClassifier(ctx)
