"""Playing a robot's frames into its descriptor service: the ``step`` and ``replay``
endpoints of the replay and rgbd modes.

The dataset is cut into ``n_robots`` consecutive sub-trajectories, as the
paper's evaluation cuts it (``frames_per_robot`` overrides the even split);
this robot plays block ``robot``. Frames are sent as requests to the
descriptor (``descriptor/<robot>/process``), so the replay waits for each
query to finish: a slow swarm slows the replay rather than losing frames.

Every frame goes through the robot's outbox (:mod:`.outbox`, on disk): one the
descriptor cannot take now (it, its verifier or the router not answering) waits
there and is sent again, oldest first, until it is taken; nothing played is lost,
and the descriptor's idempotent stores keep a frame sent twice stored once.

* ``step`` (lock-step replay): the main job asks every detector for step t and
  waits for all before t + 1. A frame the detector cannot make a constellation
  of is answered with an error reply that says why; the service goes on. A frame
  that must wait is answered ``queued``; its report comes with a later reply
  (``late_reports``). A step past the end flushes the outbox: the job asks for one
  until no robot has frames ``pending``.
* ``replay`` (free replay): the whole block at ``rate_hz`` (0: as fast as the
  swarm answers), in the background; reports appear on ``events/query/<robot>``.

With ``place_method`` dvpr (rgbd mode only) each frame goes instead to the robot's
place-owner (``place-owner/<robot>/process``) as a :class:`PlaceFrame`: its float32
full-image descriptor and its constellation; the step answers with the
:class:`PlaceReport` in ``StepReply.place``, and a free replay's reports appear on
``events/place_query/<robot>``.
"""

from __future__ import annotations

import math
import threading
import time
from typing import Protocol

import numpy as np
import numpy.typing as npt

from swarmrec.core.split import split_frames
from swarmrec.core.types import Constellation
from swarmrec.errors import (
    TRANSIENT_CODES,
    CallError,
    ConfigError,
    ErrorCode,
    InvalidArgument,
    RemoteError,
    RequestError,
    Unavailable,
    WireError,
)
from swarmrec.runtime import ServiceContext, keys
from swarmrec.runtime.settings import BusSettings
from swarmrec.services.detector.outbox import Outbox
from swarmrec.services.settings import DetectorSettings, PlaceSettings, VprSettings
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import constellation_to_proto

__all__ = ["FramePlayer", "FrameSource", "robot_block"]

#: Late reports kept for the next step's reply.
LATE_REPORTS = 10_000


def _code_of(e: Exception) -> ErrorCode:
    return e.code if isinstance(e, RemoteError | RequestError) else ErrorCode.INTERNAL


def robot_block(n_frames: int, bus: BusSettings, detector: DetectorSettings) -> range:
    """The frames (indices into the whole sequence) that robot ``bus.robot`` plays."""
    if detector.frames_per_robot:
        per = detector.frames_per_robot
        return range(min(bus.robot * per, n_frames), min((bus.robot + 1) * per, n_frames))
    return split_frames(n_frames, bus.n_robots)[bus.robot]


class FrameSource(Protocol):
    """Where a robot's constellations come from (recorded, or detected in RGB-D frames)."""

    #: One id per frame of this robot's block (a timestamp, a file name).
    frame_ids: list[str]

    def constellation(self, t: int) -> Constellation:
        """The constellation of this robot's frame ``t``; may raise RequestError for a
        frame it cannot make (counted and logged by the source)."""
        ...


class PlaceSource(FrameSource, Protocol):
    """A source that also gives each frame's full-image descriptor (rgbd with place_method dvpr)."""

    def place_frame(self, t: int) -> tuple[Constellation, npt.NDArray[np.float32]]:
        """Frame ``t``'s constellation and float32 descriptor; RequestError as ``constellation``."""
        ...


class FramePlayer:
    """Sends a source's frames to the robot's descriptor, by step or as a free replay."""

    def __init__(self, ctx: ServiceContext, source: FrameSource) -> None:
        self.ctx, self.source = ctx, source
        bus = ctx.bus
        detector = ctx.settings(DetectorSettings)
        self.lock = threading.Lock()
        self.outbox = Outbox(ctx.open_log("outbox"), detector.outbox_capacity)
        self.retry_s = detector.outbox_retry_s
        # Reports of queued frames the retrier delivered, for the next step's reply.
        self.late: list[pb.QueryReport] = []
        self._retrier = threading.Thread(target=self._retry, name="outbox", daemon=True)
        self._retrier.start()
        self.replaying: threading.Thread | None = None
        self.key = keys.endpoint(bus.swarm, "descriptor", bus.robot, "process")
        self.dvpr = ctx.settings(VprSettings).place_method == "dvpr"
        if self.dvpr and not hasattr(source, "place_frame"):
            raise ConfigError(
                "place_method dvpr describes camera images: run the detector in rgbd mode "
                "(a replayed constellation has no image)"
            )
        self.place_key = keys.endpoint(bus.swarm, "place-owner", bus.robot, "process")
        # A frame's query holds several nested requests; give it their time and some.
        self.timeout_s = 4 * bus.request_timeout_s
        self.exact = ctx.settings(PlaceSettings).exact_positions
        # Frames the descriptor refused for what they are (answered with the step's error).
        self.refused: dict[int, Exception] = {}
        # Constellations made for frames still in the outbox: a frame is detected once, when
        # played, not again at each send (bounded by the outbox's capacity; after a restart a
        # queued frame is made again from its source).
        self.made: dict[int, Constellation] = {}
        self.unmade: dict[int, RequestError] = {}  # at most one per frame of the block

    def _make(self, t: int) -> None:
        """Make frame ``t`` (RequestError for a frame that cannot be made) and queue it.
        A frame that cannot be made is remembered: asked again (a lock-step retry), it is
        refused with the same error without being decoded, detected and counted twice."""
        unmade = self.unmade.get(t)
        if unmade is not None:
            raise RequestError(str(unmade), code=unmade.code)
        try:
            c = self.source.constellation(t)
        except RequestError as e:
            self.unmade[t] = e
            raise
        self.outbox.add(t)
        self.made[t] = c

    def _done(self, t: int) -> None:
        self.outbox.done(t)
        self.made.pop(t, None)

    def _send(self, t: int) -> pb.QueryReport:
        robot = self.ctx.bus.robot
        c = self.made.get(t)
        if c is None:
            c = self.made[t] = self.source.constellation(t)
        try:
            wire = constellation_to_proto(c, robot, t, self.source.frame_ids[t], exact=self.exact)
        except WireError as e:
            # A frame the detector cannot put on the wire (NaN position): counted, skipped.
            self.ctx.metrics.rejected.labels("frame", "ERROR_CODE_INVALID_ARGUMENT").inc()
            self.ctx.log.warning("frame not sent", extra={"fields": {"frame": t, "reason": str(e)}})
            raise InvalidArgument(f"frame {t}: {e}") from None
        return self.ctx.caller.call(
            self.key, wire, pb.QueryReport, target_robot=robot, endpoint="process", timeout_s=self.timeout_s
        )

    def _flush(self, deadline: float) -> list[tuple[int, pb.QueryReport]]:
        """Send the waiting frames, oldest first, until one must wait again or ``deadline``
        (caller holds the lock). A frame the descriptor refuses for what it is (not for
        being unreachable) leaves the outbox: sending it again would be refused again."""
        delivered = []
        for frame in self.outbox.waiting():
            if time.monotonic() > deadline:
                break
            try:
                report = self._send(frame)
            except RemoteError as e:
                if e.code in TRANSIENT_CODES:
                    break
                self._done(frame)
                self.ctx.log.warning("frame refused", extra={"fields": {"frame": frame, "reason": str(e)}})
                self.refused[frame] = e
                continue
            except CallError:
                break
            except RequestError as e:
                self._done(frame)
                self.refused[frame] = e
                continue
            self._done(frame)
            delivered.append((frame, report))
        return delivered

    def _take_late(self) -> list[pb.QueryReport]:
        late, self.late = self.late, []
        return late

    def _send_place(self, t: int) -> pb.PlaceReport:
        robot = self.ctx.bus.robot
        source: PlaceSource = self.source  # type: ignore[assignment]  # checked in __init__
        c, descriptor = source.place_frame(t)
        try:
            wire = constellation_to_proto(c, robot, t, self.source.frame_ids[t], exact=self.exact)
        except WireError as e:
            self.ctx.metrics.rejected.labels("frame", "ERROR_CODE_INVALID_ARGUMENT").inc()
            self.ctx.log.warning("frame not sent", extra={"fields": {"frame": t, "reason": str(e)}})
            raise InvalidArgument(f"frame {t}: {e}") from None
        # Imported here: a constellation detector never loads the full-image method's code.
        from swarmrec.wire.vpr import descriptor_to_wire

        # The robot's own place-owner routes with the exact float32 values (robot scope, no radio).
        data, encoding = descriptor_to_wire(descriptor, "float32")
        msg = pb.PlaceFrame(
            robot_id=robot,
            frame_index=t,
            frame_id=self.source.frame_ids[t],
            descriptor=data,
            encoding=encoding,  # type: ignore[arg-type]  # an enum value
            constellation=wire,
        )
        return self.ctx.caller.call(
            self.place_key,
            msg,
            pb.PlaceReport,
            target_robot=robot,
            endpoint="process",
            timeout_s=self.timeout_s,
        )

    def step(self, req: pb.StepRequest) -> pb.StepReply:
        if self.dvpr:
            return self._step_place(req)
        robot = self.ctx.bus.robot
        deadline = time.monotonic() + self.timeout_s
        with self.lock:  # steps of one robot run in order
            if req.step >= len(self.source.frame_ids):
                delivered = self._flush(deadline)
                return pb.StepReply(
                    robot_id=robot,
                    step=req.step,
                    finished=True,
                    late_reports=[r for _f, r in delivered] + self._take_late(),
                    pending=len(self.outbox),
                )
            self._make(req.step)  # a frame that cannot be made is refused here
            self.refused.pop(req.step, None)
            delivered = self._flush(deadline)
            refused = self.refused.pop(req.step, None)
            if refused is not None:
                raise RequestError(f"descriptor refused frame {req.step}: {refused}", code=_code_of(refused))
            own = next((r for f, r in delivered if f == req.step), None)
            late = [r for f, r in delivered if f != req.step] + self._take_late()
            reply = pb.StepReply(
                robot_id=robot, step=req.step, queued=own is None, late_reports=late, pending=len(self.outbox)
            )
            if own is not None:
                reply.report.CopyFrom(own)
            return reply

    def _step_place(self, req: pb.StepRequest) -> pb.StepReply:
        """A dvpr step: the frame to the robot's place-owner, answered at once. Full-image
        frames do not go through the outbox: the dvpr lock-step is sequential, and an
        owner's answer depends on the order queries reached it (docs/vpr.md)."""
        robot = self.ctx.bus.robot
        if req.step >= len(self.source.frame_ids):
            return pb.StepReply(robot_id=robot, step=req.step, finished=True)
        with self.lock:
            try:
                report = self._send_place(req.step)
            except CallError as e:
                raise Unavailable(f"place-owner: {e}") from None
        return pb.StepReply(robot_id=robot, step=req.step, place=report)

    def _retry(self) -> None:
        """Send queued frames again in the background (a free replay, or between steps)."""
        while not self.ctx.stop.wait(self.retry_s):
            if not len(self.outbox) or not self.lock.acquire(blocking=False):
                continue
            try:
                delivered = self._flush(time.monotonic() + self.timeout_s)
                self.late += [r for _f, r in delivered]
                del self.late[:-LATE_REPORTS]  # a free replay reads them from the events instead
            except Exception:  # the retrier must keep going; the next round retries
                self.ctx.log.exception("sending queued frames failed")
            finally:
                self.lock.release()

    def pending(self) -> int:
        return len(self.outbox)

    def replay(self, req: pb.ReplayRequest) -> pb.ReplayReply:
        if not (math.isfinite(req.rate_hz) and req.rate_hz >= 0):
            raise InvalidArgument(f"rate_hz must be >= 0, got {req.rate_hz}")
        with self.lock:
            if self.replaying is not None and self.replaying.is_alive():
                raise Unavailable("a replay is already running")
            self.replaying = threading.Thread(target=self._replay, args=(req.rate_hz,), daemon=True)
            self.replaying.start()
        return pb.ReplayReply(robot_id=self.ctx.bus.robot, n_frames=len(self.source.frame_ids))

    def _replay(self, rate_hz: float) -> None:
        period = 1.0 / rate_hz if rate_hz > 0 else 0.0
        # Robots are not synchronised: each starts at its own phase of the period,
        # or all ten would query at the same instant, every time.
        bus = self.ctx.bus
        start = time.perf_counter() + period * bus.robot / bus.n_robots
        n = len(self.source.frame_ids)
        for t in range(n):
            if self.ctx.stop.is_set():
                return
            if period:
                delay = start + t * period - time.perf_counter()
                if delay > 0 and self.ctx.stop.wait(delay):
                    return
            with self.lock:
                try:
                    self._make(t)
                except RequestError as e:
                    self.ctx.log.warning("frame failed", extra={"fields": {"frame": t, "reason": str(e)}})
                    continue
                self._flush(time.monotonic() + self.timeout_s)
        self.ctx.log.info("replay finished", extra={"fields": {"frames": n, "waiting": len(self.outbox)}})

    def close(self) -> None:
        if self.replaying is not None:
            self.replaying.join(timeout=5.0)
