"""The detector service, replay mode: plays its robot's part of a
constellation dataset into the robot's descriptor service.

The dataset is cut into ``n_robots`` consecutive sub-trajectories, as the
paper's evaluation cuts it (``frames_per_robot`` overrides the even split);
this robot replays block ``robot``. Frames are sent as requests to the
descriptor (``descriptor/<robot>/process``), so the replay waits for each
query to finish: a slow swarm slows the replay rather than losing frames.

Endpoints:

* ``step``: :class:`StepRequest` -> :class:`StepReply`. Lock-step replay:
  the main job asks every detector for step t and waits for all before t + 1.
* ``replay``: :class:`ReplayRequest` -> :class:`ReplayReply`. Free replay of
  the whole block at ``rate_hz`` (0: as fast as the swarm answers), in the
  background; reports appear on ``events/query/<robot>``.

The ONNX detection path (RGB-D frames in) is the detector issue's; this
service is the same endpoint fed from recorded constellations.
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
from swarmrec.services.rpc import CallError
from swarmrec.services.runner import Endpoint, RequestContext, RequestError, ServiceContext
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import constellation_to_proto

__all__ = ["DetectorReplay"]


class DetectorReplay:
    def __init__(self, ctx: ServiceContext) -> None:
        s = ctx.settings
        self.ctx = ctx
        if not s.dataset:
            raise ConfigError("the detector replays a dataset: set --dataset (a folder or .zip)")
        names = read_label_names(s.labels_file) if s.labels_file else COCO_NAMES
        seq = read_constellations(s.dataset, names)
        if seq.n_labels != s.n_labels:
            raise ConfigError(f"the dataset's label list has {seq.n_labels} labels, the swarm {s.n_labels}")
        if s.frames_per_robot:
            per = s.frames_per_robot
            block = range(min(s.robot * per, len(seq)), min((s.robot + 1) * per, len(seq)))
        else:
            block = split_frames(len(seq), s.n_robots)[s.robot]
        self.frames: list[Constellation] = [seq.constellations[g] for g in block]
        self.frame_ids = [seq.frame_ids[g] for g in block]
        self.lock = threading.Lock()
        self.replaying: threading.Thread | None = None
        self.key = keys.endpoint(s.swarm, "descriptor", s.robot, "process")
        # A frame's query holds several nested requests; give it their time and some.
        self.timeout_s = 4 * s.request_timeout_s
        ctx.log.info("dataset loaded", extra={"fields": {"dataset": s.dataset, "frames": len(self.frames)}})

    def endpoints(self) -> Sequence[Endpoint]:
        return [
            Endpoint("step", pb.StepRequest, self.step),
            Endpoint("replay", pb.ReplayRequest, self.replay),
        ]

    def member_info(self) -> pb.MemberInfo:
        return pb.MemberInfo()

    def _send(self, t: int) -> pb.QueryReport:
        s = self.ctx.settings
        try:
            wire = constellation_to_proto(self.frames[t], s.robot, t, self.frame_ids[t])
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
        if req.step >= len(self.frames):
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
        return pb.ReplayReply(robot_id=self.ctx.settings.robot, n_frames=len(self.frames))

    def _replay(self, rate_hz: float) -> None:
        period = 1.0 / rate_hz if rate_hz > 0 else 0.0
        # Robots are not synchronised: each starts at its own phase of the period,
        # or all ten would query at the same instant, every time.
        settings = self.ctx.settings
        start = time.perf_counter() + period * settings.robot / settings.n_robots
        for t in range(len(self.frames)):
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
        self.ctx.log.info("replay finished", extra={"fields": {"frames": len(self.frames)}})

    def close(self) -> None:
        if self.replaying is not None:
            self.replaying.join(timeout=5.0)
