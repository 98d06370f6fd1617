"""The index-shard service: one label range of the swarm's descriptor index.

Robot k's shard owns label range k. Endpoint ``query`` takes a
:class:`PartialQuery`, answers with the ``n_ret`` best stored frames
(:class:`CandidatesReply`) and, unless the query is read-only, stores the
query's slice; ``lookup`` is the same search that never stores (clients and
the gateway use it, so the router's access control can keep them from storing).
Stored slices are appended to its record log (``<data_dir>/index-shard.log``)
before the answer goes out, and replayed on start.

Stores are idempotent per (robot, frame): the same slice again is answered as
before and nothing is appended; another slice for a stored frame is refused
(ALREADY_EXISTS) before anything is computed. The index keeps one row per
stored frame (:class:`~swarmrec.core.index.RangeIndex`), so memory and the
work of a query follow what is stored, not the frame indices requests claim;
counts past a frame's bounds (``max_objects_per_label``,
``max_objects_per_frame``) are refused (TOO_LARGE).
"""

from __future__ import annotations

import threading

import numpy as np

from swarmrec.core.index import RangeIndex
from swarmrec.core.presets import get_preset
from swarmrec.errors import AlreadyExists, InvalidArgument, LimitExceededError
from swarmrec.runtime import Endpoint, RequestContext, ServiceBase, ServiceContext
from swarmrec.services.limits import MAX_FRAME_GAP, MAX_FRAME_INDEX, MAX_N_RET
from swarmrec.services.metrics import ShardMetrics
from swarmrec.services.settings import PlaceSettings
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import (
    Candidate,
    candidates_to_proto,
    check_fields,
    encode,
    partial_descriptor_from_proto,
)

__all__ = ["IndexShard"]


class IndexShard(ServiceBase):
    def __init__(self, ctx: ServiceContext) -> None:
        self.ctx = ctx
        self.bus = ctx.bus
        self.places = ctx.settings(PlaceSettings)
        self.metrics = ctx.metric_set(ShardMetrics)
        bounds = self.places.bounds(self.bus)
        self.lo, self.hi = int(bounds[self.bus.robot]), int(bounds[self.bus.robot + 1])
        self.index = RangeIndex(self.lo, self.hi, self.bus.n_robots)
        self.lock = threading.Lock()
        self.n_ret = get_preset(self.places.preset).n_ret
        self.limits = self.places.frame_limits()
        self.store = ctx.open_log("index-shard")
        restored = skipped = 0
        for record in self.store.records():
            msg = pb.PartialDescriptor.FromString(record)
            try:
                counts = partial_descriptor_from_proto(msg, self.places.n_labels, self.limits).counts
            except LimitExceededError as e:
                # Stored before the bounds existed (or were lowered); skipped, not deleted.
                skipped += 1
                fields = {"robot": msg.robot_id, "frame": msg.frame_index, "reason": str(e)}
                ctx.log.warning("stored slice over the bounds skipped", extra={"fields": fields})
                continue
            # A log written before stores were idempotent may hold a frame twice: the last wins.
            self.index.add(msg.robot_id, msg.frame_index, counts)
            restored += 1
        self.metrics.stored_descriptors.set(self.index.size)
        fields = {
            "label_lo": self.lo,
            "label_hi": self.hi,
            "records": restored,
            "skipped": skipped,
            "stored": self.index.size,
        }
        ctx.log.info("index loaded", extra={"fields": fields})

    def member_info(self) -> pb.MemberInfo:
        return pb.MemberInfo(
            label_lo=self.lo, label_hi=self.hi, stored_items=self.index.size, n_labels=self.places.n_labels
        )

    def query(self, req: pb.PartialQuery, _ctx: RequestContext) -> pb.CandidatesReply:
        check_fields(req, "descriptor")
        if req.n_ret > MAX_N_RET:
            raise InvalidArgument(f"n_ret must be at most {MAX_N_RET}, got {req.n_ret}")
        n_ret = req.n_ret or self.n_ret
        desc = req.descriptor
        if desc.robot_id >= self.bus.n_robots:
            raise InvalidArgument(f"robot {desc.robot_id} is not in this swarm of {self.bus.n_robots} robots")
        if desc.frame_index >= MAX_FRAME_INDEX or desc.query_step >= MAX_FRAME_INDEX:
            raise InvalidArgument(f"frame index and query step must be below {MAX_FRAME_INDEX}")
        part = partial_descriptor_from_proto(desc, self.places.n_labels, self.limits)
        if (part.lo, part.hi) != (self.lo, self.hi):
            raise InvalidArgument(
                f"this shard owns labels [{self.lo}, {self.hi}), not [{part.lo}, {part.hi})"
            )
        if not part.counts.any():
            raise InvalidArgument("partial descriptor has no labels; send only non-empty slices")
        # A read-only lookup (a client's) searches everything even in a lock-step swarm.
        lockstep = self.places.lockstep and not req.read_only
        before = (desc.query_step or desc.frame_index) if lockstep else None
        with self.lock:
            if desc.frame_index > self.index.frames_of(desc.robot_id) + MAX_FRAME_GAP or (
                before is not None and before > self.index.frames + MAX_FRAME_GAP
            ):
                raise InvalidArgument(
                    f"frame index or step more than {MAX_FRAME_GAP} frames past what is stored"
                )
            stored = None if req.read_only else self.index.get(desc.robot_id, desc.frame_index)
            if stored is not None and not np.array_equal(stored, part.counts):
                raise AlreadyExists(
                    f"frame {desc.frame_index} of robot {desc.robot_id} is already stored here with "
                    "another slice; stores are idempotent (the same slice again is accepted)"
                )
            found = self.index.candidates(part.counts, n_ret, before=before)
            if not req.read_only and stored is None:
                # Stored before the answer leaves: an acknowledged frame survives a crash.
                self.store.append(encode(desc))
                self.index.add(desc.robot_id, desc.frame_index, part.counts)
                self.metrics.stored_descriptors.set(self.index.size)
        self.metrics.partial_queries.inc()
        return candidates_to_proto(
            req.query_id,
            self.lo,
            self.hi,
            (Candidate(c.robot, c.frame, c.score) for c in found),
            include_scores=req.include_scores,
        )

    def lookup(self, req: pb.PartialQuery, ctx: RequestContext) -> pb.CandidatesReply:
        if not req.read_only:
            raise InvalidArgument("lookup never stores: send read_only = true (descriptors use query)")
        return self.query(req, ctx)

    ENDPOINTS = (
        Endpoint(
            "query",
            pb.PartialQuery,
            pb.CandidatesReply,
            query,
            "candidates for a descriptor slice; stored unless read_only",
        ),
        Endpoint(
            "lookup",
            pb.PartialQuery,
            pb.CandidatesReply,
            lookup,
            "candidates for a descriptor slice, never stored (read_only must be set): clients' endpoint",
        ),
    )
