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

**Re-balancing** (docs/vpr.md, "Re-balancing a live swarm"; :mod:`swarmrec.vpr.live`). The
table is versioned and can change while the swarm runs. ``rebalance`` (an operator's, or
every ``vpr_rebalance_every_s`` on its own) asks the coordinator, the lowest live
place-owner, to plan the next table: it gathers every owner's ``cluster_load`` (queries per
cluster since the table began, how they lie between cells, the splits of its hot clusters),
plans with the offline rules and sends it to every owner (``adopt_table``). An owner that
adopts a table refuses queries routed with another version from then on (a querier then
fetches the coordinator's table and routes again: a query is refused, never lost), and moves
what it stores to where the new table puts each descriptor (its owner, and after the first
re-balancing copies at the owners of its next-nearest cells): ``store_entries`` at each new
holder (idempotent, logged there), then the entries it no longer holds are removed (logged
as removals). A holder that cannot reach a new holder keeps those entries and tries again
every second, so nothing stored is lost when an owner is down. A querier also stores a copy
of each of its queries at the copy holders the table names (``store_copy``), and retries an
owner that does not answer. The table is saved in the data folder (``cluster-table.pb``), so
a restarted owner follows the version it followed; one that missed a table (it was down, or
lost the file) fetches the coordinator's when a request names a newer version, and a querier
refused for its old version does the same: a swarm that never re-balances sends no table.

**State.** Each accepted descriptor is appended to the record log (``place-owner.log``)
before the answer; the faiss index is saved to ``<data_dir>/owner-index.npz`` every
``vpr_snapshot_every`` new descriptors and when the service stops. A restart loads the
snapshot and adds what the log holds beyond it, so nothing acknowledged is lost, even
after a SIGKILL.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import threading
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from swarmrec.core.presets import get_preset
from swarmrec.errors import (
    AlreadyExists,
    CallError,
    ConfigError,
    ErrorCode,
    FailedPrecondition,
    InvalidArgument,
    PermissionDenied,
    RemoteError,
    SwarmrecError,
    Unavailable,
    WireError,
)
from swarmrec.runtime import Endpoint, RequestContext, ServiceBase, ServiceContext, keys
from swarmrec.runtime.settings import StorageSettings
from swarmrec.services.limits import MAX_FRAME_INDEX
from swarmrec.services.metrics import PlaceOwnerMetrics
from swarmrec.services.settings import PlaceSettings, VprSettings
from swarmrec.vpr.balance import RebalanceRule
from swarmrec.vpr.errors import DescriptorError, StateFileError
from swarmrec.vpr.index import OwnerIndex, set_faiss_threads
from swarmrec.vpr.live import (
    MAX_SPLITS,
    LiveTable,
    Window,
    as_int8_exact,
    merge_loads,
    next_table,
    owner_load,
    split_allowed,
)
from swarmrec.vpr.quantize import Int8Quantizer
from swarmrec.vpr.table import centres_digest, swarm_table
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import check_fields, constellation_from_proto, encode, match_scores
from swarmrec.wire.vpr import (
    descriptor_from_wire,
    descriptor_to_wire,
    encoding_of,
    load_from_proto,
    load_to_proto,
    table_from_proto,
    table_to_proto,
)

__all__ = ["SNAPSHOT_NAME", "TABLE_NAME", "PlaceOwner"]

#: The faiss snapshot in the service's data folder.
SNAPSHOT_NAME = "owner-index.npz"
#: The table the owner follows (a ClusterTable), in the service's data folder.
TABLE_NAME = "cluster-table.pb"
#: Descriptors a move sends in one request (~0.5 kB each as float32).
MOVE_BATCH = 512
#: A store_entries request with more entries is refused (TOO_LARGE would need the limit; FAILED
#: is clearer to a holder that sent a bigger batch than any version of this service does).
MAX_MOVE_ENTRIES = 4096
#: How often a querier routes a query again when it was refused for its table's version, or
#: its owner did not answer.
ROUTE_ATTEMPTS = 4
#: Words of an owner's refusal of a table change that asks for the whole table.
WHOLE_TABLE = "send the whole table"
#: Seconds between a holder's tries to deliver entries a move could not deliver.
PENDING_RETRY_S = 1.0


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
        self.dimension = self.table.router.dimension
        self.wire_encoding = encoding_of(self.vpr.vpr_wire_code)
        self.float32 = encoding_of("float32")
        # OpenMP's waiting threads made single searches 5-20x slower on shared cores.
        set_faiss_threads(1)
        self.lock = threading.Lock()
        self.entries = ctx.open_log("place-owner")
        storage = ctx.settings(StorageSettings)
        self.snapshot: Path | None = storage.data_dir / SNAPSHOT_NAME if storage.data_dir else None
        self.table_path: Path | None = storage.data_dir / TABLE_NAME if storage.data_dir else None
        # The table followed now (version 0: the settings'); a saved later one replaces it.
        self.live = self._restore_table(LiveTable(self.table.router))
        self.window = Window(self.live.version)
        self.rule = RebalanceRule(
            clusters_per_robot=max(1, self.vpr.vpr_clusters_per_robot),
            slack=self.vpr.vpr_rebalance_slack,
            replica_share=self.vpr.vpr_copy_share,
            neighbours=self.vpr.vpr_copy_neighbours,
        )
        # Entries a move could not deliver yet: target robot -> (robot, frame) entries.
        self.pending: dict[int, set[tuple[int, int]]] = {}
        # One re-balancing or move at a time.
        self.moving = threading.RLock()
        self._looked = -1.0
        # The table before the current one, and the version whose move this owner made.
        self.previous: LiveTable | None = None
        self.moved_version = -1
        self.catching = threading.Lock()
        self.index = self._restore()
        self.unsaved = 0
        self.metrics.stored_descriptors.set(len(self.index))
        self.closure_log = ctx.open_log("loop-closures")
        self.closures = [pb.LoopClosure.FromString(r) for r in self.closure_log.records()]
        self.closed = {c.query_frame_index for c in self.closures}
        fields = {
            "stored": len(self.index),
            "owned_clusters": sorted(self.owned),
            "clusters": self.live.assignment.n_clusters,
            "assignment_version": self.live.version,
            "centres": str(self.table.centres_path),
            "centres_sha256": centres_digest(self.live.centres),
        }
        ctx.log.info("owner index ready", extra={"fields": fields})
        self.metrics.table_version.set(self.live.version)
        self._thread = threading.Thread(target=self._background, name="place-owner-table", daemon=True)
        self._thread.start()

    @property
    def owned(self) -> frozenset[int]:
        return frozenset(self.live.assignment.clusters_of(self.bus.robot))

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
        added = skipped = removed = 0
        for record in self.entries.records():
            entry = pb.PlaceEntry.FromString(record)
            try:
                x = descriptor_from_wire(entry.descriptor, entry.encoding, self.dimension)
            except WireError as e:
                skipped += 1
                self.ctx.log.warning("logged descriptor skipped", extra={"fields": {"reason": str(e)}})
                continue
            if entry.removed:
                removed += index.remove([entry.robot_id], [entry.frame_index])
            elif index.get(entry.robot_id, entry.frame_index) is None:
                index.store(x, entry.robot_id, entry.frame_index)
                added += 1
        counts = {"from_snapshot": from_snapshot, "from_log": added, "skipped": skipped}
        if removed:
            counts["removed_by_log"] = removed
        self.ctx.log.info("owner index restored", extra={"fields": counts})
        return index

    def _restore_table(self, start: LiveTable) -> LiveTable:
        """The table saved in the data folder when it is a later one of this swarm's, else ``start``."""
        if self.table_path is None or not self.table_path.is_file():
            return start
        try:
            msg = pb.ClusterTable.FromString(self.table_path.read_bytes())
            saved = table_from_proto(msg, self.dimension, self.bus.n_robots)
        except Exception as e:  # protobuf's DecodeError or a WireError: not usable
            raise StateFileError(self.table_path, f"not a table of this swarm: {e}") from None
        return saved if saved.version > start.version else start

    def _save_table(self, table: LiveTable) -> None:
        if self.table_path is None:
            return
        tmp = self.table_path.with_name(self.table_path.name + ".tmp")
        tmp.write_bytes(encode(table_to_proto(table)))
        os.replace(tmp, self.table_path)

    def _save(self) -> None:
        """Save the faiss index (called under the lock)."""
        if self.snapshot is None:
            return
        self.index.save(self.snapshot)
        self.unsaved = 0
        self.metrics.snapshots.inc()

    def close(self) -> None:
        self._thread.join(timeout=2 * PENDING_RETRY_S)
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
        self._check_entry(robot, frame)
        x = descriptor_from_wire(req.descriptor, req.encoding, self.dimension)
        self._catch_up(req.assignment_version)  # the querier may know a table this owner missed
        with self.lock:
            # Checked under the lock: a table adopted meanwhile is seen here or the query is
            # stored before it (and then moved with the rest).
            self._check_route(self.live, cluster, req.assignment_version)
            stored = self._stored_as(robot, frame, x)
            match = self.index.search(x, robot)
            if stored is None:
                self._store(x, robot, frame, req.descriptor, req.encoding)
                self.window.add(x)
            n = len(self.index)
        self.metrics.owner_queries.inc()
        self.metrics.cluster_queries.labels(str(cluster)).inc()
        self.metrics.stored_descriptors.set(n)
        return _match(match)

    def _check_entry(self, robot: int, frame: int) -> None:
        if robot >= self.bus.n_robots:
            raise InvalidArgument(f"robot {robot} is not in this swarm of {self.bus.n_robots} robots")
        if frame >= MAX_FRAME_INDEX:
            raise InvalidArgument(f"frame index must be below {MAX_FRAME_INDEX}, got {frame}")

    def _stored_as(self, robot: int, frame: int, x: np.ndarray) -> np.ndarray | None:
        """What is stored for ``robot``'s ``frame`` (None: nothing); ALREADY_EXISTS when it is
        another descriptor than ``x`` (under the lock)."""
        stored = self.index.get(robot, frame)
        if stored is not None and not np.array_equal(stored, x):
            raise AlreadyExists(
                f"frame {frame} of robot {robot} is already stored here with another descriptor; "
                "stores are idempotent (the same descriptor again is accepted)"
            )
        return stored

    def _store(self, x: np.ndarray, robot: int, frame: int, data: bytes, encoding: int) -> bool:
        """Log and store one descriptor (under the lock); False when it was stored already."""
        if self.index.get(robot, frame) is not None:
            return False
        entry = pb.PlaceEntry(robot_id=robot, frame_index=frame, descriptor=data, encoding=encoding)  # type: ignore[arg-type]
        self.entries.append(encode(entry))
        self.index.store(x, robot, frame)
        self.unsaved += 1
        if self.unsaved >= self.vpr.vpr_snapshot_every:
            self._save()
        return True

    def lookup(self, req: pb.PlaceQuery, _ctx: RequestContext) -> pb.PlaceMatch:
        # Read-only, so not caller-bound: any client may search; robot and frame are optional.
        check_fields(req, "cluster")
        if req.HasField("robot_id") and req.robot_id >= self.bus.n_robots:
            raise InvalidArgument(f"robot {req.robot_id} is not in this swarm of {self.bus.n_robots} robots")
        self._catch_up(req.assignment_version)
        self._check_route(self.live, req.cluster, req.assignment_version)
        x = descriptor_from_wire(req.descriptor, req.encoding, self.dimension)
        # No robot named: exclude a robot id no frame has (the swarm's are 0 .. n_robots - 1).
        excluded = req.robot_id if req.HasField("robot_id") else self.bus.n_robots
        return _match(self.index.search(x, excluded))

    def _check_route(self, table: LiveTable, cluster: int, version: int) -> None:
        """Refuse a query for a cluster unknown, routed with another table, or not owned here."""
        _check_version(table, version)
        k = table.assignment.n_clusters
        if cluster >= k:
            raise InvalidArgument(f"cluster {cluster} is not one of the swarm's {k} clusters")
        owner = table.assignment.owners[cluster]
        if owner != self.bus.robot:
            raise FailedPrecondition(f"cluster {cluster} is robot {owner}'s, not robot {self.bus.robot}'s")

    def store_copy(self, req: pb.PlaceQuery, ctx: RequestContext) -> pb.StoreReply:
        """A querier's copy of its query for a cell next to its nearest (stored, never searched)."""
        check_fields(req, "robot_id", "frame_index")
        robot, frame = req.robot_id, req.frame_index
        ctx.require_own(robot, frame)
        self._check_entry(robot, frame)
        x = descriptor_from_wire(req.descriptor, req.encoding, self.dimension)
        self._catch_up(req.assignment_version)
        with self.lock:
            table = self.live
            _check_version(table, req.assignment_version)
            if self.bus.robot not in table.copy_holders(x)[0]:
                raise FailedPrecondition(
                    f"table version {table.version} puts no copy of this descriptor at robot {self.bus.robot}"
                )
            self._stored_as(robot, frame, x)
            new = self._store(x, robot, frame, req.descriptor, req.encoding)
            n = len(self.index)
        if new:
            self.metrics.copies_stored.inc()
        self.metrics.stored_descriptors.set(n)
        return pb.StoreReply()

    def assignment_table(self, _req: pb.AssignmentRequest, _ctx: RequestContext) -> pb.AssignmentReply:
        table = self.live
        return pb.AssignmentReply(
            robot_id=self.bus.robot,
            version=table.version,
            table_json=json.dumps(table.assignment.to_json()),
            owned_clusters=table.assignment.clusters_of(self.bus.robot),
            centres_sha256=centres_digest(table.centres),
            dimension=self.dimension,
            wire_encoding=self.wire_encoding,  # type: ignore[arg-type]  # an enum value
        )

    def cluster_table(self, _req: pb.TableRequest, _ctx: RequestContext) -> pb.ClusterTable:
        return table_to_proto(self.live)

    # --- re-balancing -----------------------------------------------------------

    def cluster_load(self, req: pb.ClusterLoadRequest, _ctx: RequestContext) -> pb.ClusterLoad:
        check_fields(req)
        if math.isnan(req.split_above) or req.split_above < 0:
            raise InvalidArgument(f"split_above must be a number >= 0 (inf: no split), got {req.split_above}")
        with self.lock:
            table, window = self.live, self.window
            if req.version != table.version:
                raise FailedPrecondition(
                    f"load asked for table version {req.version}; this owner follows {table.version}"
                )
            rows = list(window.rows) if not req.counts_only else []
            queries = window.queries
        if req.counts_only:
            return pb.ClusterLoad(robot_id=self.bus.robot, version=table.version, queries=queries)
        if not split_allowed(len(rows), req.split_above):
            raise InvalidArgument(
                f"split_above {req.split_above:g} would split {len(rows)} queries into more than "
                f"{MAX_SPLITS} clusters"
            )
        snapshot = Window(window.version, queries, rows)
        load = load_to_proto(
            owner_load(table, self.bus.robot, snapshot, req.split_above, int(req.seed) % 2**31)
        )
        load.queries = queries
        return load

    def _lowest_live(self) -> int:
        """The lowest place-owner this one sees alive (itself included): the coordinator."""
        live = {self.bus.robot}
        try:
            for rep in self.ctx.session.liveliness().get(
                keys.alive(self.bus.swarm, "place-owner", "*"), timeout=self.bus.request_timeout_s
            ):
                if rep.ok is not None and (parsed := keys.parse_alive(str(rep.ok.key_expr))) is not None:
                    live.add(parsed[1])
        except Exception as e:  # zenoh's errors while closing: itself alone
            self.ctx.log.warning("liveliness query failed", extra={"fields": {"reason": str(e)}})
        return min(live)

    def rebalance(self, _req: pb.RebalanceRequest, _ctx: RequestContext) -> pb.RebalanceReply:
        coordinator = self._lowest_live()
        if coordinator != self.bus.robot:
            raise FailedPrecondition(
                f"re-balancing is the coordinator's, the lowest live place-owner (robot {coordinator})"
            )
        return self._rebalance()

    def _rebalance(self) -> pb.RebalanceReply:
        """Gather every owner's load, plan the next table, have every owner adopt it."""
        with self.moving:
            table = self.live
            n = self.bus.n_robots
            # Splits: a cluster busier than the capacity of the queries so far (every owner's).
            total = self._swarm_queries(table)
            if total == 0:
                return pb.RebalanceReply(changed=False, table=table_to_proto(table))
            capacity = (1.0 + self.rule.slack) * total / n
            request = pb.ClusterLoadRequest(version=table.version, split_above=capacity, seed=table.version)
            try:
                loads = [
                    load_from_proto(m, self.dimension)
                    for m in self._ask_all("cluster_load", request, pb.ClusterLoad).values()
                ]
                merged = merge_loads(table, loads)
            except (ConfigError, WireError) as e:
                raise Unavailable(f"the owners' loads do not fit together: {e}") from None
            new = next_table(table, merged, self.rule)
            adopt = pb.AdoptTableRequest(table=table_to_proto(new))
            deadline_s = 30 * self.bus.request_timeout_s
            # Every owner follows the table first (queries by the old one are refused from
            # then on), then each moves what it holds: no move reaches an owner on the old one.
            follow = _delta(table, new)
            follow.hold_moves = True
            held = pb.AdoptTableRequest()
            held.CopyFrom(adopt)
            held.hold_moves = True
            self._ask_all("adopt_table", follow, pb.AdoptTableReply, deadline_s=deadline_s, whole=held)
            # The second time the version alone: every owner has the table now.
            move = pb.AdoptTableRequest(
                table=pb.ClusterTable(version=new.version, dimension=self.dimension), base_version=new.version
            )
            replies = self._ask_all(
                "adopt_table", move, pb.AdoptTableReply, deadline_s=deadline_s, whole=adopt
            )
        sent = sum(r.sent for r in replies.values())
        pending = sum(r.pending for r in replies.values())
        fields = {
            "version": new.version,
            "clusters": new.assignment.n_clusters,
            "observed_queries": merged.queries,
            "moved": sent,
            "pending": pending,
            "copy_margin": new.copy_margin,
        }
        self.ctx.log.info("cluster table rolled out", extra={"fields": fields})
        return pb.RebalanceReply(
            changed=True, table=adopt.table, observed_queries=merged.queries, moved=sent, pending=pending
        )

    def _ask_all(
        self,
        endpoint: str,
        request: Any,
        reply_cls: type[Any],
        deadline_s: float | None = None,
        whole: Any = None,
    ) -> dict[int, Any]:
        """Every owner's reply (this one's served here, not over the bus); Unavailable when one
        does not answer within ``deadline_s`` (retried until then). ``whole``: the request
        sent instead to an owner that refuses ``request`` as a change to a table it lacks."""
        deadline = time.monotonic() + (deadline_s or 3 * self.bus.request_timeout_s)
        handler: Callable[[Any, Any], Any] = {"cluster_load": self.cluster_load, "adopt_table": self._adopt}[
            endpoint
        ]
        out: dict[int, Any] = {}
        for r in range(self.bus.n_robots):
            sent = request
            while True:
                try:
                    if r == self.bus.robot:
                        out[r] = handler(whole if whole is not None else request, None)
                    else:
                        key = keys.endpoint(self.bus.swarm, "place-owner", r, endpoint)
                        out[r] = self.ctx.caller.call(key, sent, reply_cls, target_robot=r, endpoint=endpoint)
                    break
                except CallError as e:
                    if isinstance(e, RemoteError) and whole is not None and WHOLE_TABLE in e.message:
                        sent = whole
                        continue
                    if time.monotonic() > deadline or self.ctx.stop.is_set():
                        raise Unavailable(f"place-owner {r} did not answer {endpoint}: {e}") from None
                    time.sleep(0.2)
        return out

    def adopt_table(self, req: pb.AdoptTableRequest, ctx: RequestContext) -> pb.AdoptTableReply:
        check_fields(req, "table")
        coordinator = self._lowest_live()
        if ctx.caller_robot is None or ctx.caller_robot > coordinator:
            raise PermissionDenied(
                f"tables come from the coordinator, the lowest live place-owner ({coordinator}), "
                f"not from {ctx.caller_robot}"
            )
        return self._adopt(req, None)

    def _adopt(self, req: pb.AdoptTableRequest, _ctx: RequestContext | None) -> pb.AdoptTableReply:
        msg = req.table
        if req.HasField("base_version") and req.table.version == self.live.version:
            msg = table_to_proto(self.live)  # followed already (its moves asked now)
        elif req.HasField("base_version"):
            msg = _applied(req, self.live, self.dimension)
        new = table_from_proto(msg, self.dimension, self.bus.n_robots)
        with self.lock:
            current = self.live
            if new.version < current.version:
                raise FailedPrecondition(
                    f"table version {new.version} is older than the {current.version} followed"
                )
            if new.version > current.version:
                self._save_table(new)
                # Moves skip what the previous table put in place: one version back, and only
                # when this process made that table's move (after a restart it sends all).
                made = self.moved_version == current.version
                self.previous = current if made and new.version == current.version + 1 else None
                self.live = new
                self.window = Window(new.version)
        if new.version > current.version:
            self.metrics.table_version.set(new.version)
            self.metrics.tables_adopted.inc()
            fields = {
                "version": new.version,
                "owned_clusters": list(new.assignment.clusters_of(self.bus.robot)),
            }
            self.ctx.log.info("cluster table adopted", extra={"fields": fields})
        sent = removed = 0
        if not req.hold_moves:
            sent, removed = self._move()
        pending = sum(len(v) for v in self.pending.values())
        return pb.AdoptTableReply(
            robot_id=self.bus.robot, version=new.version, sent=sent, removed=removed, pending=pending
        )

    def _move(self) -> tuple[int, int]:
        """Send every stored entry to the robots the table puts it at, then forget the ones it
        no longer holds; entries a holder could not be reached for stay (retried later)."""
        with self.moving:
            table = self.live
            robots, frames, vectors = self.index.export()
            holders = table.holders(vectors)
            me = self.bus.robot
            waiting = {key for v in self.pending.values() for key in v}
            # The previous table's holders have what it put there (its move completed, or the
            # entry is pending at the one that sends it): an entry goes only to new holders,
            # from one of its holders (the lowest). After that first move of a table, only
            # what is pending goes again.
            first = self.moved_version != table.version
            prev = self.previous if first and self.previous is not None else None
            before = prev.holders(vectors) if prev is not None else None
            by_target: dict[int, list[int]] = defaultdict(list)
            considered: list[int] = []
            for j, where in enumerate(holders):
                entry = (int(robots[j]), int(frames[j]))
                if not first and entry not in waiting:
                    continue
                considered.append(j)
                if before is None or entry in waiting or me not in before[j]:
                    targets = where - {me}
                elif me == min(before[j]):
                    targets = where - before[j]
                else:
                    targets = set()
                for target in targets:
                    by_target[target].append(j)
            failed: dict[int, set[tuple[int, int]]] = {}
            sent = 0
            for target, rows in sorted(by_target.items()):
                try:
                    for start in range(0, len(rows), MOVE_BATCH):
                        part = rows[start : start + MOVE_BATCH]
                        entries = [self._entry(int(robots[j]), int(frames[j]), vectors[j]) for j in part]
                        key = keys.endpoint(self.bus.swarm, "place-owner", target, "store_entries")
                        request = pb.StoreEntriesRequest(version=table.version, entries=entries)
                        self.ctx.caller.call(
                            key, request, pb.StoreEntriesReply, target_robot=target, endpoint="store_entries"
                        )
                        sent += len(part)
                except CallError as e:
                    failed[target] = {(int(robots[j]), int(frames[j])) for j in rows}
                    fields = {"target": target, "entries": len(rows), "reason": str(e)}
                    self.ctx.log.warning("move not delivered yet, kept and retried", extra={"fields": fields})
            kept = {key for v in failed.values() for key in v}
            leaving = [
                j for j in considered if me not in holders[j] and (int(robots[j]), int(frames[j])) not in kept
            ]
            removed = 0
            with self.lock:
                if self.live is table:  # a newer table moves them again from scratch
                    for j in leaving:
                        removed += self.index.remove([robots[j]], [frames[j]])
                        gone = pb.PlaceEntry(
                            robot_id=int(robots[j]), frame_index=int(frames[j]), removed=True
                        )
                        self.entries.append(encode(gone))
                    self.pending = failed
                    self.moved_version = table.version
                n = len(self.index)
            self.metrics.moved.labels("sent").inc(sent)
            self.metrics.moved.labels("removed").inc(removed)
            self.metrics.stored_descriptors.set(n)
            return sent, removed

    def _entry(self, robot: int, frame: int, vector: np.ndarray) -> pb.PlaceEntry:
        """A stored descriptor as a move sends it: in the swarm's wire code when that decodes
        to exactly the stored vector (an int8 code's decoded vector encodes to the same code),
        else as float32, so the new holder stores the very same vector."""
        data, encoding = descriptor_to_wire(vector, self.vpr.vpr_wire_code)
        if encoding != self.float32 and not np.array_equal(
            descriptor_from_wire(data, encoding, self.dimension), vector
        ):
            data, encoding = vector.astype("<f4").tobytes(), self.float32
        return pb.PlaceEntry(robot_id=robot, frame_index=frame, descriptor=data, encoding=encoding)  # type: ignore[arg-type]

    def store_entries(self, req: pb.StoreEntriesRequest, ctx: RequestContext) -> pb.StoreEntriesReply:
        """Entries a holder moved here (any robots' frames): checked whole, then stored once each."""
        check_fields(req)
        if ctx.caller_robot is None:
            raise PermissionDenied("entries are moved by a place-owner of the swarm")
        if len(req.entries) > MAX_MOVE_ENTRIES:
            raise InvalidArgument(f"at most {MAX_MOVE_ENTRIES} entries a request, got {len(req.entries)}")
        rows = []
        for e in req.entries:
            self._check_entry(e.robot_id, e.frame_index)
            if e.removed:
                raise InvalidArgument("a moved entry cannot be a removal")
            rows.append(descriptor_from_wire(e.descriptor, e.encoding, self.dimension))
        self._catch_up(req.version)  # moved by a table this owner may have missed
        stored = 0
        with self.lock:
            table = self.live
            if req.version != table.version:
                raise FailedPrecondition(
                    f"moved by table version {req.version}; this owner follows {table.version}"
                )
            # Only what the table puts here: a holder cannot park entries at any owner.
            here = [self.bus.robot in where for where in table.holders(np.stack(rows))] if rows else []
            if not all(here):
                e = req.entries[here.index(False)]
                raise FailedPrecondition(
                    f"table version {table.version} puts frame {e.frame_index} of robot {e.robot_id} "
                    f"elsewhere, not at robot {self.bus.robot}"
                )
            for e, x in zip(req.entries, rows, strict=True):
                self._stored_as(e.robot_id, e.frame_index, x)
            for e, x in zip(req.entries, rows, strict=True):
                stored += self._store(x, e.robot_id, e.frame_index, e.descriptor, e.encoding)
            n = len(self.index)
        self.metrics.moved.labels("received").inc(stored)
        self.metrics.stored_descriptors.set(n)
        return pb.StoreEntriesReply(stored=stored)

    def _background(self) -> None:
        """Deliver pending moves, re-balance on a timer (the coordinator)."""
        stop = self.ctx.stop
        last = time.monotonic()
        every = self.vpr.vpr_rebalance_every_s
        while not stop.wait(PENDING_RETRY_S):
            try:
                if self.pending:
                    self._move()
                if every > 0 and time.monotonic() - last >= every:
                    last = time.monotonic()
                    coordinating = self._lowest_live() == self.bus.robot
                    if coordinating and self._swarm_queries(self.live) >= self.vpr.vpr_rebalance_min_queries:
                        self._rebalance()
            except SwarmrecError as e:
                self.ctx.log.warning("table upkeep failed, tried again", extra={"fields": {"reason": str(e)}})

    def _swarm_queries(self, table: LiveTable) -> int:
        """How many queries every owner saw since ``table`` began (counts only)."""
        loads = self._ask_all(
            "cluster_load", pb.ClusterLoadRequest(version=table.version, counts_only=True), pb.ClusterLoad
        )
        return sum(m.queries for m in loads.values())

    def _catch_up(self, wanted: int) -> None:
        """Follow the coordinator's table when a request names a version ``wanted`` newer than
        this owner's (it was down when the table came, or lost its file). One look at a time;
        after a look that found nothing newer, none for 1 s: requests claiming versions that
        do not exist cannot make it ask more often."""
        if wanted <= self.live.version:
            return  # the common case, without the lock
        with self.catching:
            if self.live.version >= wanted or time.monotonic() - self._looked < 1.0:
                return
            coordinator = self._lowest_live()
            fresh = self._fetch_table(coordinator) if coordinator != self.bus.robot else None
            if fresh is not None and fresh.version > self.live.version:
                with contextlib.suppress(FailedPrecondition):  # a newer one came meanwhile
                    self._adopt(pb.AdoptTableRequest(table=table_to_proto(fresh)), None)
            if self.live.version < wanted:
                self._looked = time.monotonic()

    def _fetch_table(self, robot: int) -> LiveTable | None:
        key = keys.endpoint(self.bus.swarm, "place-owner", robot, "table")
        try:
            msg = self.ctx.caller.call(
                key, pb.TableRequest(), pb.ClusterTable, target_robot=robot, endpoint="table"
            )
            return table_from_proto(msg, self.dimension, self.bus.n_robots)
        except (CallError, WireError) as e:
            self.ctx.log.warning("table not fetched", extra={"fields": {"robot": robot, "reason": str(e)}})
            return None

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
        report = pb.PlaceReport(robot_id=own, frame_index=frame, n_objects=len(c))
        self._ask_owner(report, x, wire, len(c))
        report.duration_us = min(int((time.perf_counter() - t0) * 1e6), 2**32 - 1)
        self.metrics.query_seconds.observe(report.duration_us / 1e6)
        if report.verified and report.score > 0 and report.score >= self.places.loop_closure_min_score:
            report.loop_closure = True
            self._loop_closure(report)
        self.ctx.publish(keys.event(self.bus.swarm, "place_query", own), report)
        return report

    def _ask_owner(
        self, report: pb.PlaceReport, x: np.ndarray, wire: pb.Constellation, n_objects: int
    ) -> None:
        """Route ``x`` with the table followed now, ask its owner, store the copies, verify the
        match. Refused for its table's version, the query is routed again with the newer one
        (fetched from the coordinator when this robot is behind); an owner that does not
        answer is asked again (its store is idempotent)."""
        data, encoding = descriptor_to_wire(x, self.vpr.vpr_wire_code)
        own = self.bus.robot
        caller = self.ctx.caller
        failure = ""
        for attempt in range(ROUTE_ATTEMPTS):
            table = self.live
            route = table.router.route(x)
            report.cluster, report.owner_robot_id = route.cluster, route.owner
            query = pb.PlaceQuery(robot_id=own, frame_index=report.frame_index, descriptor=data,
                                  encoding=encoding, cluster=route.cluster,  # type: ignore[arg-type]
                                  assignment_version=table.version)  # fmt: skip
            key = keys.endpoint(self.bus.swarm, "place-owner", route.owner, "query")
            try:
                match = caller.call(
                    key, query, pb.PlaceMatch, target_robot=route.owner, endpoint="owner_query"
                )
            except RemoteError as e:
                failure = f"owner {route.owner}: {e}"
                if e.code != ErrorCode.FAILED_PRECONDITION or "version" not in e.message:
                    break
                self.metrics.rerouted.inc()
                self._newer_table(table, e.message, attempt)
                continue
            except CallError as e:
                failure = f"owner {route.owner}: {e}"
                if attempt + 1 < ROUTE_ATTEMPTS:
                    self.metrics.rerouted.inc()
                continue
            report.answered = True
            report.match.CopyFrom(match)
            self._store_copies(table, query, x)
            if match.found and n_objects >= self.preset.min_objects:
                self._verify(report, wire)
            return
        report.failure = failure

    def _newer_table(self, seen: LiveTable, refusal: str, attempt: int) -> None:
        """After an owner refused a query routed with ``seen``: when the owner follows a newer
        version (its refusal says which), catch up with the coordinator's table; when an older
        one, wait a moment (it is adopting this robot's, or catches up itself)."""
        found = re.search(r"this owner follows version (\d+)", refusal)
        theirs = int(found.group(1)) if found else seen.version + 1
        if theirs > seen.version:
            self._catch_up(theirs)
            if self.live is not seen:
                return
        time.sleep(0.05 * 2**attempt)  # 0.05, 0.1, 0.2 s

    def _store_copies(self, table: LiveTable, query: pb.PlaceQuery, x: np.ndarray) -> None:
        """The query, stored (not searched) at the table's copy holders of its descriptor as
        the owners store it (the wire's code, decoded)."""
        if not table.copies:
            return
        stored = descriptor_from_wire(query.descriptor, query.encoding, self.dimension)
        owner = table.assignment.owners[query.cluster]
        for robot in table.copy_holders(stored)[0].tolist():
            if robot < 0 or robot == owner:
                continue
            key = keys.endpoint(self.bus.swarm, "place-owner", robot, "store_copy")
            try:
                self.ctx.caller.call(key, query, pb.StoreReply, target_robot=robot, endpoint="store_copy")
            except CallError as e:
                self.metrics.copies_failed.inc()
                fields = {"robot": robot, "frame": query.frame_index, "owner": owner, "reason": str(e)}
                self.ctx.log.warning("copy not stored", extra={"fields": fields})

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
        Endpoint(
            "table",
            pb.TableRequest,
            pb.ClusterTable,
            cluster_table,
            "the versioned table this robot routes and owns by, centres and copy rule included",
        ),
        Endpoint(
            "store_copy",
            pb.PlaceQuery,
            pb.StoreReply,
            store_copy,
            "copy holder: a querier's descriptor for a cell next to its nearest, stored and never searched",
        ),
        Endpoint(
            "cluster_load",
            pb.ClusterLoadRequest,
            pb.ClusterLoad,
            cluster_load,
            "owner: queries per cluster since the table began, their cell pairs and gaps, hot clusters split",
        ),
        Endpoint(
            "adopt_table",
            pb.AdoptTableRequest,
            pb.AdoptTableReply,
            adopt_table,
            "owner: follow the coordinator's new table and move stored descriptors to where it puts them",
        ),
        Endpoint(
            "store_entries",
            pb.StoreEntriesRequest,
            pb.StoreEntriesReply,
            store_entries,
            "new holder: descriptors another owner moved here (idempotent)",
        ),
        Endpoint(
            "rebalance",
            pb.RebalanceRequest,
            pb.RebalanceReply,
            rebalance,
            "coordinator (lowest live place-owner): plan the next table from the owners' loads, roll it out",
        ),
    )


def _check_version(table: LiveTable, version: int) -> None:
    """FAILED_PRECONDITION for a request routed with another table than ``table`` (a querier
    reads the version this owner follows from the words: ``_newer_table``)."""
    if version != table.version:
        raise FailedPrecondition(
            f"routed with assignment version {version}; this owner follows version {table.version}"
        )


def _delta(base: LiveTable, new: LiveTable) -> pb.AdoptTableRequest:
    """``new`` as changes to ``base``'s centres: the rows that differ and those appended."""
    msg = table_to_proto(new)
    msg.centres = b""
    k = base.assignment.n_clusters
    replaced = [c for c in range(k) if not np.array_equal(new.centres[c], base.centres[c])]
    rows = np.concatenate([new.centres[replaced], new.centres[k:]]).astype(np.float32)
    exact = len(rows) == 0 or np.array_equal(as_int8_exact(rows), rows)
    if exact:
        quantizer = Int8Quantizer(new.router.dimension)
        old, added = quantizer.encode(new.centres[replaced]), quantizer.encode(new.centres[k:])
        replaced_data, appended_data = old.tobytes(), added.tobytes()
        encoding = pb.DescriptorEncoding.DESCRIPTOR_ENCODING_INT8
    else:
        replaced_data = np.ascontiguousarray(new.centres[replaced], "<f4").tobytes()
        appended_data = np.ascontiguousarray(new.centres[k:], "<f4").tobytes()
        encoding = pb.DescriptorEncoding.DESCRIPTOR_ENCODING_FLOAT32
    return pb.AdoptTableRequest(
        table=msg,
        base_version=base.version,
        replaced=replaced,
        replaced_centres=replaced_data,
        appended_centres=appended_data,
        centres_encoding=encoding,
    )


def _applied(req: pb.AdoptTableRequest, base: LiveTable, d: int) -> pb.ClusterTable:
    """The whole table a change to ``base`` gives (FAILED_PRECONDITION, naming
    :data:`WHOLE_TABLE`, when this owner is not on the base version; InvalidArgument when the
    change does not fit it)."""
    if req.base_version != base.version:
        raise FailedPrecondition(
            f"a change to table version {req.base_version}; this owner follows {base.version}: {WHOLE_TABLE}"
        )
    k = base.assignment.n_clusters
    int8 = req.centres_encoding == pb.DescriptorEncoding.DESCRIPTOR_ENCODING_INT8
    if not int8 and req.centres_encoding not in (0, pb.DescriptorEncoding.DESCRIPTOR_ENCODING_FLOAT32):
        raise InvalidArgument(f"centres encoding {req.centres_encoding} is not float32 or int8")
    row = 4 + d if int8 else 4 * d
    if len(req.replaced_centres) != row * len(req.replaced) or len(req.appended_centres) % row:
        raise InvalidArgument("the table's changed centres are not whole rows")
    if len(set(req.replaced)) != len(req.replaced) or any(c >= k for c in req.replaced):
        raise InvalidArgument(f"changed clusters must be distinct and below the base's {k}")

    def rows(data: bytes) -> np.ndarray:
        if not int8:
            return np.frombuffer(data, "<f4").reshape(-1, d)
        try:
            return Int8Quantizer(d).decode(np.frombuffer(data, np.uint8).reshape(-1, row))
        except DescriptorError as e:
            raise InvalidArgument(f"the table's changed centres: {e}") from None

    centres = base.centres.copy()
    centres[list(req.replaced)] = rows(req.replaced_centres)
    appended = rows(req.appended_centres)
    full = np.concatenate([centres, appended]).astype("<f4")
    if len(full) != len(req.table.owners):
        raise InvalidArgument(f"{len(full)} centres for a table of {len(req.table.owners)} owners")
    msg = pb.ClusterTable()
    msg.CopyFrom(req.table)
    msg.centres = full.tobytes()
    return msg


def _match(match: object) -> pb.PlaceMatch:
    if match is None:
        return pb.PlaceMatch(found=False)
    return pb.PlaceMatch(found=True, distance=match.distance, robot_id=match.robot, frame_index=match.frame)  # type: ignore[attr-defined]
