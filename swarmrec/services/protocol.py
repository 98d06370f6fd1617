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
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from swarmrec.core.descriptor import semantic_descriptor
from swarmrec.core.funnel import Reason, classify, verifier_failure
from swarmrec.core.presets import Preset
from swarmrec.core.selection import select_robots
from swarmrec.core.types import Constellation
from swarmrec.errors import CallError, RemoteError, WireError
from swarmrec.runtime import keys
from swarmrec.runtime.rpc import Caller, Pending
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import (
    candidates_from_proto,
    match_scores,
    outcomes_to_proto,
    partial_descriptor_to_proto,
)

__all__ = ["QueryPlan", "two_step_query"]

IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True)
class QueryPlan:
    """What a querier must know of the swarm."""

    swarm: str
    n_robots: int
    bounds: IntArray
    n_labels: int
    preset: Preset
    #: n_ret the shards are configured with (None: unknown, always send it).
    shard_n_ret: int | None = None


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
) -> pb.QueryReport:
    """Run both steps for one frame; ``wire`` is its wire form (robot, frame, objects).

    ``query_id`` 0 costs no byte: zenoh pairs each reply with its query already.
    """
    t0 = time.perf_counter()
    report = pb.QueryReport(robot_id=wire.robot_id, frame_index=wire.frame_index, queried=True)
    desc = semantic_descriptor(constellation, plan.n_labels)
    # Step 1: every non-empty slice to its shard, all in flight together.
    asked: list[tuple[int, Pending]] = []
    for k in range(plan.bounds.shape[0] - 1):
        lo, hi = int(plan.bounds[k]), int(plan.bounds[k + 1])
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
        # A read-only query goes to the shards' lookup, which the router lets clients call.
        key = keys.endpoint(plan.swarm, "index-shard", k, "lookup" if read_only else "query")
        asked.append((k, caller.start(key, request, target_robot=k, endpoint="shard_query")))
    cand_robot: list[int] = []
    cand_frame: list[int] = []
    for k, pending in asked:
        try:
            reply = pending.result(pb.CandidatesReply)
            found = candidates_from_proto(reply, plan.n_labels)
        except (CallError, WireError):
            report.failed_shard_robot_ids.append(k)
            continue
        before = len(cand_robot)
        for c in found:
            if c.robot_id < plan.n_robots:
                cand_robot.append(c.robot_id)
                cand_frame.append(c.frame_index)
        report.shard_candidates.add(robot_id=k, n_candidates=len(cand_robot) - before)
    report.n_candidates = len(cand_robot)
    # Step 2: the full constellation to the chosen robots that have candidates.
    robots_arr = np.asarray(cand_robot, np.int64)
    frames_arr = np.asarray(cand_frame, np.int64)
    chosen = select_robots(robots_arr, plan.preset.n_fq, self_robot)
    # The verifiers need the objects, not the frame's name: frame_id stays home. A robot
    # or frame of 0 is left absent (a verify query may, and reads it as 0), so the
    # presence a store requires costs no byte between robots.
    query = pb.Constellation(
        robot_id=wire.robot_id or None,
        frame_index=wire.frame_index or None,
        labels=wire.labels,
        positions_mm=wire.positions_mm,
        positions_m=wire.positions_m,
    )
    verifying: list[tuple[int, Pending]] = []
    for r in chosen.tolist():
        frames = np.unique(frames_arr[robots_arr == r])
        if frames.shape[0] == 0:
            continue  # a robot chosen to fill the list has nothing to verify
        report.verified_robot_ids.append(r)
        request = pb.VerifyRequest(query_id=query_id, query=query, candidate_frame_indices=frames.tolist())
        key = keys.endpoint(plan.swarm, "verifier", r, "verify")
        verifying.append((r, caller.start(key, request, target_robot=r, endpoint="verify")))
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
    report.duration_us = min(int((time.perf_counter() - t0) * 1e6), 2**32 - 1)
    return report
