"""The index-shard service: label groups of the swarm's descriptor index.

The label list is cut into groups (by default the paper's even ranges, one per
robot) and each group lives on ``replicas`` shards, as the placement says
(:mod:`swarmrec.core.placement`; docs/elastic-index.md). A shard keeps one
:class:`~swarmrec.core.index.RangeIndex` per group it holds, so a group's
partial scores never depend on which shard computes them.

Endpoints:

* ``query``: a :class:`PartialQuery` for a group this shard owns -> the ``n_ret``
  best stored frames (:class:`CandidatesReply`); unless the query is read-only,
  the query's slice is then stored. ``lookup`` is the same search that never
  stores (clients and the gateway use it, so the router's access control can
  keep them from storing).
* ``store``: a :class:`ShardStore`: a slice stored without a search (the other
  owners and the learners of its group get these).
* ``placement``: the placement this shard follows and what it holds (:class:`ShardState`).
* ``adopt``: the coordinator's new placement; ``transfer``: a page of a group's
  descriptors for a shard copying it.

Every request that reads or writes a group carries the placement version its
sender routed with; a shard following another version refuses it with
FAILED_PRECONDITION (the sender refreshes and routes again), so no query is
answered from a table the shard no longer follows. A shard restarted from its
disk answers nothing until the coordinator confirms its placement.

Stored slices are appended to the record log (``<data_dir>/index-shard.log``)
before the answer goes out, and replayed on start; the placement followed and
the groups copied completely are kept beside it (``placement.state``).

Stores are idempotent per (robot, frame): the same slice again is answered as
before and nothing is appended; another slice for a stored frame is refused
(ALREADY_EXISTS) before anything is computed. Counts past a frame's bounds
(``max_objects_per_label``, ``max_objects_per_frame``) are refused (TOO_LARGE).

The coordinator (the lowest live shard) runs in every shard and acts only
while it is the lowest: :mod:`swarmrec.services.coordinator`.
"""

from __future__ import annotations

import contextlib
import os
import threading
import time
from pathlib import Path

import numpy as np
import numpy.typing as npt
import zenoh

from swarmrec.core.index import RangeIndex
from swarmrec.core.placement import Placement, ring
from swarmrec.core.presets import get_preset
from swarmrec.errors import (
    AlreadyExists,
    CallError,
    FailedPrecondition,
    InvalidArgument,
    LimitExceededError,
    RemoteError,
    WireError,
)
from swarmrec.runtime import Endpoint, RequestContext, ServiceBase, ServiceContext, keys
from swarmrec.runtime.settings import StorageSettings
from swarmrec.services.coordinator import Coordinator, ShardSettings, reason_name
from swarmrec.services.limits import MAX_FRAME_GAP, MAX_FRAME_INDEX, MAX_N_RET
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import (
    Candidate,
    DescriptorSlice,
    candidates_to_proto,
    check_fields,
    encode,
    partial_descriptor_from_proto,
    partial_descriptor_to_proto,
)
from swarmrec.wire.placement import placement_from_proto, placement_to_proto

__all__ = ["IndexShard"]

#: Largest row a transfer may start at (rows are counted in an int64 array).
_MAX_ROW = 1 << 40
#: How long a request routed with a newer placement than the shard's waits for it.
BEHIND_WAIT_S = 1.0


class IndexShard(ServiceBase, ShardSettings):
    def __init__(self, ctx: ServiceContext) -> None:
        self.read_settings(ctx)
        self.n_ret = get_preset(self.places.preset).n_ret
        self.limits = self.places.frame_limits()
        # One lock for the placement, the indexes and the log: a version switch happens
        # between two stores, never during one (docs/elastic-index.md, handoffs).
        self.lock = threading.RLock()
        # Notified when the placement changes: a request routed with a newer version than
        # this shard's waits for the adoption that is on its way instead of failing.
        self.placement_changed = threading.Condition(self.lock)
        self.store_log = ctx.open_log("index-shard")
        storage = ctx.config.get(StorageSettings) if ctx.config.has(StorageSettings) else None
        data_dir = storage.data_dir if storage is not None else None
        self.state_path: Path | None = data_dir / "placement.state" if data_dir else None
        self.indexes: dict[int, RangeIndex] = {}
        self.ready: set[int] = set()
        self.served = [0] * len(self.groups)
        self.syncing: set[int] = set()
        saved = self._load_state()
        if saved is None:
            # A shard with nothing on disk starts from version 0 (every shard of a new swarm
            # computes the same table), but answers only once it has checked that the swarm
            # is not further along (coordinator.confirm_on_start).
            self.placement = ring(
                self.groups, range(self.bus.n_robots), replicas=self.index_settings.replicas
            )
            held = set(self.placement.groups_of(self.shard))
            self.ready = set(held)
        else:
            self.placement, self.ready = saved
            held = set(self.placement.groups_of(self.shard)) | set(self.placement.learning(self.shard))
        self.confirmed = False
        self.draining = False
        self._draining_token: zenoh.LivelinessToken | None = None
        for g in sorted(held):
            self.indexes[g] = RangeIndex(*self.groups[g], self.bus.n_robots)
        restored, skipped = self._replay_log(held)
        self._update_gauges()
        fields = {
            "groups": sorted(self.placement.groups_of(self.shard)),
            "learning": sorted(self.placement.learning(self.shard)),
            "version": self.placement.version,
            "records": restored,
            "skipped": skipped,
            "stored": self.stored,
        }
        ctx.log.info("index loaded", extra={"fields": fields})
        self.coordinator = Coordinator(self)

    # --- state ----------------------------------------------------------------------

    @property
    def stored(self) -> int:
        return sum(ix.size for ix in self.indexes.values())

    def _replay_log(self, groups: set[int]) -> tuple[int, int]:
        """Load the logged slices of ``groups`` into their indexes; (loaded, skipped)."""
        restored = skipped = 0
        for record in self.store_log.records():
            msg = pb.PartialDescriptor.FromString(record)
            g = self.placement.group_of_range(msg.label_lo, msg.label_hi)
            if g is None or g not in groups:
                continue
            try:
                counts = partial_descriptor_from_proto(msg, self.places.n_labels, self.limits).counts
            except LimitExceededError as e:
                # Stored before the bounds existed (or were lowered); skipped, not deleted.
                skipped += 1
                fields = {"robot": msg.robot_id, "frame": msg.frame_index, "reason": str(e)}
                self.ctx.log.warning("stored slice over the bounds skipped", extra={"fields": fields})
                continue
            # A log written before stores were idempotent may hold a frame twice: the last wins.
            self.indexes[g].add(msg.robot_id, msg.frame_index, counts)
            restored += 1
        return restored, skipped

    def _load_state(self) -> tuple[Placement, set[int]] | None:
        if self.state_path is None or not self.state_path.exists():
            return None
        try:
            state = pb.ShardState.FromString(self.state_path.read_bytes())
            placement = placement_from_proto(state.placement, self.places.n_labels)
        except (WireError, ValueError) as e:
            self.ctx.log.warning(f"placement state unreadable, starting from version 0: {e}")
            return None
        if placement.groups != self.groups:
            self.ctx.log.warning("placement state is for other label groups: starting from version 0")
            return None
        return placement, set(state.ready_groups) & set(range(len(self.groups)))

    def _save_state(self) -> None:
        """The placement followed and the groups held completely, atomically (a crash leaves
        the old file or the new one)."""
        if self.state_path is None:
            return
        state = pb.ShardState(placement=placement_to_proto(self.placement), ready_groups=sorted(self.ready))
        tmp = self.state_path.with_name(self.state_path.name + ".tmp")
        tmp.write_bytes(state.SerializeToString())
        os.replace(tmp, self.state_path)

    def _update_gauges(self) -> None:
        self.metrics.stored_descriptors.set(self.stored)
        self.metrics.placement_version.set(self.placement.version)
        self.metrics.groups.labels("owner").set(len(self.placement.groups_of(self.shard)))
        self.metrics.groups.labels("learner").set(len(self.placement.learning(self.shard)))

    def state(self, known_version: int | None = None) -> pb.ShardState:
        """What this shard follows and holds; the placement itself is left out when it is
        ``known_version`` or older (the asker has it, or a newer one: only a newer placement
        is news to it, and a hundred shards' placements at every coordinator tick, from every
        shard to every other as a swarm starts, or to every querier after a placement change,
        were most of the index's traffic). Confirmed or not: no one follows the placement of
        a shard that is not confirmed, and ``confirmed`` says which it is."""
        query_calls, query_cpu_s = self.ctx.metrics.cost("query").snapshot()
        store_calls, store_cpu_s = self.ctx.metrics.cost("store").snapshot()
        with self.lock:
            known = known_version is not None and self.placement.version <= known_version
            return pb.ShardState(
                placement=None if known else placement_to_proto(self.placement),
                placement_version=self.placement.version,
                query_calls=query_calls,
                query_cpu_s=query_cpu_s,
                store_calls=store_calls,
                store_cpu_s=store_cpu_s,
                shard_id=self.shard,
                ready_groups=sorted(self.ready),
                served_groups=[g for g, n in enumerate(self.served) if n],
                served_queries=[n for n in self.served if n],
                confirmed=self.confirmed,
                draining=self.draining,
            )

    def follow(self, placement: Placement, *, confirm: bool = True) -> bool:
        """Follow ``placement`` (a newer one, or the same to confirm it): groups gained get
        an index (filled from this shard's own log, then copied from an owner when
        learning), groups let go are dropped from memory (their records stay in the log).
        False when ``placement`` is older than the one followed."""
        if placement.groups != self.groups:
            raise InvalidArgument("the placement's label groups are not this swarm's")
        with self.lock:
            if placement.version < self.placement.version:
                return False
            old = set(self.indexes)
            owned = set(placement.groups_of(self.shard))
            learning = set(placement.learning(self.shard))
            gained = (owned | learning) - old
            for g in old - owned - learning:
                del self.indexes[g]
                self.ready.discard(g)
            for g in gained:
                self.indexes[g] = RangeIndex(*self.groups[g], self.bus.n_robots)
            if gained:
                self._replay_log(gained)
            # A group owned without having been learned is one this shard held when it went
            # away (kept listed while no replica was left): its own records are all there is.
            self.ready |= owned - learning
            self.ready -= learning - self.ready
            self.placement = placement
            self.confirmed = self.confirmed or confirm
            self.placement_changed.notify_all()
            self._save_state()
            self._update_gauges()
            copy = sorted(g for g in learning if g not in self.ready and g not in self.syncing)
            self.syncing |= set(copy)
        for g in copy:
            threading.Thread(target=self._copy_group, args=(g,), name=f"copy-group-{g}", daemon=True).start()
        return True

    def follow_own(self, placement: Placement, reason: int) -> None:
        """Follow a placement this shard's coordinator computed, counted as published (by
        ``reason``, a ``PlacementReason``)."""
        self.follow(placement)
        self.metrics.placements_published.labels(reason=reason_name(reason)).inc()

    # --- copying a group (a learner) ----------------------------------------------------

    def _copy_group(self, group: int) -> None:
        """Page through an owner's descriptors of ``group`` until it has sent everything it
        held when asked; then the group is ready (the coordinator promotes this shard).
        Another owner is tried when one fails; the placement moving on ends the copy."""
        page = self.index_settings.transfer_page
        caller = self.ctx.caller
        try:
            while not self.ctx.stop.is_set():
                with self.lock:
                    p = self.placement
                    if group not in p.learning(self.shard):
                        return
                    sources = [o for o in p.owners[group] if o != self.shard]
                if self._copy_from(group, sources, p.version, page, caller):
                    with self.lock:
                        if group in self.placement.learning(self.shard):
                            self.ready.add(group)
                            self._save_state()
                    self.ctx.log.info("group copied", extra={"fields": {"group": group}})
                    return
                self.ctx.stop.wait(0.2)
        finally:
            with self.lock:
                self.syncing.discard(group)

    def _copy_from(self, group: int, sources: list[int], version: int, page: int, caller: object) -> bool:
        from swarmrec.runtime.rpc import Caller

        assert isinstance(caller, Caller)
        for source in sources:
            row = 0
            try:
                while not self.ctx.stop.is_set():
                    req = pb.TransferRequest(
                        group=group, placement_version=version, start_row=row, max_records=page
                    )
                    key = keys.endpoint(self.bus.swarm, "index-shard", source, "transfer")
                    reply = caller.call(key, req, pb.TransferReply, target_robot=source, endpoint="transfer")
                    self._take(group, reply.records)
                    row = reply.next_row
                    if reply.done:
                        return True
            except RemoteError as e:
                # The owner is not at our version yet, or lost the group: try the next one.
                self.ctx.log.info(f"copy of group {group} from shard {source}: {e}")
            except CallError as e:
                self.ctx.log.info(f"copy of group {group} from shard {source} failed: {e}")
        return False

    def _take(self, group: int, records: list[pb.PartialDescriptor]) -> None:
        """Copied slices into ``group``'s index and this shard's log (a restart keeps them)."""
        with self.lock:
            index = self.indexes.get(group)
            if index is None:
                return
            for msg in records:
                if (msg.label_lo, msg.label_hi) != self.groups[group]:
                    raise RemoteError("transfer", 2, "a copied slice is not of the group asked for")
                part = partial_descriptor_from_proto(msg, self.places.n_labels, self.limits)
                if index.get(msg.robot_id, msg.frame_index) is not None or msg.robot_id >= self.bus.n_robots:
                    continue  # stored already (a new store got here first: same content)
                self.store_log.append(encode(msg))
                index.add(msg.robot_id, msg.frame_index, part.counts)
                self.metrics.handoff_records.inc()
            self.metrics.stored_descriptors.set(self.stored)

    # --- the ServiceBase hooks ---------------------------------------------------------

    def member_info(self) -> pb.MemberInfo:
        with self.lock:
            owned = self.placement.groups_of(self.shard)
            lo, hi = self.groups[owned[0]] if owned else (0, 0)
            return pb.MemberInfo(
                label_lo=lo,
                label_hi=hi,
                stored_items=self.stored,
                n_labels=self.places.n_labels,
                label_ranges=[b for g in owned for b in self.groups[g]],
            )

    def serving(self, ready: bool) -> None:
        if ready:
            self.coordinator.start()
        else:
            # Still serving (the runner stops the endpoints after this): hand the groups on first.
            self.drain()
            self.coordinator.stop()

    def drain(self) -> None:
        """Before stopping, let the coordinator move this shard's groups to the others (a
        scale-down loses nothing even when a group's other replica goes too): wait until
        this shard holds no group, for at most ``drain_timeout_s``. At once when no other
        shard stays (the whole swarm is stopping) or nothing is held.

        Whether anyone stays is read from the draining tokens (:func:`keys.draining`) the
        stopping shards declare, never by asking every shard: when a whole swarm of a
        hundred shards stops, a hundred such rounds of a hundred requests each took the
        processes past their time to stop."""
        self.draining = True
        with contextlib.suppress(zenoh.ZError):  # a session already closed: nothing to tell
            self._draining_token = self.ctx.session.liveliness().declare_token(
                keys.draining(self.bus.swarm, "index-shard", self.shard)
            )
        deadline = time.monotonic() + self.index_settings.drain_timeout_s
        waited = False
        while time.monotonic() < deadline:
            with self.lock:
                holds = bool(self.placement.groups_of(self.shard) or self.placement.learning(self.shard))
            if not holds:
                break
            if not self.coordinator.anyone_stays():
                break  # nobody stays to take the groups
            waited = True
            time.sleep(0.2)
        if waited:
            fields = {"version": self.placement.version, "groups": self.placement.groups_of(self.shard)}
            self.ctx.log.info("drained", extra={"fields": fields})

    def close(self) -> None:
        self.coordinator.stop()
        if self._draining_token is not None:
            with contextlib.suppress(zenoh.ZError):  # the session closed first
                self._draining_token.undeclare()  # type: ignore[no-untyped-call]  # untyped in zenoh's stub
            self._draining_token = None

    # --- requests ----------------------------------------------------------------------

    def _group_for(
        self, desc: pb.PartialDescriptor, version: int, *, storing: bool
    ) -> tuple[int, DescriptorSlice]:
        """The group ``desc`` belongs to, checked against the placement followed (under the lock)."""
        if not self.confirmed:
            self.metrics.refused.labels("unconfirmed").inc()
            raise FailedPrecondition(
                f"shard {self.shard} restarted and waits for the coordinator to confirm its placement: retry"
            )
        if 0 < version - self.placement.version <= 4:
            # The coordinator sends a new placement to every shard at once; the sender learned
            # it from one that got it first. Wait for ours (the lock is released meanwhile);
            # a version far ahead is no adoption on its way, and is refused at once.
            self.placement_changed.wait_for(lambda: self.placement.version >= version, timeout=BEHIND_WAIT_S)
        if version != self.placement.version:
            self.metrics.refused.labels("stale").inc()
            raise FailedPrecondition(
                f"routed with placement version {version}, shard {self.shard} follows "
                f"{self.placement.version}: refresh the placement and route again"
            )
        part = partial_descriptor_from_proto(desc, self.places.n_labels, self.limits)
        g = self.placement.group_of_range(part.lo, part.hi)
        if g is None:
            raise InvalidArgument(f"labels [{part.lo}, {part.hi}) are not a label group of this swarm")
        holds = g in self.placement.groups_of(self.shard) or (
            storing and g in self.placement.learning(self.shard)
        )
        if not holds:
            self.metrics.refused.labels("not_held").inc()
            raise FailedPrecondition(
                f"shard {self.shard} does not {'hold' if storing else 'answer for'} label group {g} "
                f"at placement version {version}"
            )
        return g, part

    def _check_ids(self, desc: pb.PartialDescriptor) -> None:
        if desc.robot_id >= self.bus.n_robots:
            raise InvalidArgument(f"robot {desc.robot_id} is not in this swarm of {self.bus.n_robots} robots")
        if desc.frame_index >= MAX_FRAME_INDEX or desc.query_step >= MAX_FRAME_INDEX:
            raise InvalidArgument(f"frame index and query step must be below {MAX_FRAME_INDEX}")

    def _store(self, g: int, desc: pb.PartialDescriptor, counts: npt.NDArray[np.int64]) -> None:
        """Store a slice unless stored already with the same content (caller holds the lock)."""
        index = self.indexes[g]
        stored = index.get(desc.robot_id, desc.frame_index)
        if stored is not None:
            if not np.array_equal(stored, counts):
                raise AlreadyExists(
                    f"frame {desc.frame_index} of robot {desc.robot_id} is already stored here with "
                    "another slice; stores are idempotent (the same slice again is accepted)"
                )
            return
        if desc.frame_index > index.frames_of(desc.robot_id) + MAX_FRAME_GAP:
            raise InvalidArgument(f"frame index more than {MAX_FRAME_GAP} frames past what is stored")
        # Stored before the answer leaves: an acknowledged frame survives a crash.
        self.store_log.append(encode(desc))
        index.add(desc.robot_id, desc.frame_index, counts)
        self.metrics.stored_descriptors.set(self.stored)

    def query(self, req: pb.PartialQuery, ctx: RequestContext) -> pb.CandidatesReply:
        check_fields(req, "descriptor")
        if not req.read_only:
            ctx.require_own(req.descriptor.robot_id, req.descriptor.frame_index)
        if req.n_ret > MAX_N_RET:
            raise InvalidArgument(f"n_ret must be at most {MAX_N_RET}, got {req.n_ret}")
        n_ret = req.n_ret or self.n_ret
        desc = req.descriptor
        self._check_ids(desc)
        # A read-only lookup (a client's) searches everything even in a lock-step swarm.
        lockstep = self.places.lockstep and not req.read_only
        before = (desc.query_step or desc.frame_index) if lockstep else None
        with self.lock:
            g, part = self._group_for(desc, req.placement_version, storing=False)
            if not part.counts.any():
                raise InvalidArgument("partial descriptor has no labels; send only non-empty slices")
            index = self.indexes[g]
            if desc.frame_index > index.frames_of(desc.robot_id) + MAX_FRAME_GAP or (
                before is not None and before > index.frames + MAX_FRAME_GAP
            ):
                raise InvalidArgument(
                    f"frame index or step more than {MAX_FRAME_GAP} frames past what is stored"
                )
            stored = None if req.read_only else index.get(desc.robot_id, desc.frame_index)
            if stored is not None and not np.array_equal(stored, part.counts):
                raise AlreadyExists(
                    f"frame {desc.frame_index} of robot {desc.robot_id} is already stored here with "
                    "another slice; stores are idempotent (the same slice again is accepted)"
                )
            # A slice already here (a replica's store can come before its query's retry)
            # is accepted when the same, and its frame is never its own candidate.
            own = None if stored is None else (desc.robot_id, desc.frame_index)
            found = index.candidates(part.counts, n_ret, before=before, exclude=own)
            if not req.read_only:
                self._store(g, desc, part.counts)
            if not req.read_only:
                # The load the placement moves groups for is the robots': a client's lookups
                # (read-only, anyone may send them) must not move the index.
                self.served[g] += 1
        self.metrics.partial_queries.inc()
        if not req.read_only:
            self.metrics.group_queries.labels(str(g)).inc()
        return candidates_to_proto(
            req.query_id,
            (Candidate(c.robot, c.frame, c.score) for c in found),
            include_scores=req.include_scores,
        )

    def lookup(self, req: pb.PartialQuery, ctx: RequestContext) -> pb.CandidatesReply:
        check_fields(req, "descriptor")
        if not req.read_only:
            raise InvalidArgument("lookup never stores: send read_only = true (descriptors use query)")
        return self.query(req, ctx)

    def store(self, req: pb.ShardStore, ctx: RequestContext) -> pb.StoreReply:
        check_fields(req, "descriptor")
        ctx.require_own(req.descriptor.robot_id, req.descriptor.frame_index)
        desc = req.descriptor
        self._check_ids(desc)
        with self.lock:
            g, part = self._group_for(desc, req.placement_version, storing=True)
            if not part.counts.any():
                raise InvalidArgument("partial descriptor has no labels; send only non-empty slices")
            self._store(g, desc, part.counts)
            return pb.StoreReply(stored_frames=self.stored)

    def placement_state(self, req: pb.PlacementRequest, _ctx: RequestContext) -> pb.ShardState:
        check_fields(req)
        return self.state(req.known_version if req.HasField("known_version") else None)

    def adopt(self, req: pb.AdoptRequest, ctx: RequestContext) -> pb.ShardState:
        check_fields(req, "placement")
        # Only the lowest live shard coordinates: a placement from a shard that knows less
        # (it has not seen a lower one yet) is refused, so two tables never compete.
        lowest = self.coordinator.lowest_live()
        if ctx.caller_robot is None or ctx.caller_robot > lowest:
            raise FailedPrecondition(
                f"placements come from the coordinator, the lowest live shard ({lowest}), "
                f"not from {ctx.caller_robot}"
            )
        placement = placement_from_proto(req.placement, self.places.n_labels)
        if not self.follow(placement):
            raise FailedPrecondition(
                f"placement version {placement.version} is older than the {self.placement.version} followed"
            )
        return self.state(known_version=placement.version)  # the coordinator sent it: not back

    def transfer(self, req: pb.TransferRequest, _ctx: RequestContext) -> pb.TransferReply:
        check_fields(req)
        if req.group >= len(self.groups):
            raise InvalidArgument(f"group {req.group} is not one of the {len(self.groups)} label groups")
        if req.start_row >= _MAX_ROW:
            raise InvalidArgument(f"start_row must be below {_MAX_ROW}")
        page = min(req.max_records or self.index_settings.transfer_page, self.index_settings.transfer_page)
        with self.lock:
            if self.placement.version < req.placement_version or not self.confirmed:
                raise FailedPrecondition(
                    f"shard {self.shard} follows placement version {self.placement.version}, "
                    f"not yet {req.placement_version}: ask again"
                )
            if req.group not in self.placement.groups_of(self.shard) or req.group not in self.ready:
                raise FailedPrecondition(f"shard {self.shard} does not own label group {req.group}")
            index = self.indexes[req.group]
            rows = index.rows(int(req.start_row), int(req.start_row) + page)
            next_row = min(int(req.start_row) + page, index.size)
            done = next_row >= index.size
        lo, hi = self.groups[req.group]
        records = [
            partial_descriptor_to_proto(
                _dense(counts, lo, self.places.n_labels), lo, hi, robot=r, frame=f, query_step=0
            )
            for r, f, counts in rows
        ]
        return pb.TransferReply(group=req.group, records=records, next_row=next_row, done=done)

    ENDPOINTS = (
        Endpoint(
            "query",
            pb.PartialQuery,
            pb.CandidatesReply,
            query,
            "candidates for a descriptor slice of a group this shard owns; stored unless read_only",
        ),
        Endpoint(
            "lookup",
            pb.PartialQuery,
            pb.CandidatesReply,
            lookup,
            "candidates for a descriptor slice, never stored (read_only must be set): clients' endpoint",
        ),
        Endpoint(
            "store",
            pb.ShardStore,
            pb.StoreReply,
            store,
            "store a slice without a search (the other owners and the learners of its group)",
        ),
        Endpoint(
            "placement",
            pb.PlacementRequest,
            pb.ShardState,
            placement_state,
            "the placement this shard follows, the groups it holds and the load it served",
        ),
        Endpoint(
            "adopt",
            pb.AdoptRequest,
            pb.ShardState,
            adopt,
            "follow the coordinator's newer placement (shards only)",
        ),
        Endpoint(
            "transfer",
            pb.TransferRequest,
            pb.TransferReply,
            transfer,
            "a page of a group's descriptors, for a shard copying the group (shards only)",
        ),
    )


def _dense(counts: npt.NDArray[np.float64], lo: int, n_labels: int) -> npt.NDArray[np.int64]:
    """A slice's counts as the full-length descriptor partial_descriptor_to_proto cuts from."""
    full = np.zeros(n_labels, np.int64)
    full[lo : lo + counts.shape[0]] = counts.astype(np.int64)
    return full
