"""The descriptor service: turns its robot's constellations into queries.

Endpoints:

* ``process``: a :class:`Constellation` of this robot -> :class:`QueryReport`.
  The frame is stored in the robot's own verifier and, when it has at least
  ``min_objects`` objects, queried with the two-step protocol
  (:mod:`swarmrec.services.protocol`); its slices are stored by the shards.
  The best verified match at least ``loop_closure_min_score`` good (and, on
  the robot's own trajectory, more than ``exclusion`` frames back) becomes a
  loop closure, published on ``events/loop_closure/<robot>``; every report is
  published on ``events/query/<robot>``.
* ``loop_closures``: :class:`LoopClosuresRequest` -> :class:`LoopClosureList`,
  kept in ``<data_dir>/loop-closures.log`` across restarts.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Sequence

from swarmrec.core.presets import get_preset
from swarmrec.errors import WireError
from swarmrec.services import keys
from swarmrec.services.common import MAX_FRAME_INDEX, invalid, label_bounds_of, wire_error
from swarmrec.services.protocol import QueryPlan, two_step_query
from swarmrec.services.rpc import CallError
from swarmrec.services.runner import Endpoint, RequestContext, RequestError, ServiceContext
from swarmrec.services.storage import RecordLog
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import constellation_from_proto, encode

__all__ = ["Descriptor"]


class Descriptor:
    def __init__(self, ctx: ServiceContext) -> None:
        s = ctx.settings
        self.ctx = ctx
        self.preset = get_preset(s.preset)
        self.plan = QueryPlan(
            s.swarm, s.n_robots, label_bounds_of(s), s.n_labels, self.preset, self.preset.n_ret
        )
        self.lock = threading.Lock()
        path = s.data_dir / "loop-closures.log" if s.data_dir else None
        self.closure_log = RecordLog(path, fsync=s.fsync, log=ctx.log)
        self.closures = [pb.LoopClosure.FromString(r) for r in self.closure_log.records()]

    def endpoints(self) -> Sequence[Endpoint]:
        return [
            Endpoint("process", pb.Constellation, self.process),
            Endpoint("loop_closures", pb.LoopClosuresRequest, self.loop_closures),
        ]

    def member_info(self) -> pb.MemberInfo:
        return pb.MemberInfo()

    def process(self, msg: pb.Constellation, _ctx: RequestContext) -> pb.QueryReport:
        s = self.ctx.settings
        if msg.robot_id != s.robot:
            raise invalid(
                f"descriptor {s.robot} queries only its own robot's frames, got robot {msg.robot_id}"
            )
        if msg.frame_index >= MAX_FRAME_INDEX:
            raise invalid(f"frame index must be below {MAX_FRAME_INDEX}, got {msg.frame_index}")
        try:
            c = constellation_from_proto(msg, s.n_labels)
        except WireError as e:
            raise wire_error(e) from None
        t0 = time.perf_counter()
        caller = self.ctx.caller
        stored = caller.start(
            keys.endpoint(s.swarm, "verifier", s.robot, "store"), msg, target_robot=s.robot, endpoint="store"
        )
        if len(c) >= self.preset.min_objects:
            report = two_step_query(
                caller,
                self.plan,
                c,
                msg,
                query_id=0,
                read_only=False,
                self_robot=s.robot,
            )
        else:
            report = pb.QueryReport(robot_id=s.robot, frame_index=msg.frame_index, queried=False)
        try:
            stored.result(pb.StoreReply)
        except CallError as e:
            # Without its own verifier the robot cannot answer for this frame later.
            raise RequestError(
                pb.ErrorCode.ERROR_CODE_UNAVAILABLE, f"own verifier did not store the frame: {e}"
            ) from None
        report.duration_us = min(int((time.perf_counter() - t0) * 1e6), 2**32 - 1)
        self.ctx.metrics.query_seconds.observe(report.duration_us / 1e6)
        if report.queried:
            self._loop_closure(report)
        # Every frame's report, queried or not, so a listener can count frames.
        self.ctx.publish(keys.event(s.swarm, "query", s.robot), report)
        return report

    def _loop_closure(self, report: pb.QueryReport) -> None:
        s = self.ctx.settings
        for m in report.matches:  # best first
            if m.score < s.loop_closure_min_score:
                return
            own_recent = (
                m.match_robot_id == s.robot
                and abs(m.match_frame_index - report.frame_index) <= self.preset.exclusion
            )
            if own_recent:
                continue
            closure = pb.LoopClosure(
                query_robot_id=s.robot,
                query_frame_index=report.frame_index,
                match_robot_id=m.match_robot_id,
                match_frame_index=m.match_frame_index,
                score=m.score,
                semantic_score=m.semantic_score,
                n_matched=m.n_matched,
                unix_time_ns=time.time_ns(),
            )
            with self.lock:
                self.closure_log.append(encode(closure))
                self.closures.append(closure)
            self.ctx.metrics.loop_closures.inc()
            self.ctx.publish(keys.event(s.swarm, "loop_closure", s.robot), closure)
            return

    def loop_closures(self, req: pb.LoopClosuresRequest, _ctx: RequestContext) -> pb.LoopClosureList:
        if math.isnan(req.min_score):
            # Every comparison with NaN is false: the answer would be an empty list, read as "none found".
            raise invalid("min_score must be a number, got NaN")
        with self.lock:
            found = [c for c in self.closures if c.score >= req.min_score]
        return pb.LoopClosureList(robot_id=self.ctx.settings.robot, loop_closures=found)

    def close(self) -> None:
        self.closure_log.close()
