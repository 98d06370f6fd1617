"""The index-shard service: one label range of the swarm's descriptor index.

Robot k's shard owns label range k. Endpoint ``query`` takes a
:class:`PartialQuery`, answers with the ``n_ret`` best stored frames
(:class:`CandidatesReply`) and, unless the query is read-only, stores the
query's slice. Stored slices are appended to ``<data_dir>/index-shard.log``
before the answer goes out, and replayed on start.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence

from swarmrec.core.index import RangeIndex
from swarmrec.core.presets import get_preset
from swarmrec.errors import WireError
from swarmrec.services.common import (
    MAX_FRAME_GAP,
    MAX_FRAME_INDEX,
    MAX_N_RET,
    invalid,
    label_bounds_of,
    wire_error,
)
from swarmrec.services.runner import Endpoint, RequestContext, ServiceContext
from swarmrec.services.storage import RecordLog
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import Candidate, candidates_to_proto, encode, partial_descriptor_from_proto

__all__ = ["IndexShard"]


class IndexShard:
    def __init__(self, ctx: ServiceContext) -> None:
        s = ctx.settings
        self.ctx = ctx
        bounds = label_bounds_of(s)
        self.lo, self.hi = int(bounds[s.robot]), int(bounds[s.robot + 1])
        self.index = RangeIndex(self.lo, self.hi, s.n_robots)
        self.lock = threading.Lock()
        self.n_ret = get_preset(s.preset).n_ret
        path = s.data_dir / "index-shard.log" if s.data_dir else None
        self.store = RecordLog(path, fsync=s.fsync, log=ctx.log)
        restored = 0
        for record in self.store.records():
            msg = pb.PartialDescriptor.FromString(record)
            self.index.add(
                msg.robot_id, msg.frame_index, partial_descriptor_from_proto(msg, s.n_labels).counts
            )
            restored += 1
        ctx.metrics.stored_descriptors.set(self.index.size)
        ctx.log.info(
            "index loaded",
            extra={
                "fields": {
                    "label_lo": self.lo,
                    "label_hi": self.hi,
                    "records": restored,
                    "stored": self.index.size,
                }
            },
        )

    def endpoints(self) -> Sequence[Endpoint]:
        return [Endpoint("query", pb.PartialQuery, self.query)]

    def member_info(self) -> pb.MemberInfo:
        return pb.MemberInfo(label_lo=self.lo, label_hi=self.hi, stored_items=self.index.size)

    def query(self, req: pb.PartialQuery, _ctx: RequestContext) -> pb.CandidatesReply:
        s = self.ctx.settings
        if not req.HasField("descriptor"):
            raise invalid("partial query without a descriptor")
        if req.n_ret > MAX_N_RET:
            raise invalid(f"n_ret must be at most {MAX_N_RET}, got {req.n_ret}")
        n_ret = req.n_ret or self.n_ret
        desc = req.descriptor
        if desc.robot_id >= s.n_robots:
            raise invalid(f"robot {desc.robot_id} is not in this swarm of {s.n_robots} robots")
        if desc.frame_index >= MAX_FRAME_INDEX or desc.query_step >= MAX_FRAME_INDEX:
            raise invalid(f"frame index and query step must be below {MAX_FRAME_INDEX}")
        try:
            part = partial_descriptor_from_proto(desc, s.n_labels)
        except WireError as e:
            raise wire_error(e) from None
        if (part.lo, part.hi) != (self.lo, self.hi):
            raise invalid(f"this shard owns labels [{self.lo}, {self.hi}), not [{part.lo}, {part.hi})")
        if not part.counts.any():
            raise invalid("partial descriptor has no labels; send only non-empty slices")
        # A read-only lookup (a client's) searches everything even in a lock-step swarm.
        before = (desc.query_step or desc.frame_index) if s.lockstep and not req.read_only else None
        with self.lock:
            if desc.frame_index > self.index.frames_of(desc.robot_id) + MAX_FRAME_GAP or (
                before is not None and before > self.index.frames + MAX_FRAME_GAP
            ):
                raise invalid(f"frame index or step more than {MAX_FRAME_GAP} frames past what is stored")
            found = self.index.candidates(part.counts, n_ret, before=before)
            if not req.read_only:
                # Stored before the answer leaves: an acknowledged frame survives a crash.
                self.store.append(encode(desc))
                self.index.add(desc.robot_id, desc.frame_index, part.counts)
                self.ctx.metrics.stored_descriptors.set(self.index.size)
        self.ctx.metrics.shard_partial_queries.inc()
        return candidates_to_proto(
            req.query_id,
            self.lo,
            self.hi,
            (Candidate(c.robot, c.frame, c.score) for c in found),
            include_scores=req.include_scores,
        )

    def close(self) -> None:
        self.store.close()
