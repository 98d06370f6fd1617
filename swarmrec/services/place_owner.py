"""The place-owner service: full-image place recognition for one robot (docs/vpr.md).

Every robot runs one. It plays the method's two roles for its robot:

* **owner** of its clusters of the descriptor space (the swarm's assignment table,
  :mod:`swarmrec.vpr.table`): ``query`` takes a :class:`PlaceQuery` routed to one of its
  clusters, searches everything routed to it so far (its own clusters, every robot's frames
  but the querier's own; :class:`~swarmrec.vpr.index.OwnerIndex`, faiss exact L2), answers
  the nearest (:class:`PlaceMatch`: squared distance, robot, frame), then stores the query.
* **querier** for its robot's frames: ``process`` takes a :class:`PlaceFrame` from the
  robot's detector (the frame's float32 descriptor and its constellation), stores the
  constellation in the robot's own verifier (the authority on what frame t is, as for the
  constellation method), routes the descriptor to the owner of its nearest centre and asks
  it (quantised to the swarm's ``vpr_wire_code``, int8 by default), then sends the query
  constellation to the verifier of the match's robot, which scores the pair geometrically.
  A verified match at least ``loop_closure_min_score`` good is a loop closure: kept
  (``loop-closures.log``, served by ``loop_closures``) and published on
  ``events/loop_closure/<robot>``; every frame's :class:`PlaceReport` goes to
  ``events/place_query/<robot>``. A frame with fewer than the preset's ``min_objects``
  objects (3) is still routed, answered and stored at its owner, but its match cannot be
  verified, so it never becomes a loop closure (``verified`` false in its report).

``assignment`` serves the table this robot routes and owns by (its version, the JSON
table, its own clusters, a digest of the centres). ``lookup`` is the owner's search without
the store, for clients (the gateway's ``PlaceQuery``): a :class:`PlaceQuery` for one of its
clusters, routed with its table's version, answered with the nearest stored frame (of a robot
other than ``robot_id`` when the query names one, of any robot otherwise); nothing changes.

**Bad input.** A query is checked before anything is stored: robot and frame present and
in range, the cluster known to the table and owned here, the table's version the
sender's (else FAILED_PRECONDITION: it routed with another table), the descriptor of the
swarm's length, finite and of unit norm in its encoding (:func:`swarmrec.wire.vpr.descriptor_from_wire`).
Stores are idempotent: the same (robot, frame) with the same descriptor again is answered
(a fresh search) and stored once; other content is ALREADY_EXISTS.

**State.** Each accepted descriptor is appended to the record log (``place-owner.log``)
before the answer; the faiss index is saved to ``<data_dir>/owner-index.npz`` every
``vpr_snapshot_every`` new descriptors and when the service stops. A restart loads the
snapshot and adds what the log holds beyond it, so nothing acknowledged is lost, even
after a SIGKILL.
"""

from __future__ import annotations

import json
import math
import threading
import time
from pathlib import Path

import numpy as np

from swarmrec.core.presets import get_preset
from swarmrec.errors import (
    AlreadyExists,
    CallError,
    ErrorCode,
    FailedPrecondition,
    InvalidArgument,
    RemoteError,
    Unavailable,
    WireError,
)
from swarmrec.runtime import Endpoint, RequestContext, ServiceBase, ServiceContext, keys
from swarmrec.runtime.settings import StorageSettings
from swarmrec.services.limits import MAX_FRAME_INDEX
from swarmrec.services.metrics import PlaceOwnerMetrics
from swarmrec.services.settings import PlaceSettings, VprSettings
from swarmrec.vpr.errors import StateFileError
from swarmrec.vpr.index import OwnerIndex, set_faiss_threads
from swarmrec.vpr.table import swarm_table
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import check_fields, constellation_from_proto, encode, match_scores
from swarmrec.wire.vpr import descriptor_from_wire, descriptor_to_wire, encoding_of

__all__ = ["SNAPSHOT_NAME", "PlaceOwner"]

#: The faiss snapshot in the service's data folder.
SNAPSHOT_NAME = "owner-index.npz"


class PlaceOwner(ServiceBase):
    def __init__(self, ctx: ServiceContext) -> None:
        self.ctx = ctx
        self.bus = ctx.bus
        self.places = ctx.settings(PlaceSettings)
        self.vpr = ctx.settings(VprSettings)
        self.metrics = ctx.metric_set(PlaceOwnerMetrics)
        self.preset = get_preset(self.places.preset)
        self.limits = self.places.frame_limits()
        # A missing or wrong centres or table file stops the service here, with its reason.
        self.table = swarm_table(
            self.bus.n_robots,
            self.vpr.vpr_clusters_per_robot,
            self.vpr.vpr_assignment_seed,
            centres=self.vpr.vpr_centres,
            assignment=self.vpr.vpr_assignment,
        )
        self.router = self.table.router
        self.assignment = self.table.assignment
        self.dimension = self.router.dimension
        self.owned = frozenset(self.assignment.clusters_of(self.bus.robot))
        self.wire_encoding = encoding_of(self.vpr.vpr_wire_code)
        # OpenMP's waiting threads made single searches 5-20x slower on shared cores.
        set_faiss_threads(1)
        self.lock = threading.Lock()
        self.entries = ctx.open_log("place-owner")
        storage = ctx.settings(StorageSettings)
        self.snapshot: Path | None = storage.data_dir / SNAPSHOT_NAME if storage.data_dir else None
        self.index = self._restore()
        self.unsaved = 0
        self.metrics.stored_descriptors.set(len(self.index))
        self.closure_log = ctx.open_log("loop-closures")
        self.closures = [pb.LoopClosure.FromString(r) for r in self.closure_log.records()]
        self.closed = {c.query_frame_index for c in self.closures}
        fields = {
            "stored": len(self.index),
            "owned_clusters": sorted(self.owned),
            "clusters": self.assignment.n_clusters,
            "assignment_version": self.assignment.version,
            "centres": str(self.table.centres_path),
            "centres_sha256": self.table.digest,
        }
        ctx.log.info("owner index ready", extra={"fields": fields})

    # --- state ----------------------------------------------------------------

    def _restore(self) -> OwnerIndex:
        """The snapshot (when there is a usable one) plus every logged descriptor it lacks."""
        index: OwnerIndex | None = None
        if self.snapshot is not None and self.snapshot.is_file():
            try:
                index = OwnerIndex.load(self.snapshot)
                if index.dimension != self.dimension:
                    found = f"dimension {index.dimension}, the swarm's is {self.dimension}"
                    raise StateFileError(self.snapshot, found)
            except StateFileError as e:
                # The log holds every descriptor: rebuilding from it loses nothing.
                fields = {"reason": str(e)}
                self.ctx.log.warning("snapshot not used, rebuilt from the log", extra={"fields": fields})
                index = None
        from_snapshot = len(index) if index is not None else 0
        index = index if index is not None else OwnerIndex(self.dimension)
        added = skipped = 0
        for record in self.entries.records():
            entry = pb.PlaceEntry.FromString(record)
            try:
                x = descriptor_from_wire(entry.descriptor, entry.encoding, self.dimension)
            except WireError as e:
                skipped += 1
                self.ctx.log.warning("logged descriptor skipped", extra={"fields": {"reason": str(e)}})
                continue
            if index.get(entry.robot_id, entry.frame_index) is None:
                index.store(x, entry.robot_id, entry.frame_index)
                added += 1
        counts = {"from_snapshot": from_snapshot, "from_log": added, "skipped": skipped}
        self.ctx.log.info("owner index restored", extra={"fields": counts})
        return index

    def _save(self) -> None:
        """Save the faiss index (called under the lock)."""
        if self.snapshot is None:
            return
        self.index.save(self.snapshot)
        self.unsaved = 0
        self.metrics.snapshots.inc()

    def close(self) -> None:
        with self.lock:
            if self.unsaved:
                self._save()

    def member_info(self) -> pb.MemberInfo:
        return pb.MemberInfo(stored_items=len(self.index), n_labels=self.places.n_labels)

    # --- owner ----------------------------------------------------------------

    def query(self, req: pb.PlaceQuery, ctx: RequestContext) -> pb.PlaceMatch:
        check_fields(req, "robot_id", "frame_index", "cluster")
        robot, frame, cluster = req.robot_id, req.frame_index, req.cluster
        ctx.require_own(robot, frame)  # the caller is the robot the key names (keys.CALLER_BOUND)
        if robot >= self.bus.n_robots:
            raise InvalidArgument(f"robot {robot} is not in this swarm of {self.bus.n_robots} robots")
        if frame >= MAX_FRAME_INDEX:
            raise InvalidArgument(f"frame index must be below {MAX_FRAME_INDEX}, got {frame}")
        self._check_route(cluster, req.assignment_version)
        x = descriptor_from_wire(req.descriptor, req.encoding, self.dimension)
        with self.lock:
            stored = self.index.get(robot, frame)
            if stored is not None and not np.array_equal(stored, x):
                raise AlreadyExists(
                    f"frame {frame} of robot {robot} is already stored here with another descriptor; "
                    "stores are idempotent (the same descriptor again is accepted)"
                )
            match = self.index.search(x, robot)
            if stored is None:
                entry = pb.PlaceEntry(robot_id=robot, frame_index=frame, descriptor=req.descriptor,
                                      encoding=req.encoding)  # fmt: skip
                self.entries.append(encode(entry))
                self.index.store(x, robot, frame)
                self.unsaved += 1
                if self.unsaved >= self.vpr.vpr_snapshot_every:
                    self._save()
            n = len(self.index)
        self.metrics.owner_queries.inc()
        self.metrics.cluster_queries.labels(str(cluster)).inc()
        self.metrics.stored_descriptors.set(n)
        if match is None:
            return pb.PlaceMatch(found=False)
        return pb.PlaceMatch(
            found=True, distance=match.distance, robot_id=match.robot, frame_index=match.frame
        )

    def lookup(self, req: pb.PlaceQuery, _ctx: RequestContext) -> pb.PlaceMatch:
        # Read-only, so not caller-bound: any client may search; robot and frame are optional.
        check_fields(req, "cluster")
        if req.HasField("robot_id") and req.robot_id >= self.bus.n_robots:
            raise InvalidArgument(f"robot {req.robot_id} is not in this swarm of {self.bus.n_robots} robots")
        self._check_route(req.cluster, req.assignment_version)
        x = descriptor_from_wire(req.descriptor, req.encoding, self.dimension)
        # No robot named: exclude a robot id no frame has (the swarm's are 0 .. n_robots - 1).
        excluded = req.robot_id if req.HasField("robot_id") else self.bus.n_robots
        match = self.index.search(x, excluded)
        if match is None:
            return pb.PlaceMatch(found=False)
        return pb.PlaceMatch(
            found=True, distance=match.distance, robot_id=match.robot, frame_index=match.frame
        )

    def _check_route(self, cluster: int, version: int) -> None:
        """Refuse a query for a cluster unknown, routed with another table, or not owned here."""
        k = self.assignment.n_clusters
        if cluster >= k:
            raise InvalidArgument(f"cluster {cluster} is not one of the swarm's {k} clusters")
        if version != self.assignment.version:
            raise FailedPrecondition(
                f"routed with assignment version {version}; this owner follows "
                f"version {self.assignment.version}"
            )
        if cluster not in self.owned:
            owner = self.assignment.owners[cluster]
            raise FailedPrecondition(f"cluster {cluster} is robot {owner}'s, not robot {self.bus.robot}'s")

    def assignment_table(self, _req: pb.AssignmentRequest, _ctx: RequestContext) -> pb.AssignmentReply:
        return pb.AssignmentReply(
            robot_id=self.bus.robot,
            version=self.assignment.version,
            table_json=json.dumps(self.assignment.to_json()),
            owned_clusters=sorted(self.owned),
            centres_sha256=self.table.digest,
            dimension=self.dimension,
            wire_encoding=self.wire_encoding,  # type: ignore[arg-type]  # an enum value
        )

    # --- querier --------------------------------------------------------------

    def process(self, msg: pb.PlaceFrame, _ctx: RequestContext) -> pb.PlaceReport:
        check_fields(msg, "robot_id", "frame_index", "constellation")
        own, frame = self.bus.robot, msg.frame_index
        if msg.robot_id != own:
            raise InvalidArgument(
                f"place-owner {own} queries only its own robot's frames, got robot {msg.robot_id}"
            )
        if frame >= MAX_FRAME_INDEX:
            raise InvalidArgument(f"frame index must be below {MAX_FRAME_INDEX}, got {frame}")
        x = descriptor_from_wire(msg.descriptor, msg.encoding, self.dimension)
        wire = pb.Constellation()
        wire.CopyFrom(msg.constellation)
        wire.robot_id, wire.frame_index, wire.frame_id = own, frame, msg.frame_id
        c = constellation_from_proto(wire, self.places.n_labels, self.limits)
        t0 = time.perf_counter()
        caller = self.ctx.caller
        try:
            caller.call(keys.endpoint(self.bus.swarm, "verifier", own, "store"), wire, pb.StoreReply,
                        target_robot=own, endpoint="store")  # fmt: skip
        except RemoteError as e:
            if e.code == ErrorCode.ALREADY_EXISTS:
                raise AlreadyExists(f"frame {frame}: {e.message}") from None
            raise Unavailable(f"own verifier did not store the frame: {e}") from None
        except CallError as e:
            raise Unavailable(f"own verifier did not store the frame: {e}") from None
        route = self.router.route(x)
        report = pb.PlaceReport(
            robot_id=own,
            frame_index=frame,
            cluster=route.cluster,
            owner_robot_id=route.owner,
            n_objects=len(c),
        )
        data, encoding = descriptor_to_wire(x, self.vpr.vpr_wire_code)
        query = pb.PlaceQuery(
            robot_id=own,
            frame_index=frame,
            descriptor=data,
            encoding=encoding,  # type: ignore[arg-type]  # an enum value
            cluster=route.cluster,
            assignment_version=self.assignment.version,
        )
        try:
            match = caller.call(keys.endpoint(self.bus.swarm, "place-owner", route.owner, "query"), query,
                                pb.PlaceMatch, target_robot=route.owner, endpoint="owner_query")  # fmt: skip
        except CallError as e:
            report.failure = f"owner {route.owner}: {e}"
        else:
            report.answered = True
            report.match.CopyFrom(match)
            if match.found and len(c) >= self.preset.min_objects:
                self._verify(report, wire)
        report.duration_us = min(int((time.perf_counter() - t0) * 1e6), 2**32 - 1)
        self.metrics.query_seconds.observe(report.duration_us / 1e6)
        if report.verified and report.score > 0 and report.score >= self.places.loop_closure_min_score:
            report.loop_closure = True
            self._loop_closure(report)
        self.ctx.publish(keys.event(self.bus.swarm, "place_query", own), report)
        return report

    def _verify(self, report: pb.PlaceReport, wire: pb.Constellation) -> None:
        """The match's robot scores the pair geometrically (its verifier's ``verify``)."""
        m = report.match
        # A robot or frame of 0 is left absent: a verify query may, and reads it as 0.
        query = pb.Constellation(
            robot_id=wire.robot_id or None,
            frame_index=wire.frame_index or None,
            labels=wire.labels,
            positions_mm=wire.positions_mm,
            positions_m=wire.positions_m,
        )
        request = pb.VerifyRequest(query=query, candidate_frame_indices=[m.frame_index])
        key = keys.endpoint(self.bus.swarm, "verifier", m.robot_id, "verify")
        try:
            reply = self.ctx.caller.call(
                key, request, pb.VerifyReply, target_robot=m.robot_id, endpoint="verify"
            )
            # The verifier lists only frames that scored > 0: none means not associated (score 0).
            found = next((v for v in reply.matches if v.frame_index == m.frame_index), None)
            scores = match_scores(found) if found is not None else (0.0, 0.0)
        except (CallError, WireError) as e:
            report.failure = f"verifier {m.robot_id}: {e}"
            return
        report.verified = True
        report.score, report.semantic_score = scores
        report.n_matched = found.n_matched if found is not None else 0

    def _loop_closure(self, report: pb.PlaceReport) -> None:
        m = report.match
        closure = pb.LoopClosure(
            query_robot_id=report.robot_id,
            query_frame_index=report.frame_index,
            match_robot_id=m.robot_id,
            match_frame_index=m.frame_index,
            score=report.score,
            semantic_score=report.semantic_score,
            n_matched=report.n_matched,
            unix_time_ns=time.time_ns(),
        )
        with self.lock:
            if report.frame_index in self.closed:
                return  # processed again: its closure is kept already
            self.closure_log.append(encode(closure))
            self.closures.append(closure)
            self.closed.add(report.frame_index)
        self.metrics.loop_closures.inc()
        self.ctx.publish(keys.event(self.bus.swarm, "loop_closure", report.robot_id), closure)

    def loop_closures(self, req: pb.LoopClosuresRequest, _ctx: RequestContext) -> pb.LoopClosureList:
        check_fields(req)
        if not math.isfinite(req.min_score):
            raise InvalidArgument(f"min_score must be a finite number, got {req.min_score}")
        with self.lock:
            found = [c for c in self.closures if c.score >= req.min_score]
        return pb.LoopClosureList(robot_id=self.bus.robot, loop_closures=found)

    ENDPOINTS = (
        Endpoint(
            "query",
            pb.PlaceQuery,
            pb.PlaceMatch,
            query,
            "owner: the nearest stored frame of another robot, then the query is stored",
        ),
        Endpoint(
            "process",
            pb.PlaceFrame,
            pb.PlaceReport,
            process,
            "querier: store, route, ask the owner and verify one of this robot's frames",
        ),
        Endpoint(
            "lookup",
            pb.PlaceQuery,
            pb.PlaceMatch,
            lookup,
            "owner: the nearest stored frame (of another robot than robot_id, when given); stores nothing",
        ),
        Endpoint(
            "assignment",
            pb.AssignmentRequest,
            pb.AssignmentReply,
            assignment_table,
            "the assignment table this robot routes and owns by",
        ),
        Endpoint(
            "loop_closures",
            pb.LoopClosuresRequest,
            pb.LoopClosureList,
            loop_closures,
            "the loop closures found so far",
        ),
    )
