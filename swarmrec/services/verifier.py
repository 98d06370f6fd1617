"""The verifier service: holds its robot's constellations and verifies queries
against them geometrically (data association, Eq. 2-7).

Endpoints:

* ``store``: a :class:`Constellation` of this robot (sent by its descriptor
  service) -> :class:`StoreReply`; appended to its record log
  (``<data_dir>/verifier.log``) before the answer, replayed on start.
* ``verify``: a :class:`VerifyRequest` (the query constellation and the
  candidate frames) -> :class:`VerifyReply`, every candidate with a score > 0,
  best first.
"""

from __future__ import annotations

import math
import threading

import numpy as np

from swarmrec.core.presets import get_preset
from swarmrec.core.types import Constellation
from swarmrec.core.verification import verify
from swarmrec.errors import InvalidArgument
from swarmrec.runtime import Endpoint, RequestContext, ServiceBase, ServiceContext
from swarmrec.services.limits import MAX_FRAME_INDEX
from swarmrec.services.metrics import VerifierMetrics
from swarmrec.services.settings import PlaceSettings
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import constellation_from_proto, encode, verify_match_to_proto

__all__ = ["Verifier"]


class Verifier(ServiceBase):
    def __init__(self, ctx: ServiceContext) -> None:
        self.ctx = ctx
        self.bus = ctx.bus
        self.places = ctx.settings(PlaceSettings)
        self.metrics = ctx.metric_set(VerifierMetrics)
        self.preset = get_preset(self.places.preset)
        self.frames: dict[int, Constellation] = {}
        self.lock = threading.Lock()
        self.store_log = ctx.open_log("verifier")
        for record in self.store_log.records():
            msg = pb.Constellation.FromString(record)
            self.frames[msg.frame_index] = constellation_from_proto(msg, self.places.n_labels)
        self.metrics.stored_frames.set(len(self.frames))
        # Load the association kernels now (numba compiles or reads its cache on
        # first use), so the first query does not pay hundreds of milliseconds.
        probe = Constellation(np.zeros(3, np.int64), np.eye(3))
        verify(probe, (0, 0), self.bus.robot, [(0, probe)], 1, self.preset)
        ctx.log.info("frames loaded", extra={"fields": {"stored": len(self.frames)}})

    def member_info(self) -> pb.MemberInfo:
        with self.lock:
            return pb.MemberInfo(stored_items=len(self.frames), n_labels=self.places.n_labels)

    def _constellation(self, msg: pb.Constellation) -> Constellation:
        n_robots = self.bus.n_robots
        if msg.robot_id >= n_robots:
            raise InvalidArgument(f"robot {msg.robot_id} is not in this swarm of {n_robots} robots")
        if msg.frame_index >= MAX_FRAME_INDEX:
            raise InvalidArgument(f"frame index must be below {MAX_FRAME_INDEX}, got {msg.frame_index}")
        return constellation_from_proto(msg, self.places.n_labels)

    def store(self, msg: pb.Constellation, _ctx: RequestContext) -> pb.StoreReply:
        own = self.bus.robot
        if msg.robot_id != own:
            raise InvalidArgument(
                f"verifier {own} stores only its own robot's frames, got robot {msg.robot_id}"
            )
        c = self._constellation(msg)
        with self.lock:
            self.store_log.append(encode(msg))
            self.frames[msg.frame_index] = c
            n = len(self.frames)
        self.metrics.stored_frames.set(n)
        return pb.StoreReply(stored_frames=n)

    def verify(self, req: pb.VerifyRequest, _ctx: RequestContext) -> pb.VerifyReply:
        if not req.HasField("query"):
            raise InvalidArgument("verify request without a query constellation")
        query = self._constellation(req.query)
        preset = self.preset
        if req.HasField("distance_threshold_m"):
            d = req.distance_threshold_m
            if not (math.isfinite(d) and d > 0):
                raise InvalidArgument(f"distance_threshold_m must be a positive number, got {d}")
            preset = preset.with_(d=float(d))
        with self.lock:
            if req.candidate_frame_indices:
                wanted = sorted(set(req.candidate_frame_indices))
                frames = [(f, self.frames[f]) for f in wanted if f in self.frames]
                missing = len(wanted) - len(frames)
                if missing:
                    self.ctx.log.warning(
                        "asked to verify frames it does not hold", extra={"fields": {"missing": missing}}
                    )
            else:
                frames = [(f, c) for f, c in self.frames.items() if len(c) >= preset.min_common]
        results = verify(
            query,
            (req.query.robot_id, req.query.frame_index),
            self.bus.robot,
            frames,
            self.places.n_labels,
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
