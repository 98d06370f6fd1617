"""The two-step decentralized query (paper Sec. III-C/D) over the bus.

1. The query frame's semantic descriptor is cut by label range; each
   non-empty slice goes to the index shard that owns the range, all at once.
2. The shards answer with their best candidates. The ``n_fq`` robots with
   the most candidates, plus the querying robot, get the full constellation
   and check their candidate frames geometrically, all at once.

A peer that does not answer (gone, crashed, timed out) or answers with an
error is recorded in the report and the query goes on with the others: an
empty answer is never taken for "no match". The report also records where
each candidate stopped (:mod:`swarmrec.core.funnel`); that costs no byte
between robots.

The descriptor service runs this for its robot's frames; the client library
runs it read-only (nothing is stored) to ask a running swarm.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from swarmrec.core.descriptor import semantic_descriptor
from swarmrec.core.funnel import Reason, classify, verifier_failure
from swarmrec.core.presets import Preset
from swarmrec.core.selection import select_robots
from swarmrec.core.types import Constellation
from swarmrec.errors import CallError, ErrorCode, RemoteError, WireError
from swarmrec.runtime import keys
from swarmrec.runtime.rpc import Caller, Pending
from swarmrec.services.routing import Routing
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import (
    candidates_from_proto,
    match_scores,
    outcomes_to_proto,
    partial_descriptor_to_proto,
)

__all__ = ["ROUTE_ATTEMPTS", "QueryPlan", "ask_shards", "two_step_query"]

IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True)
class QueryPlan:
    """What a querier must know of the swarm."""

    swarm: str
    n_robots: int
    bounds: IntArray
    n_labels: int
    preset: Preset
    #: Where each label group lives (the index placement), kept fresh.
    routing: Routing
    #: n_ret the shards are configured with (None: unknown, always send it).
    shard_n_ret: int | None = None


#: Rounds of asking a group's owners: the first owner, then (after a refresh or a
#: failure) the next, at most this many times in all.
ROUTE_ATTEMPTS = 3


@dataclass
class _GroupAsk:
    """One group's partial query in flight."""

    group: int
    request: pb.PartialQuery
    owners: list[int]
    shard: int = -1
    pending: Pending | None = None
    tried: list[int] = field(default_factory=list)


def _send(caller: Caller, plan: QueryPlan, ask: _GroupAsk, shard: int, version: int, read_only: bool) -> None:
    ask.shard = shard
    ask.tried.append(shard)
    ask.request.placement_version = version
    # A read-only query goes to the shards' lookup, which the router lets clients call.
    key = keys.endpoint(plan.swarm, "index-shard", shard, "lookup" if read_only else "query")
    ask.pending = caller.start(key, ask.request, target_robot=shard, endpoint="shard_query")


def ask_shards(
    caller: Caller,
    plan: QueryPlan,
    desc: npt.NDArray[np.int64],
    wire: pb.Constellation,
    *,
    query_id: int,
    read_only: bool,
    include_scores: bool,
    report: pb.QueryReport,
) -> tuple[list[tuple[int, pb.CandidatesReply]], dict[int, int]]:
    """Step 1: every non-empty slice to an owner of its label group, all in flight together.

    A shard that says the placement moved on makes the querier refresh it and ask
    again; one that does not answer is suspected and the group's next owner is asked.
    Returns the groups' replies (group, reply) and, per group answered, the shard that
    answered (it stored the slice with its search). A group no owner answered for adds
    the shards asked to the report's failed shards.
    """
    routing = plan.routing
    placement = routing.placement
    asks: list[_GroupAsk] = []
    for g, (lo, hi) in enumerate(placement.groups):
        if not desc[lo:hi].any():
            continue
        request = pb.PartialQuery(
            query_id=query_id,
            # n_ret 0: the shards' own, which the swarm shares (costs no byte).
            n_ret=0 if plan.preset.n_ret == plan.shard_n_ret else plan.preset.n_ret,
            # query_step 0: the step is the frame index (costs no byte on the wire).
            descriptor=partial_descriptor_to_proto(
                desc, lo, hi, robot=wire.robot_id, frame=wire.frame_index, query_step=0
            ),
            read_only=read_only,
            include_scores=include_scores,
        )
        owners = routing.owners_in_order(placement, g, wire.robot_id, wire.frame_index)
        ask = _GroupAsk(g, request, owners)
        asks.append(ask)
        if owners:
            _send(caller, plan, ask, owners[0], placement.version, read_only)
    replies: list[tuple[int, pb.CandidatesReply]] = []
    answered: dict[int, int] = {}
    for attempt in range(ROUTE_ATTEMPTS):
        retry: list[_GroupAsk] = []
        stale: set[int] = set()  # the shards that refused as routed with another placement
        for ask in asks:
            if ask.pending is None:
                continue
            pending, ask.pending = ask.pending, None
            try:
                reply = pending.result(pb.CandidatesReply)
            except RemoteError as e:
                if e.code != ErrorCode.FAILED_PRECONDITION:
                    continue  # a refusal of the request itself: another owner would refuse it too
                stale.add(ask.shard)  # routed with another placement than the shard's
                retry.append(ask)
                continue
            except CallError:
                routing.suspect(ask.shard)
                retry.append(ask)
                continue
            replies.append((ask.group, reply))
            answered[ask.group] = ask.shard
        if not retry or attempt == ROUTE_ATTEMPTS - 1:
            break
        moved = False
        if stale:
            before = placement.version
            placement = routing.refresh(caller, from_shards=stale, routed=before)
            moved = placement.version != before
        for ask in retry:
            owners = routing.owners_in_order(placement, ask.group, wire.robot_id, wire.frame_index)
            # The placement moved on: its first owner. Otherwise (a failure, or a shard behind
            # the swarm or not yet confirmed) the next owner not asked yet.
            fresh = owners if moved else [o for o in owners if o not in ask.tried]
            if fresh:
                _send(caller, plan, ask, fresh[0], placement.version, read_only)
    for ask in asks:
        if ask.group not in answered:
            for shard in ask.tried or ask.owners[:1]:
                if shard not in report.failed_shard_robot_ids:
                    report.failed_shard_robot_ids.append(shard)
    return replies, answered


def two_step_query(
    caller: Caller,
    plan: QueryPlan,
    constellation: Constellation,
    wire: pb.Constellation,
    *,
    query_id: int,
    read_only: bool,
    self_robot: int | None,
    include_scores: bool = False,
    on_unstored: Callable[[pb.PartialDescriptor], None] | None = None,
) -> pb.QueryReport:
    """Run both steps for one frame; ``wire`` is its wire form (robot, frame, objects).

    ``query_id`` 0 costs no byte: zenoh pairs each reply with its query already.
    Unless ``read_only``, every slice is stored by every owner and learner of its group:
    the owner that answered stored it with its search, the others get a
    :class:`ShardStore` while the verifiers work; a slice some shard did not acknowledge
    goes to ``on_unstored`` (the descriptor's queue of pending stores retries it).
    """
    t0 = time.perf_counter()
    report = pb.QueryReport(robot_id=wire.robot_id, frame_index=wire.frame_index, queried=True)
    desc = semantic_descriptor(constellation, plan.n_labels)
    replies, answered = ask_shards(
        caller,
        plan,
        desc,
        wire,
        query_id=query_id,
        read_only=read_only,
        include_scores=include_scores,
        report=report,
    )
    cand_robot: list[int] = []
    cand_frame: list[int] = []
    for g, reply in replies:
        try:
            found = candidates_from_proto(reply, plan.n_labels)
        except WireError:
            report.failed_shard_robot_ids.append(answered[g])
            continue
        before = len(cand_robot)
        for c in found:
            if c.robot_id < plan.n_robots:
                cand_robot.append(c.robot_id)
                cand_frame.append(c.frame_index)
        report.shard_candidates.add(robot_id=answered[g], n_candidates=len(cand_robot) - before, group=g)
    report.n_candidates = len(cand_robot)
    # Step 2: the full constellation to the chosen robots that have candidates.
    robots_arr = np.asarray(cand_robot, np.int64)
    frames_arr = np.asarray(cand_frame, np.int64)
    chosen = select_robots(robots_arr, plan.preset.n_fq, self_robot)
    # The verifiers need the objects, not the frame's name: frame_id stays home. A robot
    # or frame of 0 is left absent (a verify query may, and reads it as 0), so the
    # presence a store requires costs no byte between robots. A robot of the swarm sends
    # another robot's verifier the objects alone: the verifier orders a pair by (robot,
    # frame), takes the query's robot from the caller's id, and the robots differ, so the
    # frame cannot matter (5 bytes a request less).
    query = pb.Constellation(
        robot_id=wire.robot_id or None,
        frame_index=wire.frame_index or None,
        labels=wire.labels,
        positions_mm=wire.positions_mm,
        positions_m=wire.positions_m,
    )
    objects_only = pb.Constellation(
        labels=wire.labels, positions_mm=wire.positions_mm, positions_m=wire.positions_m
    )
    verifying: list[tuple[int, Pending]] = []
    for r in chosen.tolist():
        frames = np.unique(frames_arr[robots_arr == r])
        if frames.shape[0] == 0:
            continue  # a robot chosen to fill the list has nothing to verify
        report.verified_robot_ids.append(r)
        sent = objects_only if self_robot is not None and r != self_robot else query
        request = pb.VerifyRequest(query_id=query_id, query=sent, candidate_frame_indices=frames.tolist())
        key = keys.endpoint(plan.swarm, "verifier", r, "verify")
        verifying.append((r, caller.start(key, request, target_robot=r, endpoint="verify")))
    # The replicas' stores leave after the verify requests, so they wait on no store being
    # sent (starting one costs the querier ~0.25 ms); they are stored while the verifiers work.
    stores = [] if read_only else start_replica_stores(caller, plan, desc, wire, answered)
    pairs: list[pb.VerifiedPair] = []
    failures: dict[int, Reason] = {}
    for r, pending in verifying:
        try:
            vreply = pending.result(pb.VerifyReply)
        except CallError as e:
            report.failed_verifier_robot_ids.append(r)
            failures[r] = verifier_failure(e)
            continue
        if vreply.robot_id != r:
            caller.count_failure("verify", RemoteError.reason)
            report.failed_verifier_robot_ids.append(r)
            failures[r] = Reason.VERIFIER_ERROR
            continue
        try:
            scored = [(m, *match_scores(m)) for m in vreply.matches]
        except WireError:
            caller.count_failure("verify", RemoteError.reason)
            report.failed_verifier_robot_ids.append(r)
            failures[r] = Reason.VERIFIER_ERROR
            continue
        for m, score, semantic in scored:
            pairs.append(
                pb.VerifiedPair(
                    match_robot_id=r,
                    match_frame_index=m.frame_index,
                    score=score,
                    semantic_score=semantic,
                    n_matched=m.n_matched,
                )
            )
    pairs.sort(key=lambda p: (-p.score, p.match_robot_id, p.match_frame_index))
    report.matches.extend(pairs)
    matched = [(p.match_robot_id, p.match_frame_index, p.score) for p in pairs]
    funnel = classify(zip(cand_robot, cand_frame, strict=True), report.verified_robot_ids, failures, matched)
    report.candidates.extend(outcomes_to_proto(funnel))
    if not read_only:
        finish_replica_stores(caller, stores, desc, wire, plan, answered, on_unstored)
    report.duration_us = min(int((time.perf_counter() - t0) * 1e6), 2**32 - 1)
    return report


@dataclass
class _Store:
    group: int
    shard: int
    pending: Pending
    #: The placement version it was routed with.
    version: int


def start_replica_stores(
    caller: Caller,
    plan: QueryPlan,
    desc: npt.NDArray[np.int64],
    wire: pb.Constellation,
    answered: dict[int, int],
) -> list[_Store]:
    """A :class:`ShardStore` of each answered group's slice to its other owners and learners."""
    placement = plan.routing.placement
    stores = []
    for g, served_by in answered.items():
        lo, hi = placement.groups[g]
        msg = pb.ShardStore(
            descriptor=partial_descriptor_to_proto(
                desc, lo, hi, robot=wire.robot_id, frame=wire.frame_index, query_step=0
            ),
            placement_version=placement.version,
        )
        for shard in placement.store_targets(g):
            if shard == served_by:
                continue
            key = keys.endpoint(plan.swarm, "index-shard", shard, "store")
            stores.append(
                _Store(
                    g,
                    shard,
                    caller.start(key, msg, target_robot=shard, endpoint="shard_store"),
                    placement.version,
                )
            )
    return stores


def finish_replica_stores(
    caller: Caller,
    stores: list[_Store],
    desc: npt.NDArray[np.int64],
    wire: pb.Constellation,
    plan: QueryPlan,
    answered: dict[int, int],
    on_unstored: Callable[[pb.PartialDescriptor], None] | None,
) -> None:
    """Collect the replicas' acknowledgements. A shard that says the placement moved on
    gets the slice again at once, routed with the refreshed placement to every owner and
    learner of its group (so a lock-step step ends with every replica holding the frame,
    handoff or not); each slice some shard still did not acknowledge (and each slice no
    owner answered for) goes to ``on_unstored`` once."""
    groups = plan.routing.placement.groups
    missed: set[int] = {g for g, (lo, hi) in enumerate(groups) if desc[lo:hi].any() and g not in answered}
    for attempt in range(ROUTE_ATTEMPTS):
        stale: set[int] = set()
        refused_by: set[int] = set()
        routed: int | None = None
        for st in stores:
            try:
                st.pending.result(pb.StoreReply)
            except RemoteError as e:
                if e.code == ErrorCode.FAILED_PRECONDITION:
                    stale.add(st.group)
                    refused_by.add(st.shard)
                    routed = st.version if routed is None else min(routed, st.version)
                elif e.code != ErrorCode.ALREADY_EXISTS:  # stored there with other content: not ours to fix
                    missed.add(st.group)
            except CallError:
                missed.add(st.group)
        stale -= missed
        if not stale:
            break
        if attempt == ROUTE_ATTEMPTS - 1:
            missed |= stale
            break
        placement = plan.routing.refresh(caller, from_shards=refused_by, routed=routed)
        stores = []
        for g in sorted(stale):
            lo, hi = groups[g]
            msg = pb.ShardStore(
                descriptor=partial_descriptor_to_proto(
                    desc, lo, hi, robot=wire.robot_id, frame=wire.frame_index, query_step=0
                ),
                placement_version=placement.version,
            )
            for shard in placement.store_targets(g):
                key = keys.endpoint(plan.swarm, "index-shard", shard, "store")
                stores.append(
                    _Store(
                        g,
                        shard,
                        caller.start(key, msg, target_robot=shard, endpoint="shard_store"),
                        placement.version,
                    )
                )
    if on_unstored is None:
        return
    for g in sorted(missed):
        lo, hi = groups[g]
        on_unstored(
            partial_descriptor_to_proto(
                desc, lo, hi, robot=wire.robot_id, frame=wire.frame_index, query_step=0
            )
        )
