"""The verifier service: holds its robot's constellations and verifies queries
against them geometrically (data association, Eq. 2-7).

Endpoints:

* ``store``: a :class:`Constellation` of this robot (sent by its descriptor
  service) -> :class:`StoreReply`; appended to its record log
  (``<data_dir>/verifier.log``) before the answer, replayed on start. Stores
  are idempotent: the same frame again is accepted and answered as before
  (nothing is appended), a frame index already stored with other content is
  refused (ALREADY_EXISTS).
* ``verify``: a :class:`VerifyRequest` (the query constellation and the
  candidate frames) -> :class:`VerifyReply`, every candidate with a score > 0,
  best first.

A frame's association costs about (objects)^2 x labels, so frames with more
objects than ``max_objects_per_frame`` (or of one label than
``max_objects_per_label``) are refused on arrival, and a verify request that
would check more than ``verify_max_frames`` frames or compare more than
``verify_max_object_pairs`` object pairs is refused before any work (TOO_LARGE).
A record of the log over today's bounds (stored by an older version) is
skipped on start with a warning, not served.
"""

from __future__ import annotations

import math
import threading

import numpy as np

from swarmrec.core.association import FrameTable, build_table
from swarmrec.core.presets import get_preset
from swarmrec.core.types import Constellation
from swarmrec.core.verification import verify, verify_tables
from swarmrec.errors import AlreadyExists, InvalidArgument, LimitExceededError
from swarmrec.runtime import Endpoint, RequestContext, ServiceBase, ServiceContext
from swarmrec.services.limits import MAX_FRAME_INDEX
from swarmrec.services.metrics import VerifierMetrics
from swarmrec.services.settings import PlaceSettings
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import check_fields, constellation_from_proto, encode, verify_match_to_proto

__all__ = ["Verifier"]


class Verifier(ServiceBase):
    def __init__(self, ctx: ServiceContext) -> None:
        self.ctx = ctx
        self.bus = ctx.bus
        self.places = ctx.settings(PlaceSettings)
        self.metrics = ctx.metric_set(VerifierMetrics)
        self.preset = get_preset(self.places.preset)
        self.limits = self.places.frame_limits()
        self.frames: dict[int, Constellation] = {}
        # Each frame packed for the association kernels once, when stored (verify compares
        # one query with many frames: packing them per request cost ~4/5 of its time).
        self.tables: dict[int, FrameTable] = {}
        self.frame_ids: dict[int, str] = {}
        self.lock = threading.Lock()
        self.store_log = ctx.open_log("verifier")
        skipped = 0
        for record in self.store_log.records():
            msg = pb.Constellation.FromString(record)
            try:
                c = constellation_from_proto(msg, self.places.n_labels, self.limits)
            except LimitExceededError as e:
                # Stored before the bounds existed (or were lowered): serving it would
                # slow every later verify. Skipped, not deleted: raising the bound brings it back.
                skipped += 1
                fields = {"frame": msg.frame_index, "reason": str(e)}
                ctx.log.warning("stored frame over the bounds skipped", extra={"fields": fields})
                continue
            # A log written before stores were idempotent may hold a frame twice: the last wins.
            self.frames[msg.frame_index] = c
            self.tables[msg.frame_index] = build_table([c], self.places.n_labels)
            self.frame_ids[msg.frame_index] = msg.frame_id
        self.metrics.stored_frames.set(len(self.frames))
        # Load the association kernels now (numba compiles or reads its cache on
        # first use), so the first query does not pay hundreds of milliseconds.
        probe = Constellation(np.zeros(3, np.int64), np.eye(3))
        verify(probe, (0, 0), self.bus.robot, [(0, probe)], 1, self.preset)
        ctx.log.info("frames loaded", extra={"fields": {"stored": len(self.frames), "skipped": skipped}})

    def member_info(self) -> pb.MemberInfo:
        with self.lock:
            return pb.MemberInfo(stored_items=len(self.frames), n_labels=self.places.n_labels)

    def _constellation(self, msg: pb.Constellation) -> Constellation:
        n_robots = self.bus.n_robots
        if msg.robot_id >= n_robots:
            raise InvalidArgument(f"robot {msg.robot_id} is not in this swarm of {n_robots} robots")
        if msg.frame_index >= MAX_FRAME_INDEX:
            raise InvalidArgument(f"frame index must be below {MAX_FRAME_INDEX}, got {msg.frame_index}")
        return constellation_from_proto(msg, self.places.n_labels, self.limits)

    def store(self, msg: pb.Constellation, _ctx: RequestContext) -> pb.StoreReply:
        check_fields(msg, "robot_id", "frame_index")
        own = self.bus.robot
        if msg.robot_id != own:
            raise InvalidArgument(
                f"verifier {own} stores only its own robot's frames, got robot {msg.robot_id}"
            )
        c = self._constellation(msg)
        f = msg.frame_index
        table = build_table([c], self.places.n_labels)
        with self.lock:
            old = self.frames.get(f)
            if old is None:
                self.store_log.append(encode(msg))
                self.frames[f] = c
                self.tables[f] = table
                self.frame_ids[f] = msg.frame_id
            elif not (_same_objects(old, c) and self.frame_ids[f] == msg.frame_id):
                # Peers may already have matched against the stored frame: replacing it would
                # change answers behind their back (and an empty payload would wipe it).
                raise AlreadyExists(
                    f"frame {f} of robot {own} is already stored with other content; stores are "
                    "idempotent (the same frame again is accepted), a changed frame needs a new index"
                )
            n = len(self.frames)
        self.metrics.stored_frames.set(n)
        return pb.StoreReply(stored_frames=n)

    def _frames_to_check(
        self, req: pb.VerifyRequest, n_query: int, min_common: int
    ) -> list[tuple[int, FrameTable]]:
        """The stored frames a verify request asks for (under the lock), within the bounds."""
        max_frames = self.places.verify_max_frames
        if req.candidate_frame_indices:
            asked = len(req.candidate_frame_indices)
            if asked > max_frames:
                raise LimitExceededError("candidate frames to verify", asked, max_frames, "verify_max_frames")
            wanted = sorted(set(req.candidate_frame_indices))
            frames = [(f, self.tables[f]) for f in wanted if f in self.tables]
            missing = len(wanted) - len(frames)
            if missing:
                self.ctx.log.warning(
                    "asked to verify frames it does not hold", extra={"fields": {"missing": missing}}
                )
        else:
            frames = [(f, self.tables[f]) for f, c in self.frames.items() if len(c) >= min_common]
            if len(frames) > max_frames:
                raise LimitExceededError(
                    "stored frames to verify (no candidate list: all of them)", len(frames), max_frames,
                    "verify_max_frames",
                )  # fmt: skip
        pairs = n_query * sum(t.n_objects(0) for _f, t in frames)
        if pairs > self.places.verify_max_object_pairs:
            raise LimitExceededError(
                "object pairs to compare",
                pairs,
                self.places.verify_max_object_pairs,
                "verify_max_object_pairs",
            )
        return frames

    def verify(self, req: pb.VerifyRequest, ctx: RequestContext) -> pb.VerifyReply:
        # The query's robot and frame may be absent: they only order the association's
        # arguments, as (robot, frame) against the stored frame's. A descriptor leaves both
        # out of a request to another robot's verifier (the robots differ, so the frame
        # cannot matter): the query's robot is then the caller's; otherwise 0.
        check_fields(req, "query")
        robot = req.query.robot_id
        if not req.query.HasField("robot_id") and ctx.caller_robot not in (None, self.bus.robot):
            robot = ctx.caller_robot
        query = self._constellation(req.query)
        preset = self.preset
        if req.HasField("distance_threshold_m"):
            d = req.distance_threshold_m
            if not (math.isfinite(d) and d > 0):
                raise InvalidArgument(f"distance_threshold_m must be a positive number, got {d}")
            preset = preset.with_(d=float(d))
        with self.lock:
            frames = self._frames_to_check(req, len(query), preset.min_common)
        results = verify_tables(
            build_table([query], self.places.n_labels),
            (robot, req.query.frame_index),
            self.bus.robot,
            frames,
            preset,
        )
        results = [m for m in results if m.score > 0]
        if req.max_matches:
            results = results[: req.max_matches]
        reply = pb.VerifyReply(query_id=req.query_id, robot_id=self.bus.robot)
        for m in results:
            pairs = m.pairs if req.include_pairs else None
            reply.matches.append(
                verify_match_to_proto(m.frame, m.pairs.shape[0], m.n_common, m.n_union, pairs)
            )
        return reply

    ENDPOINTS = (
        Endpoint("store", pb.Constellation, pb.StoreReply, store, "keep one of this robot's frames"),
        Endpoint(
            "verify", pb.VerifyRequest, pb.VerifyReply, verify, "score candidate frames against a query"
        ),
    )


def _same_objects(a: Constellation, b: Constellation) -> bool:
    """The same objects in the same order at the same positions (bit for bit)."""
    return np.array_equal(a.labels, b.labels) and np.array_equal(a.positions, b.positions)
