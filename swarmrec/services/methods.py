"""What a client asks of the full-image, SLAM and landmark services, over any caller.

The Python client over zenoh (:class:`swarmrec.client.ZenohClient`) and the gRPC gateway
(:mod:`swarmrec.services.gateway_methods`, with a caller that ends at the call's deadline)
run the same functions, so the two transports answer alike; each returns the gateway's
reply message (``gateway_pb2``)::

    cluster_table      each place-owner/<r>/assignment: the owners' tables, the newest, agreed?
    place_query        route a unit descriptor by that table and the centres (nearest centre),
                       then the owner's read-only place-owner/<owner>/lookup
    place_loop_closures  place-owner/<r>/loop_closures
    slam_team          each slam/<r>/status
    slam_estimate      slam/<r>/estimate
    slam_map           each slam/<r>/estimate, merged (the newest solve's robots)
    landmark_round     each fusion/<r>/posterior of one round

"Each": the live services of the kind (a scatter of their ``info``), then one request to
each, sent together.

Everything a client reads is read-only: nothing here stores or starts anything. A scatter's
answers are at most one a robot, and a merged map
larger than :data:`MAX_MAP_BYTES` is refused (TOO_LARGE) rather than built.
"""

from __future__ import annotations

import functools
import json
import time
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Protocol, TypeVar

import numpy as np
import numpy.typing as npt

# protobuf ships no type stubs (see swarmrec/runtime/rpc.py for the two codes).
from google.protobuf.message import Message  # type: ignore[import-untyped, unused-ignore]

from swarmrec.errors import (
    CallError,
    ConfigError,
    ErrorCode,
    FailedPrecondition,
    InvalidArgument,
    NoReply,
    NotFound,
    RemoteError,
    RequestError,
    WireError,
)
from swarmrec.runtime import keys
from swarmrec.runtime.rpc import Caller, Outcome
from swarmrec.vpr.clusters import Assignment, Router, load_centres
from swarmrec.vpr.errors import StateFileError
from swarmrec.vpr.table import centres_digest, default_centres_path
from swarmrec.wire import messages as pb
from swarmrec.wire.gen.swarmrec.v1 import gateway_pb2
from swarmrec.wire.vpr import ENCODINGS, descriptor_from_wire, table_from_proto

__all__ = [
    "DEFAULT_WATCH_INTERVAL_MS",
    "MAX_MAP_BYTES",
    "WATCH_INTERVAL_MS",
    "Describer",
    "cluster_table",
    "descriptor_of_values",
    "estimate_position",
    "landmark_round",
    "place_loop_closures",
    "place_query",
    "slam_estimate",
    "slam_map",
    "slam_team",
    "terminal",
]

M = TypeVar("M", bound=Message)

#: The largest merged map built (bytes of its message): gRPC's send limit of the gateway.
MAX_MAP_BYTES = 1 << 24
#: How often a stream of a robot's estimate asks it, when the request does not say (ms) ...
DEFAULT_WATCH_INTERVAL_MS = 200
#: ... and the bounds a request may ask for: a client cannot make the gateway poll a robot
#: in a busy loop, nor hold a stream that never looks.
WATCH_INTERVAL_MS = (50, 10_000)

_TERMINAL = frozenset(
    {pb.SlamState.SLAM_STATE_DONE, pb.SlamState.SLAM_STATE_ABORTED, pb.SlamState.SLAM_STATE_FAILED}
)


class Describer(Protocol):
    """What describes an image (:class:`swarmrec.vpr.model.DescriptorModel`)."""

    def describe_frames(self, frames: npt.NDArray[np.uint8]) -> npt.NDArray[np.float32]: ...


def terminal(state: int) -> bool:
    """Whether a robot's solve in ``state`` has ended (done, aborted or failed)."""
    return state in _TERMINAL


def _one_per_robot(replies: Iterable[M], robot_of: str = "robot_id") -> list[M]:
    """Replies by robot, the first of each robot only."""
    seen: dict[int, M] = {}
    for reply in replies:
        seen.setdefault(int(getattr(reply, robot_of)), reply)
    return [seen[r] for r in sorted(seen)]


def _robots_of(caller: Caller, swarm: str, kind: str) -> list[int]:
    """The robots whose ``kind`` service answers its ``info`` now (which takes no argument:
    an empty message)."""
    key = keys.endpoint(swarm, kind, "*", "info")
    pending = caller.start(key, gateway_pb2.MembersRequest(), target_robot=None, scatter=True)
    return sorted({o.reply.robot_id for o in pending.gather(pb.MemberInfo) if o.reply is not None})


def _each_robot(
    caller: Caller, swarm: str, kind: str, endpoint: str, request: Message, reply_cls: type[M]
) -> list[Outcome[M]]:
    """One request to each live ``kind`` service, sent together, and each one's outcome, by
    robot. Not one scatter: under mutual TLS a scatter's error replies do not come back
    through the router (a direct request's do), and a robot's refusal is part of the answer."""
    robots = _robots_of(caller, swarm, kind)
    if not robots:
        raise NoReply(keys.endpoint(swarm, kind, "*", endpoint), f"no {kind} service is alive")
    pending = [
        caller.start(keys.endpoint(swarm, kind, r, endpoint), request, target_robot=None) for r in robots
    ]
    out: list[Outcome[M]] = []
    for p in pending:
        try:
            out.append(Outcome(p.result(reply_cls), None))
        except CallError as e:
            out.append(Outcome(None, e))
    return out


def _replies(outcomes: Sequence[Outcome[M]]) -> list[M]:
    """The replies; the first error when there is none."""
    replies = [o.reply for o in outcomes if o.reply is not None]
    if not replies:
        raise next(o.error for o in outcomes if o.error is not None)
    return replies


def _not_found(e: CallError | None) -> bool:
    return isinstance(e, RemoteError) and e.code == ErrorCode.NOT_FOUND


def _call(caller: Caller, key: str, request: Message, reply_cls: type[M], who: str) -> M:
    """One request; a robot without the service is NOT_FOUND (what a client asked for is not there)."""
    try:
        return caller.call(key, request, reply_cls, target_robot=None)
    except NoReply:
        raise NotFound(f"{who} is not alive") from None


# --- full-image place recognition -------------------------------------------------------


def cluster_table(caller: Caller, swarm: str) -> gateway_pb2.ClusterTableReply:
    """The live owners' tables: the newest one, and whether every owner holds it."""
    outcomes = _each_robot(
        caller, swarm, "place-owner", "assignment", pb.AssignmentRequest(), pb.AssignmentReply
    )
    owners = _one_per_robot(_replies(outcomes))
    newest = max(owners, key=lambda a: a.version)
    same = {(a.version, a.table_json, a.centres_sha256, a.dimension) for a in owners}
    return gateway_pb2.ClusterTableReply(
        version=newest.version,
        table_json=newest.table_json,
        centres_sha256=newest.centres_sha256,
        agreed=len(same) == 1,
        owners=owners,
    )


@functools.lru_cache(maxsize=4)
def _centres(path: str, k: int) -> tuple[npt.NDArray[np.float32], str]:
    """The k centres of a centres file and their digest (read once a file and k)."""
    c = load_centres(path, k)
    return c, centres_digest(c)


#: Routers of re-balanced tables, by the centres' digest and the table's version (a few).
_LIVE_ROUTERS: dict[tuple[str, int], Router] = {}


def _router(
    caller: Caller, swarm: str, table: gateway_pb2.ClusterTableReply, centres: str | Path | None
) -> Router:
    """The owners' routing: their table, with the centres read here (which must be theirs);
    a table re-balanced live (docs/vpr.md) has centres of its own, fetched from an owner."""
    try:
        assignment = Assignment.from_json(json.loads(table.table_json))
    except (ValueError, TypeError) as e:
        raise FailedPrecondition(f"the place owners' cluster table does not read: {e}") from None
    if table.version > 0:
        return _live_router(caller, swarm, table)
    try:
        path = str(centres) if centres else str(default_centres_path())
        c, digest = _centres(path, assignment.n_clusters)
    except (StateFileError, ConfigError) as e:
        raise FailedPrecondition(f"the centres to route by: {e}") from None
    if digest != table.centres_sha256:
        raise FailedPrecondition(
            f"the place owners route by centres {table.centres_sha256[:12]}..., the centres here "
            f"({path}) are {digest[:12]}...: give the swarm's vpr_centres"
        )
    return Router(c, assignment)


def _live_router(caller: Caller, swarm: str, table: gateway_pb2.ClusterTableReply) -> Router:
    """The router of a re-balanced table: its centres as an owner serves them (``table``),
    checked against the digest every owner reported."""
    cached = _LIVE_ROUTERS.get((table.centres_sha256, table.version))
    if cached is not None:
        return cached
    owner = table.owners[0].robot_id
    key = keys.endpoint(swarm, "place-owner", owner, "table")
    msg = _call(caller, key, pb.TableRequest(), pb.ClusterTable, f"robot {owner}'s place owner")
    try:
        live = table_from_proto(msg, table.owners[0].dimension, _table_robots(table))
    except WireError as e:
        raise FailedPrecondition(f"robot {owner}'s cluster table does not read: {e}") from None
    if live.version != table.version or centres_digest(live.centres) != table.centres_sha256:
        raise FailedPrecondition(
            f"robot {owner} serves another table than version {table.version}: ask again"
        )
    if len(_LIVE_ROUTERS) >= 8:
        _LIVE_ROUTERS.clear()
    _LIVE_ROUTERS[(table.centres_sha256, table.version)] = live.router
    return live.router


def _table_robots(table: gateway_pb2.ClusterTableReply) -> int:
    try:
        return int(json.loads(table.table_json)["n_robots"])
    except (ValueError, TypeError, KeyError) as e:
        raise FailedPrecondition(f"the place owners' cluster table does not read: {e}") from None


def descriptor_of_values(values: Sequence[float], dimension: int) -> npt.NDArray[np.float32]:
    """A client's descriptor as float32, checked as an owner checks one (length, finite, unit)."""
    if len(values) != dimension:
        raise InvalidArgument(f"the swarm's descriptors have {dimension} values, got {len(values)}")
    x = np.asarray(values, np.float32)
    return descriptor_from_wire(x.astype("<f4").tobytes(), ENCODINGS["float32"], dimension)


def place_query(
    caller: Caller,
    swarm: str,
    descriptor: Sequence[float] | npt.NDArray[np.floating],
    *,
    exclude_robot: int | None = None,
    centres: str | Path | None = None,
) -> gateway_pb2.PlaceQueryReply:
    """Where a unit descriptor was seen: routed by the owners' table to the owner of its
    nearest centre, which searches what it holds (of robots but ``exclude_robot``)."""
    t0 = time.perf_counter()
    table = cluster_table(caller, swarm)
    if not table.agreed:
        versions = sorted({a.version for a in table.owners})
        raise FailedPrecondition(f"the place owners hold different cluster tables (versions {versions})")
    dimension = table.owners[0].dimension
    x = descriptor_of_values([float(v) for v in np.ravel(descriptor)], dimension)
    route = _router(caller, swarm, table, centres).route(x)
    query = pb.PlaceQuery(
        descriptor=x.astype("<f4").tobytes(),
        encoding=ENCODINGS["float32"],  # type: ignore[arg-type]  # an enum value
        cluster=route.cluster,
        assignment_version=table.version,
    )
    if exclude_robot is not None:
        query.robot_id = exclude_robot
    key = keys.endpoint(swarm, "place-owner", route.owner, "lookup")
    try:
        match = caller.call(key, query, pb.PlaceMatch, target_robot=None)
    except NoReply:
        raise RequestError(
            f"robot {route.owner}, the owner of cluster {route.cluster}, does not answer",
            code=ErrorCode.UNAVAILABLE,
        ) from None
    return gateway_pb2.PlaceQueryReply(
        cluster=route.cluster,
        owner_robot_id=route.owner,
        assignment_version=table.version,
        match=match,
        duration_us=min(int((time.perf_counter() - t0) * 1e6), 2**32 - 1),
    )


def place_loop_closures(caller: Caller, swarm: str, robot: int, min_score: float) -> pb.LoopClosureList:
    """The loop closures robot ``robot``'s place owner has found, oldest first."""
    key = keys.endpoint(swarm, "place-owner", robot, "loop_closures")
    request = pb.LoopClosuresRequest(min_score=min_score)
    return _call(caller, key, request, pb.LoopClosureList, f"robot {robot}'s place owner")


# --- object-based SLAM ----------------------------------------------------------------------


def slam_team(caller: Caller, swarm: str) -> gateway_pb2.SlamTeamReply:
    """Every slam service's status, by robot."""
    outcomes = _each_robot(caller, swarm, "slam", "status", pb.SlamStatusRequest(), pb.SlamStatus)
    statuses: list[pb.SlamStatus] = _one_per_robot(_replies(outcomes))
    return gateway_pb2.SlamTeamReply(robots=statuses)


def slam_estimate(caller: Caller, swarm: str, robot: int) -> pb.SlamEstimate:
    """Robot ``robot``'s estimate (NOT_FOUND: no slam service there, or nothing loaded)."""
    key = keys.endpoint(swarm, "slam", robot, "estimate")
    return _call(caller, key, pb.SlamEstimateRequest(), pb.SlamEstimate, f"robot {robot}'s slam service")


def estimate_position(e: pb.SlamEstimate) -> tuple[int, int, int, int]:
    """Where an estimate is: solve, state, linearisation, iteration (a stream sends each once)."""
    return e.solve_id, int(e.state), e.linearisation, e.iteration


def slam_map(caller: Caller, swarm: str) -> gateway_pb2.SlamMapReply:
    """The robots' estimates of the newest solve, merged in one ascending key order (a key two
    robots hold: the lower robot's, as the live solve's report merges them)."""
    outcomes = _each_robot(caller, swarm, "slam", "estimate", pb.SlamEstimateRequest(), pb.SlamEstimate)
    estimates = _one_per_robot(o.reply for o in outcomes if o.reply is not None)
    if not estimates:
        if all(_not_found(o.error) for o in outcomes):
            raise NotFound("no slam service holds a solve")
        raise next(o.error for o in outcomes if o.error is not None and not _not_found(o.error))
    solve = max(e.solve_id for e in estimates)
    merged = [e for e in estimates if e.solve_id == solve]
    size = sum(e.ByteSize() for e in merged)
    if size > MAX_MAP_BYTES:
        raise RequestError(
            f"the merged map would be {size} bytes, more than {MAX_MAP_BYTES}; read it robot by robot",
            code=ErrorCode.TOO_LARGE,
        )
    poses: dict[int, Sequence[float]] = {}
    for e in merged:
        if len(e.values) != 12 * len(e.keys):
            raise RequestError(f"robot {e.robot_id}'s estimate is malformed", code=ErrorCode.INTERNAL)
        for i, k in enumerate(e.keys):
            poses.setdefault(k, e.values[12 * i : 12 * (i + 1)])
    order = sorted(poses)
    return gateway_pb2.SlamMapReply(
        solve_id=solve,
        keys=order,
        values=[v for k in order for v in poses[k]],
        robot_ids=[e.robot_id for e in merged],
        states={e.robot_id: e.state for e in merged},
        missing_robot_ids=[e.robot_id for e in estimates if e.solve_id != solve],
        done=all(e.state == pb.SlamState.SLAM_STATE_DONE for e in merged),
    )


# --- landmark rounds --------------------------------------------------------------------------


def landmark_round(caller: Caller, swarm: str, round_id: int | None) -> gateway_pb2.LandmarkRoundReply:
    """Every fusion service's posterior of round ``round_id`` (None: each one's latest)."""
    request = pb.PosteriorRequest() if round_id is None else pb.PosteriorRequest(round_id=round_id)
    outcomes = _each_robot(caller, swarm, "fusion", "posterior", request, pb.FusionPosterior)
    posteriors = _one_per_robot(o.reply for o in outcomes if o.reply is not None)
    failed = [o.error for o in outcomes if o.error is not None and not _not_found(o.error)]
    if not posteriors and failed:
        raise failed[0]
    not_held = sum(_not_found(o.error) for o in outcomes)
    return gateway_pb2.LandmarkRoundReply(posteriors=posteriors, not_held=not_held)
