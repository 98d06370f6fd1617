"""The descriptor service: turns its robot's constellations into queries.

Endpoints:

* ``process``: a :class:`Constellation` of this robot -> :class:`QueryReport`.
  The frame is stored in the robot's own verifier first and, when it has at
  least ``min_objects`` objects, then queried with the two-step protocol
  (:mod:`swarmrec.services.protocol`); its slices are stored by every owner and
  learner of their label groups (the index placement, :mod:`swarmrec.services.routing`).
  A slice some shard did not acknowledge is kept on disk and retried in the
  background until every shard that must hold it has (:mod:`swarmrec.services.pending`);
  with ``pending_capacity`` slices waiting, new frames are refused (UNAVAILABLE).
  The verifier is the authority on what frame ``t`` of this robot is: a frame
  it refuses (ALREADY_EXISTS: stored with other content) is refused here before
  any shard stores a slice of it, and the same frame again is processed again
  without storing anything twice (a loop closure is kept once per frame).
  The best verified match at least ``loop_closure_min_score`` good (and, on
  the robot's own trajectory, more than ``exclusion`` frames back) becomes a
  loop closure (:class:`swarmrec.core.funnel.ClosureRule`, the one rule),
  published on ``events/loop_closure/<robot>``; every report, with where each
  candidate stopped in the loop-closure funnel, is published on
  ``events/query/<robot>`` and counted in ``swarmrec_funnel_candidates_total``.
* ``loop_closures``: :class:`LoopClosuresRequest` -> :class:`LoopClosureList`,
  kept in its record log (``<data_dir>/loop-closures.log``) across restarts.
* ``explain``: :class:`ExplainRequest` -> :class:`ExplainReply`, the query
  report of one frame, from the last ``explain_reports`` kept in memory (a frame
  older than those is answered AGED_OUT; the memory is lost on restart).
"""

from __future__ import annotations

import math
import threading
import time
from collections import OrderedDict

from swarmrec.core.funnel import ClosureRule, Reason, settle
from swarmrec.core.placement import groups_from_bounds
from swarmrec.core.presets import get_preset
from swarmrec.errors import AlreadyExists, CallError, ErrorCode, InvalidArgument, RemoteError, Unavailable
from swarmrec.runtime import Endpoint, RequestContext, ServiceBase, ServiceContext, keys
from swarmrec.services.limits import MAX_FRAME_INDEX
from swarmrec.services.metrics import DescriptorMetrics
from swarmrec.services.pending import PendingStores
from swarmrec.services.protocol import QueryPlan, two_step_query
from swarmrec.services.routing import LiveShards, Routing
from swarmrec.services.settings import ExplainSettings, IndexSettings, PlaceSettings
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import (
    check_fields,
    constellation_from_proto,
    encode,
    outcomes_from_proto,
    outcomes_to_proto,
)

__all__ = ["Descriptor"]


class Descriptor(ServiceBase):
    def __init__(self, ctx: ServiceContext) -> None:
        self.ctx = ctx
        self.bus = ctx.bus
        self.places = ctx.settings(PlaceSettings)
        self.metrics = ctx.metric_set(DescriptorMetrics)
        self.preset = get_preset(self.places.preset)
        self.index = ctx.settings(IndexSettings)
        bounds = self.places.bounds(self.bus)
        self.routing = Routing(
            self.bus.swarm,
            self.places.n_labels,
            groups_from_bounds(bounds.tolist()),
            replicas=self.index.replicas,
            n_shards=self.bus.n_robots,
            live=LiveShards(ctx.session, self.bus.swarm),
            suspect_s=self.index.suspect_s,
            on_refresh=self.metrics.placement_refreshes.inc,
        )
        self.plan = QueryPlan(
            self.bus.swarm,
            self.bus.n_robots,
            bounds,
            self.places.n_labels,
            self.preset,
            self.routing,
            self.preset.n_ret,
        )
        self.pending = PendingStores(ctx.open_log("pending-stores"), self.index.pending_capacity)
        self.metrics.pending_stores.set(len(self.pending))
        # Passes over the pending stores finished (PendingStores.next_batch), said in MemberInfo.
        self.pending_passes = 0
        self._retrier: threading.Thread | None = None
        self.rule = ClosureRule(self.places.loop_closure_min_score, self.preset.exclusion)
        self.lock = threading.Lock()
        self.closure_log = ctx.open_log("loop-closures")
        self.closures = [pb.LoopClosure.FromString(r) for r in self.closure_log.records()]
        # Query frames that have their loop closure: a frame processed again adds none.
        self.closed = {c.query_frame_index for c in self.closures}
        # The last reports, serialized (a few hundred bytes each), for explain; and one bit
        # per frame index processed since the start (128 KiB for every index a frame may
        # have), so a frame that aged out is told from one never seen.
        self.reports_kept = ctx.settings(ExplainSettings).explain_reports
        self.reports: OrderedDict[int, bytes] = OrderedDict()
        self.seen = bytearray(MAX_FRAME_INDEX // 8)

    def member_info(self) -> pb.MemberInfo:
        return pb.MemberInfo(
            n_labels=self.places.n_labels,
            pending_items=len(self.pending),
            pending_passes=self.pending_passes,
        )

    def serving(self, ready: bool) -> None:
        if ready and self._retrier is None:
            # Learn the swarm's placement (a descriptor joining a running swarm starts at 0).
            self.routing.refresh(self.ctx.caller)
            self._retrier = threading.Thread(target=self._retry_pending, name="pending-stores", daemon=True)
            self._retrier.start()

    def close(self) -> None:
        self.routing.close()

    def _retry_pending(self) -> None:
        """Send every waiting slice to every shard that must hold it under the current
        placement, until all of them have acknowledged it."""
        interval = self.index.retry_interval_s
        while not self.ctx.stop.wait(interval):
            try:
                self._retry_once()
            except Exception:
                self.ctx.log.exception("retrying pending stores failed")

    def _retry_once(self, batch: int = 256) -> None:
        waiting, ends_pass = self.pending.next_batch(batch)
        if not waiting:
            self.pending_passes += ends_pass
            return
        placement = self.routing.placement
        caller = self.ctx.caller
        sent = []
        for desc in waiting:
            g = placement.group_of_range(desc.label_lo, desc.label_hi)
            if g is None:
                self.pending.done(desc)  # of groups the swarm no longer has: nowhere to store it
                continue
            msg = pb.ShardStore(descriptor=desc, placement_version=placement.version)
            asked = [
                caller.start(
                    keys.endpoint(self.bus.swarm, "index-shard", shard, "store"),
                    msg,
                    target_robot=shard,
                    endpoint="shard_store",
                )
                for shard in placement.store_targets(g)
            ]
            sent.append((desc, list(zip(placement.store_targets(g), asked, strict=True))))
        stale: set[int] = set()  # the shards that refused as routed with another placement
        for desc, asked_shards in sent:
            acked = True
            for shard, pending in asked_shards:
                self.metrics.store_retries.inc()
                try:
                    pending.result(pb.StoreReply)
                except RemoteError as e:
                    if e.code == ErrorCode.FAILED_PRECONDITION:
                        stale.add(shard)
                    acked = acked and e.code == ErrorCode.ALREADY_EXISTS
                except CallError:
                    acked = False
            if acked:
                self.pending.done(desc)
        if stale:
            self.routing.refresh(caller, from_shards=stale, routed=placement.version)
        self.pending_passes += ends_pass
        self.metrics.pending_stores.set(len(self.pending))

    def process(self, msg: pb.Constellation, _ctx: RequestContext) -> pb.QueryReport:
        check_fields(msg, "robot_id", "frame_index")
        robot = self.bus.robot
        if msg.robot_id != robot:
            raise InvalidArgument(
                f"descriptor {robot} queries only its own robot's frames, got robot {msg.robot_id}"
            )
        if msg.frame_index >= MAX_FRAME_INDEX:
            raise InvalidArgument(f"frame index must be below {MAX_FRAME_INDEX}, got {msg.frame_index}")
        c = constellation_from_proto(msg, self.places.n_labels, self.places.frame_limits())
        if self.pending.room() < len(self.routing.groups):
            raise Unavailable(
                f"{len(self.pending)} stores are waiting for index shards to acknowledge them: "
                "refusing new frames until they are (the shards are gone or unreachable)"
            )
        t0 = time.perf_counter()
        caller = self.ctx.caller
        try:
            caller.call(
                keys.endpoint(self.bus.swarm, "verifier", robot, "store"),
                msg,
                pb.StoreReply,
                target_robot=robot,
                endpoint="store",
            )
        except RemoteError as e:
            self.metrics.frames.labels("not_stored").inc()
            if e.code == ErrorCode.ALREADY_EXISTS:
                raise AlreadyExists(f"frame {msg.frame_index}: {e.message}") from None
            raise Unavailable(f"own verifier did not store the frame: {e}") from None
        except CallError as e:
            self.metrics.frames.labels("not_stored").inc()
            # Without its own verifier the robot cannot answer for this frame later.
            raise Unavailable(f"own verifier did not store the frame: {e}") from None
        if len(c) >= self.preset.min_objects:
            report = two_step_query(
                caller,
                self.plan,
                c,
                msg,
                query_id=0,
                read_only=False,
                self_robot=robot,
                on_unstored=self.pending.add,
            )
            self.metrics.pending_stores.set(len(self.pending))
        else:
            report = pb.QueryReport(robot_id=robot, frame_index=msg.frame_index, queried=False)
        report.n_objects = len(c)
        report.duration_us = min(int((time.perf_counter() - t0) * 1e6), 2**32 - 1)
        self.metrics.query_seconds.observe(report.duration_us / 1e6)
        self.metrics.frames.labels("queried" if report.queried else "too_few_objects").inc()
        if report.queried:
            self._loop_closure(report)
        for o in report.candidates:
            reason = Reason.of(o.reason)
            self.metrics.funnel.labels(reason.stage.label, reason.label).inc()
        self._remember(report)
        # Every frame's report, queried or not, so a listener can count frames.
        self.ctx.publish(keys.event(self.bus.swarm, "query", robot), report)
        return report

    def _loop_closure(self, report: pb.QueryReport) -> None:
        """Keep and publish the loop closure the rule takes from the report's matches (if
        any), and put the rule's verdict on each matched candidate of the report's funnel."""
        robot = self.bus.robot
        matches = [(m.match_robot_id, m.match_frame_index, m.score) for m in report.matches]
        closure = None
        with self.lock:
            # Under the lock: a frame processed twice at once still keeps one closure.
            verdicts = self.rule.verdicts(
                robot, report.frame_index, matches, already_closed=report.frame_index in self.closed
            )
            for m, verdict in zip(report.matches, verdicts, strict=True):
                if verdict == Reason.ACCEPTED:
                    closure = pb.LoopClosure(
                        query_robot_id=robot,
                        query_frame_index=report.frame_index,
                        match_robot_id=m.match_robot_id,
                        match_frame_index=m.match_frame_index,
                        score=m.score,
                        semantic_score=m.semantic_score,
                        n_matched=m.n_matched,
                        unix_time_ns=time.time_ns(),
                    )
                    self.closure_log.append(encode(closure))
                    self.closures.append(closure)
                    self.closed.add(report.frame_index)
        settled = settle(
            outcomes_from_proto(report),
            {(r, f): v for (r, f, _score), v in zip(matches, verdicts, strict=True)},
        )
        del report.candidates[:]
        report.candidates.extend(outcomes_to_proto(settled))
        if closure is not None:
            self.metrics.loop_closures.inc()
            self.ctx.publish(keys.event(self.bus.swarm, "loop_closure", robot), closure)

    def _remember(self, report: pb.QueryReport) -> None:
        f = report.frame_index
        data = report.SerializeToString() if self.reports_kept else b""
        with self.lock:
            self.seen[f >> 3] |= 1 << (f & 7)
            if not self.reports_kept:
                return
            self.reports[f] = data
            self.reports.move_to_end(f)
            while len(self.reports) > self.reports_kept:
                self.reports.popitem(last=False)

    def explain(self, req: pb.ExplainRequest, _ctx: RequestContext) -> pb.ExplainReply:
        check_fields(req, "frame_index")
        f = req.frame_index
        if f >= MAX_FRAME_INDEX:
            raise InvalidArgument(f"frame index must be below {MAX_FRAME_INDEX}, got {f}")
        reply = pb.ExplainReply(
            robot_id=self.bus.robot,
            reports_kept=self.reports_kept,
            loop_closure_min_score=self.rule.min_score,
            exclusion=self.rule.exclusion,
            min_objects=self.preset.min_objects,
            n_ret=self.preset.n_ret,
            n_fq=self.preset.n_fq,
        )
        with self.lock:
            data = self.reports.get(f)
            seen = bool(self.seen[f >> 3] & (1 << (f & 7)))
            reply.reports_held = len(self.reports)
            if self.reports:
                reply.oldest_frame_index = next(iter(self.reports))
                reply.newest_frame_index = next(reversed(self.reports))
        if data is not None:
            reply.status = pb.ReportStatus.REPORT_STATUS_HELD
            reply.report.ParseFromString(data)
        elif seen:
            reply.status = pb.ReportStatus.REPORT_STATUS_AGED_OUT
        else:
            reply.status = pb.ReportStatus.REPORT_STATUS_NOT_SEEN
        return reply

    def loop_closures(self, req: pb.LoopClosuresRequest, _ctx: RequestContext) -> pb.LoopClosureList:
        check_fields(req)
        if not math.isfinite(req.min_score):
            # NaN compares false with everything and no score reaches inf: the answer would be
            # an empty list, indistinguishable from "none found".
            raise InvalidArgument(f"min_score must be a finite number, got {req.min_score}")
        with self.lock:
            found = [c for c in self.closures if c.score >= req.min_score]
        return pb.LoopClosureList(robot_id=self.bus.robot, loop_closures=found)

    ENDPOINTS = (
        Endpoint(
            "process", pb.Constellation, pb.QueryReport, process, "store and query one of this robot's frames"
        ),
        Endpoint(
            "loop_closures",
            pb.LoopClosuresRequest,
            pb.LoopClosureList,
            loop_closures,
            "the loop closures found so far",
        ),
        Endpoint(
            "explain",
            pb.ExplainRequest,
            pb.ExplainReply,
            explain,
            "the query report of one frame, with where each candidate stopped (the last explain_reports)",
        ),
    )
