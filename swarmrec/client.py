"""Clients of a running swarm, one interface over two transports.

    from swarmrec.client import connect

    with connect("tls/127.0.0.1:7447", swarm="lab", tls=files) as swarm:      # zenoh, mutual TLS
        ...
    with connect("grpc://127.0.0.1:50051", swarm="lab", tls=files) as swarm:  # the gRPC gateway
        for m in swarm.members():
            print(m.kind, m.robot, m.label_range, m.metrics_url)
        result = swarm.query(constellation)          # ranked matches, nothing stored
        closures = swarm.loop_closures(robot=3)
        report = swarm.explain(robot=3, frame=120).report   # its loop-closure funnel
        place = swarm.place_query(descriptor)        # full-image: routed to its cluster's owner
        table = swarm.cluster_table()                # the owners' cluster table, its version
        team, merged = swarm.slam_team(), swarm.slam_map()  # SLAM: each robot's solve, the map
        for estimate in swarm.watch_slam_estimate(robot=1): ...   # until its solve ends
        posteriors = swarm.landmark_round(4).posteriors     # every robot's fused posterior

:class:`SwarmClient` is the interface; :class:`ZenohClient` speaks zenoh to
the router (and also drives replays: ``step``, ``replay``, raw ``call``s), and
:class:`GatewayClient` speaks gRPC to the swarm's gateway
(:mod:`swarmrec.services.gateway`), the one port a client outside the swarm
needs. ``files`` (:class:`~swarmrec.runtime.tls.TlsFiles`) is the client's
identity from the swarm's PKI: over zenoh its certificate, checked by the
router's access control; over gRPC the same certificate, and the CA that the
gateway's certificate must be signed by.

Every call raises :class:`~swarmrec.errors.CallError` (``NoReply``,
``ReplyTimeout``, ``RemoteError``) when the swarm does not answer as asked;
a query that reached only part of the swarm says which robots failed.
"""

from __future__ import annotations

import abc
import json
import logging
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, TypeVar

import grpc
import numpy as np
import zenoh

# protobuf ships no type stubs (see swarmrec/runtime/rpc.py for the two codes).
from google.protobuf.message import Message  # type: ignore[import-untyped, unused-ignore]

from swarmrec.core.placement import Placement
from swarmrec.core.presets import get_preset
from swarmrec.core.types import Constellation
from swarmrec.errors import (
    CallError,
    ConfigError,
    ErrorCode,
    NoReply,
    RemoteError,
    ReplyTimeout,
    SecurityError,
    SwarmrecError,
)
from swarmrec.runtime import keys
from swarmrec.runtime.rpc import Caller
from swarmrec.runtime.tls import TlsFiles, configure_client_tls, configure_insecure, no_shared_memory
from swarmrec.services import methods
from swarmrec.services.protocol import QueryPlan, two_step_query
from swarmrec.services.registry import kind_of_wire
from swarmrec.services.routing import Routing, newest_placement, version_of
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import constellation_to_proto
from swarmrec.wire.gen.swarmrec.v1 import gateway_pb2, gateway_pb2_grpc

__all__ = [
    "ERROR_CODE_METADATA",
    "GRPC_SCHEME",
    "GatewayClient",
    "IndexState",
    "Member",
    "QueryResult",
    "SwarmClient",
    "ZenohClient",
    "connect",
    "member_of",
]

M = TypeVar("M", bound=Message)
_C = TypeVar("_C", bound="SwarmClient")

#: Addresses of the gRPC gateway start with this; anything else is a zenoh endpoint.
GRPC_SCHEME = "grpc://"
#: Trailing metadata of a failed gateway call: the swarm's ErrorCode name (ERROR_CODE_...).
ERROR_CODE_METADATA = "swarmrec-error-code"

_log = logging.getLogger("swarmrec.client")


@dataclass(frozen=True)
class Member:
    """One live service of the swarm."""

    kind: str
    robot: int
    label_range: tuple[int, int] | None
    n_labels: int
    version: str
    metrics_url: str
    #: Partial descriptors (index shard) or constellations (verifier) held; 0 otherwise.
    stored_items: int = 0
    #: A descriptor's slices not yet acknowledged by every shard that must hold them.
    pending_items: int = 0
    #: An index shard's label groups, [lo, hi) each (label_range is the first).
    label_ranges: tuple[tuple[int, int], ...] = ()


@dataclass(frozen=True)
class IndexState:
    """The elastic index as the live shards report it."""

    #: The newest placement a confirmed shard follows (None: no shard answered).
    placement: Placement | None
    #: Each live shard's placement version (-1: not confirmed yet).
    versions: dict[int, int]
    #: Slices the descriptors still have to store.
    pending: int

    @property
    def settled(self) -> bool:
        """Every shard follows the same settled placement and nothing waits to be stored."""
        p = self.placement
        return (
            p is not None
            and p.settled
            and bool(self.versions)
            and set(self.versions.values()) == {p.version}
            and self.pending == 0
        )


def member_of(info: pb.MemberInfo) -> Member:
    """What a service's MemberInfo says, as a :class:`Member`."""
    shard = info.kind == pb.ServiceKind.SERVICE_KIND_INDEX_SHARD
    return Member(
        kind=kind_of_wire(info.kind),
        robot=info.robot_id,
        label_range=(info.label_lo, info.label_hi) if shard else None,
        n_labels=info.n_labels,
        version=info.version,
        metrics_url=info.metrics_url,
        stored_items=info.stored_items,
        pending_items=info.pending_items,
        label_ranges=tuple(zip(info.label_ranges[::2], info.label_ranges[1::2], strict=False)),
    )


@dataclass(frozen=True)
class QueryResult:
    """The swarm's answer to a client query."""

    matches: list[pb.VerifiedPair]
    n_candidates: int
    verified_robots: list[int]
    failed_shards: list[int]
    failed_verifiers: list[int]
    duration_ms: float

    @property
    def complete(self) -> bool:
        """True when every shard and verifier asked has answered."""
        return not (self.failed_shards or self.failed_verifiers)


class SwarmClient(abc.ABC):
    """What a client can ask a running swarm, whatever the transport; a context manager."""

    swarm: str
    timeout_s: float

    @abc.abstractmethod
    def open(self) -> None:
        """Connect (``with`` does it)."""

    @abc.abstractmethod
    def close(self) -> None:
        """Disconnect (``with`` does it)."""

    def __enter__(self: _C) -> _C:
        self.open()
        return self

    def __exit__(
        self, t: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    @abc.abstractmethod
    def members(self) -> list[Member]:
        """Every live service with what it says about itself, by kind and robot."""

    @abc.abstractmethod
    def query(self, constellation: Constellation, *, preset: str = "paper") -> QueryResult:
        """Ask the swarm where ``constellation`` was seen; nothing is stored."""

    @abc.abstractmethod
    def loop_closures(self, robot: int, min_score: float = 0.0) -> list[pb.LoopClosure]:
        """The loop closures robot ``robot`` has found, oldest first."""

    @abc.abstractmethod
    def explain(self, robot: int, frame: int) -> pb.ExplainReply:
        """What robot ``robot``'s query of its frame ``frame`` did, from its descriptor's
        memory (the last ``explain_reports`` reports): the report and its funnel."""

    # --- full-image place recognition (docs/vpr.md) -----------------------------------

    @abc.abstractmethod
    def place_query(
        self,
        descriptor: Sequence[float] | np.ndarray | None = None,
        *,
        image: bytes | None = None,
        exclude_robot: int | None = None,
    ) -> gateway_pb2.PlaceQueryReply:
        """Where a full-image descriptor (or the descriptor of an encoded ``image``) was seen:
        its cluster, that cluster's owner and the owner's nearest stored frame (of robots but
        ``exclude_robot``); nothing is stored."""

    @abc.abstractmethod
    def cluster_table(self) -> gateway_pb2.ClusterTableReply:
        """The cluster table the place owners hold, its version, and whether they agree."""

    @abc.abstractmethod
    def place_loop_closures(self, robot: int, min_score: float = 0.0) -> list[pb.LoopClosure]:
        """The loop closures robot ``robot``'s place owner has found, oldest first."""

    # --- object-based SLAM (docs/slam.md) ----------------------------------------------

    @abc.abstractmethod
    def slam_team(self) -> list[pb.SlamStatus]:
        """Every slam service's solve, by robot."""

    @abc.abstractmethod
    def slam_estimate(self, robot: int) -> pb.SlamEstimate:
        """Robot ``robot``'s estimate of its own vertices."""

    @abc.abstractmethod
    def watch_slam_estimate(self, robot: int, interval_s: float = 0.2) -> Iterator[pb.SlamEstimate]:
        """Robot ``robot``'s estimate each time it moves on (asked every ``interval_s``),
        ending after the estimate of a solve that has ended."""

    @abc.abstractmethod
    def slam_map(self) -> gateway_pb2.SlamMapReply:
        """The merged map: every robot's estimate of the newest solve, in one key order."""

    # --- landmark rounds (docs/landmarks.md) -----------------------------------------------

    @abc.abstractmethod
    def landmark_round(self, round_id: int | None = None) -> gateway_pb2.LandmarkRoundReply:
        """Every robot's fused posterior of round ``round_id`` (None: each one's latest)."""

    def alive(self) -> set[tuple[str, int]]:
        """(kind, robot) of every live service."""
        return {(m.kind, m.robot) for m in self.members()}

    def wait_for(self, expected: set[tuple[str, int]], timeout_s: float = 30.0) -> None:
        """Block until every ``(kind, robot)`` in ``expected`` is alive."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                missing = expected - self.alive()
            except CallError:
                missing = expected
            if not missing:
                return
            if time.monotonic() > deadline:
                raise NoReply(f"swarm {self.swarm}", f"not alive after {timeout_s:g} s: {sorted(missing)}")
            time.sleep(0.1)


def connect(
    address: str | Sequence[str],
    swarm: str = "default",
    *,
    timeout_s: float = 5.0,
    tls: TlsFiles | None = None,
    insecure_reason: str = "",
) -> SwarmClient:
    """The client for ``address``: ``grpc://host:port`` is the gateway, anything else
    (``tls/host:port``, several comma-separated for failover) the router over zenoh."""
    parts = [address] if isinstance(address, str) else list(address)
    endpoints = [e.strip() for p in parts for e in p.split(",") if e.strip()]
    grpc_ones = [e for e in endpoints if e.startswith(GRPC_SCHEME)]
    if grpc_ones:
        if len(endpoints) != 1:
            raise ConfigError(f"one gateway address at a time, got {endpoints}")
        return GatewayClient(grpc_ones[0], swarm, timeout_s=timeout_s, tls=tls)
    return ZenohClient(endpoints, swarm, timeout_s=timeout_s, tls=tls, insecure_reason=insecure_reason)


# --- zenoh ---------------------------------------------------------------------------


class ZenohClient(SwarmClient):
    """A zenoh client session bound to one swarm.

    With ``tls`` the session is mutual TLS as that identity (``tls/`` endpoints only);
    without it the endpoints must be plaintext ``tcp/`` and the insecure mode is
    logged as such. :meth:`attached` wraps a session someone else owns (the gateway's).
    """

    def __init__(
        self,
        connect: Sequence[str],
        swarm: str = "default",
        *,
        timeout_s: float = 5.0,
        tls: TlsFiles | None = None,
        insecure_reason: str = "",
    ) -> None:
        self.swarm = keys.validate_swarm_name(swarm)
        self.timeout_s = timeout_s
        if not connect:
            raise ConfigError("no router endpoint to connect to")
        conf = zenoh.Config()
        conf.insert_json5("mode", '"client"')
        conf.insert_json5("scouting/multicast/enabled", "false")
        no_shared_memory(conf)
        if tls is not None:
            configure_client_tls(conf, tls, list(connect))
        else:
            secure = [e for e in connect if e.startswith("tls/")]
            if secure:
                raise SecurityError(
                    f"{secure}: a tls/ endpoint needs this client's certificate "
                    "(--pki-dir and --identity, or a deployment's client())"
                )
            conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
            configure_insecure(
                conf,
                _log,
                who="client",
                reason=insecure_reason or f"plaintext endpoints {list(connect)} given",
            )
        self._conf: zenoh.Config | None = conf
        self._endpoints = list(connect)
        self._session: zenoh.Session | None = None
        self._owned = True
        self.caller: Caller | None = None

    @classmethod
    def attached(
        cls, session: zenoh.Session, swarm: str, caller: Caller, *, timeout_s: float = 5.0
    ) -> ZenohClient:
        """A client over an open ``session`` it does not close (a service's own)."""
        self = cls.__new__(cls)
        self.swarm = keys.validate_swarm_name(swarm)
        self.timeout_s = timeout_s
        self._conf, self._session, self._owned, self.caller = None, session, False, caller
        return self

    def open(self) -> None:
        if self._conf is not None and self._session is None:
            try:
                self._session = zenoh.open(self._conf)
            except zenoh.ZError as e:
                # zenoh's own words name a source line of its own; the user needs what failed
                # and what to check (one line, and the CLI's exit code 2 for a SwarmrecError).
                why = str(e).split("!", 1)[0].split(" at /", 1)[0].strip()
                raise NoReply(
                    ", ".join(self._endpoints),
                    f"no swarm router accepted this client ({why}): is the swarm running, is this "
                    "its router's address (--connect), and, under mutual TLS, its PKI (--pki-dir)?",
                ) from None
            self.caller = Caller(self._session, None, self.timeout_s)

    def close(self) -> None:
        if self._owned and self._session is not None:
            self._session.close()  # type: ignore[no-untyped-call]  # untyped in zenoh's stub
            self._session = None

    @property
    def session(self) -> zenoh.Session:
        if self._session is None:
            raise SwarmrecError("use the client in a with block")
        return self._session

    def _caller(self) -> Caller:
        if self.caller is None:
            raise SwarmrecError("use the client in a with block")
        return self.caller

    # --- membership ---------------------------------------------------------

    def alive(self) -> set[tuple[str, int]]:
        """(kind, robot) of every service whose liveliness token is up."""
        out = set()
        for rep in self.session.liveliness().get(keys.alive_all(self.swarm), timeout=self.timeout_s):
            if rep.ok is not None:
                parsed = keys.parse_alive(str(rep.ok.key_expr))
                if parsed:
                    out.add(parsed)
        return out

    def member_infos(self, timeout_s: float | None = None) -> list[pb.MemberInfo]:
        """What every live service says about itself (its ``info`` endpoint), by kind and robot."""
        key = f"{keys.PREFIX}/{self.swarm}/*/*/info"
        replies = self.session.get(
            key,
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
            timeout=self.timeout_s if timeout_s is None else timeout_s,
        )
        out = [pb.MemberInfo.FromString(rep.ok.payload.to_bytes()) for rep in replies if rep.ok is not None]
        return sorted(out, key=lambda m: (kind_of_wire(m.kind), m.robot_id))

    def members(self, timeout_s: float | None = None) -> list[Member]:
        """Every live service with what it says about itself, by kind and robot."""
        return [member_of(info) for info in self.member_infos(timeout_s)]

    def shard_states(
        self, timeout_s: float | None = None, *, known_version: int | None = None
    ) -> list[pb.ShardState]:
        """Every live index shard's placement, groups held and load (``placement`` endpoint);
        a shard following ``known_version`` sends that version without the placement."""
        pending = self._caller().start(
            keys.endpoint(self.swarm, "index-shard", "*", "placement"),
            pb.PlacementRequest(known_version=known_version),
            target_robot=None,
            endpoint="placement",
            scatter=True,
            timeout_s=timeout_s,
        )
        return [o.reply for o in pending.gather(pb.ShardState) if o.reply is not None]

    def index_state(
        self,
        timeout_s: float | None = None,
        *,
        known: Placement | None = None,
        members: Sequence[Member] | None = None,
    ) -> IndexState:
        """The placement the shards follow and the stores the descriptors still owe. With
        ``known`` (a placement read before), the shards that still follow it do not send it
        again (a poll of a hundred shards would otherwise carry a hundred placements); with
        ``members`` (the swarm's members, read just before), they are not asked for again."""
        states = self.shard_states(timeout_s, known_version=None if known is None else known.version)
        if members is None:
            members = self.members(timeout_s)
        pending = sum(m.pending_items for m in members if m.kind == "descriptor")
        versions = {st.shard_id: (version_of(st) if st.confirmed else -1) for st in states}
        newest = newest_placement(states)
        # A confirmed shard leaving the placement out follows ``known``'s version.
        omitted = any(not st.HasField("placement") and st.confirmed for st in states)
        if known is not None and omitted and (newest is None or newest.version < known.version):
            newest = known
        return IndexState(newest, versions, pending)

    def wait_index_settled(
        self,
        timeout_s: float = 30.0,
        poll_s: float = 0.2,
        *,
        shards: int | None = None,
        stall_s: float | None = None,
    ) -> IndexState:
        """Poll :meth:`index_state` until it is settled (handoffs done, every store
        acknowledged) or ``timeout_s`` passed; the last state either way. With ``shards``,
        settled also means that many shards answer and the placement lists them all.

        With ``stall_s``, it gives up sooner when the only thing missing is stores the
        descriptors owe and their count has not gone down for ``stall_s``, on a settled
        placement every live shard follows: stores owed to a shard that died as the only
        owner of its group wait for it to come back, which no wait here can hasten."""
        deadline = time.monotonic() + timeout_s
        known: Placement | None = None
        owed: tuple[int, int] | None = None  # (placement version, fewest stores owed so far)
        since = time.monotonic()
        while True:
            state = self.index_state(known=known)
            known = state.placement
            everyone = shards is None or (
                len(state.versions) >= shards
                and state.placement is not None
                and len(state.placement.members) >= shards
            )
            now = time.monotonic()
            if (state.settled and everyone) or now >= deadline:
                return state
            p = state.placement
            only_owed = (
                p is not None
                and p.settled
                and set(state.versions.values()) == {p.version}
                and state.pending > 0
            )
            if not only_owed or p is None:
                owed = None
            elif owed is None or owed[0] != p.version or state.pending < owed[1]:
                owed, since = (p.version, state.pending), now  # progress: the stall counts from here
            elif stall_s is not None and now - since >= stall_s:
                return state
            time.sleep(poll_s)

    def plan(self, preset: str = "paper", *, timeout_s: float | None = None) -> QueryPlan:
        """What a query needs to know: the index placement the live shards follow (the
        newest a confirmed shard follows), so each slice goes to an owner of its group."""
        states = self.shard_states(timeout_s)
        placement = newest_placement(states)
        if placement is None:
            raise NoReply(
                f"{keys.PREFIX}/{self.swarm}", "no index shard is alive (with a confirmed placement)"
            )
        groups = placement.groups
        routing = Routing(
            self.swarm,
            placement.n_labels,
            groups,
            replicas=placement.replicas,
            n_shards=len(placement.members),
            placement=placement,
        )
        n_robots = max(len(groups), max(placement.members) + 1)
        bounds = np.asarray([lo for lo, _ in groups] + [groups[-1][1]], np.int64)
        return QueryPlan(self.swarm, n_robots, bounds, placement.n_labels, get_preset(preset), routing)

    # --- requests -----------------------------------------------------------

    def query(
        self,
        constellation: Constellation,
        *,
        preset: str = "paper",
        plan: QueryPlan | None = None,
        caller: Caller | None = None,
    ) -> QueryResult:
        """Ask the swarm where ``constellation`` was seen; nothing is stored (the shards'
        ``lookup``). ``caller`` sends the requests instead of the client's own (a
        deadline's)."""
        plan = plan or self.plan(preset)
        # The verifiers read either form; a read-only lookup's last micrometres do not matter.
        wire = constellation_to_proto(constellation, 0, 0)
        t0 = time.perf_counter()
        report = two_step_query(
            caller or self._caller(),
            plan,
            constellation,
            wire,
            query_id=1,
            read_only=True,
            include_scores=True,
            self_robot=None,
        )
        return QueryResult(
            matches=list(report.matches),
            n_candidates=report.n_candidates,
            verified_robots=list(report.verified_robot_ids),
            failed_shards=list(report.failed_shard_robot_ids),
            failed_verifiers=list(report.failed_verifier_robot_ids),
            duration_ms=(time.perf_counter() - t0) * 1e3,
        )

    def call(
        self,
        key: str,
        request: Message,
        reply_cls: type[M],
        *,
        target_robot: int | None,
        endpoint: str = "",
        timeout_s: float | None = None,
    ) -> M:
        """One request to one service (``keys.endpoint(...)``) and its reply; raises CallError."""
        return self._caller().call(
            key, request, reply_cls, target_robot=target_robot, endpoint=endpoint, timeout_s=timeout_s
        )

    def loop_closures(
        self, robot: int, min_score: float = 0.0, *, timeout_s: float | None = None
    ) -> list[pb.LoopClosure]:
        """The loop closures robot ``robot`` has found, oldest first."""
        key = keys.endpoint(self.swarm, "descriptor", robot, "loop_closures")
        reply = self._caller().call(
            key,
            pb.LoopClosuresRequest(min_score=min_score),
            pb.LoopClosureList,
            target_robot=robot,
            timeout_s=timeout_s,
        )
        return list(reply.loop_closures)

    def explain(self, robot: int, frame: int, *, timeout_s: float | None = None) -> pb.ExplainReply:
        key = keys.endpoint(self.swarm, "descriptor", robot, "explain")
        request = pb.ExplainRequest(frame_index=frame)
        return self._caller().call(key, request, pb.ExplainReply, target_robot=robot, timeout_s=timeout_s)

    # --- the other methods (swarmrec.services.methods, as the gateway runs them) ---------

    def place_query(
        self,
        descriptor: Sequence[float] | np.ndarray | None = None,
        *,
        image: bytes | None = None,
        exclude_robot: int | None = None,
        centres: str | Path | None = None,
    ) -> gateway_pb2.PlaceQueryReply:
        """As :meth:`SwarmClient.place_query`; an ``image`` is described here, with the
        project's descriptor model. ``centres``: the swarm's centres file when it is not the
        shipped one (the owners' digest must match)."""
        if (descriptor is None) == (image is None):
            raise ConfigError("a place query takes exactly one of a descriptor or an image")
        computed = None
        if image is not None:
            from swarmrec.services.gateway_methods import ImageDescriber  # onnxruntime on first use
            from swarmrec.services.settings import VprSettings

            computed = ImageDescriber(VprSettings()).describe(image)
        x = computed if computed is not None else descriptor
        assert x is not None
        reply = methods.place_query(
            self._caller(), self.swarm, x, exclude_robot=exclude_robot, centres=centres
        )
        if computed is not None:
            reply.descriptor.extend(computed.tolist())
        return reply

    def cluster_table(self) -> gateway_pb2.ClusterTableReply:
        return methods.cluster_table(self._caller(), self.swarm)

    def place_loop_closures(self, robot: int, min_score: float = 0.0) -> list[pb.LoopClosure]:
        return list(methods.place_loop_closures(self._caller(), self.swarm, robot, min_score).loop_closures)

    def slam_team(self) -> list[pb.SlamStatus]:
        return list(methods.slam_team(self._caller(), self.swarm).robots)

    def slam_estimate(self, robot: int) -> pb.SlamEstimate:
        return methods.slam_estimate(self._caller(), self.swarm, robot)

    def watch_slam_estimate(self, robot: int, interval_s: float = 0.2) -> Iterator[pb.SlamEstimate]:
        last: tuple[int, int, int, int] | None = None
        while True:
            estimate = self.slam_estimate(robot)
            if methods.estimate_position(estimate) != last:
                last = methods.estimate_position(estimate)
                yield estimate
            if methods.terminal(estimate.state):
                return
            time.sleep(interval_s)  # polling the robot: it publishes no events

    def slam_map(self) -> gateway_pb2.SlamMapReply:
        return methods.slam_map(self._caller(), self.swarm)

    def landmark_round(self, round_id: int | None = None) -> gateway_pb2.LandmarkRoundReply:
        return methods.landmark_round(self._caller(), self.swarm, round_id)

    def step(
        self, step: int, timeout_s: float, *, robot: int | None = None
    ) -> list[pb.StepReply | Exception]:
        """Lock-step replay: every detector (or ``robot``'s) processes ``step``; one entry per answer."""
        key = keys.endpoint(self.swarm, "detector", "*" if robot is None else robot, "step")
        pending = self._caller().start(
            key, pb.StepRequest(step=step), target_robot=None, scatter=True, timeout_s=timeout_s
        )
        return [o.reply if o.reply is not None else o.error for o in pending.gather(pb.StepReply)]  # type: ignore[misc]

    def replay(self, rate_hz: float = 0.0) -> list[pb.ReplayReply | Exception]:
        """Free replay: every detector replays its whole share at ``rate_hz`` (0: as fast as answered)."""
        key = keys.endpoint(self.swarm, "detector", "*", "replay")
        pending = self._caller().start(
            key, pb.ReplayRequest(rate_hz=rate_hz), target_robot=None, scatter=True
        )
        return [o.reply if o.reply is not None else o.error for o in pending.gather(pb.ReplayReply)]  # type: ignore[misc]


# --- the gRPC gateway -------------------------------------------------------------------


def grpc_error(e: grpc.RpcError, what: str) -> CallError:
    """A failed gateway call as the CallError a zenoh call would have raised."""
    code = e.code() if isinstance(e, grpc.Call) else None
    details = (e.details() if isinstance(e, grpc.Call) else None) or str(e)
    trailing = dict(e.trailing_metadata() or ()) if isinstance(e, grpc.Call) else {}
    swarm_code = str(trailing.get(ERROR_CODE_METADATA, ""))
    if code == grpc.StatusCode.DEADLINE_EXCEEDED:
        return ReplyTimeout(what, details)
    if code == grpc.StatusCode.UNAVAILABLE and not swarm_code:
        return NoReply(what, details)
    known = {name for name, _ in pb.ErrorCode.items()}
    value = pb.ErrorCode.Value(swarm_code) if swarm_code in known else 0
    if code == grpc.StatusCode.UNAVAILABLE and value in (0, ErrorCode.UNAVAILABLE):
        return NoReply(what, details)
    return RemoteError(what, value or _CODE_OF_STATUS.get(code, ErrorCode.UNSPECIFIED), details)


_CODE_OF_STATUS: dict[Any, ErrorCode] = {
    grpc.StatusCode.INVALID_ARGUMENT: ErrorCode.INVALID_ARGUMENT,
    grpc.StatusCode.NOT_FOUND: ErrorCode.NOT_FOUND,
    grpc.StatusCode.RESOURCE_EXHAUSTED: ErrorCode.TOO_LARGE,
    grpc.StatusCode.FAILED_PRECONDITION: ErrorCode.FAILED_PRECONDITION,
    grpc.StatusCode.INTERNAL: ErrorCode.INTERNAL,
}


def grpc_target(address: str) -> str:
    """``host:port`` of a ``grpc://host:port`` address."""
    target = address.removeprefix(GRPC_SCHEME).rstrip("/")
    host, _, port = target.rpartition(":")
    if not host or not port.isdigit():
        raise ConfigError(f"a gateway address is grpc://host:port, got {address!r}")
    return target


def channel_credentials(tls: TlsFiles) -> grpc.ChannelCredentials:
    """Verify the gateway against the swarm CA and present this client's certificate."""
    tls.check()
    return grpc.ssl_channel_credentials(
        root_certificates=tls.root_ca.read_bytes(),
        private_key=tls.key.read_bytes(),
        certificate_chain=tls.cert.read_bytes(),
    )


class GatewayClient(SwarmClient):
    """The swarm through its gRPC gateway. With ``tls`` the channel is TLS (the gateway's
    certificate checked against the swarm CA, this client's presented); without it,
    plaintext (a gateway run with ``--security insecure``)."""

    def __init__(
        self, address: str, swarm: str = "default", *, timeout_s: float = 5.0, tls: TlsFiles | None = None
    ) -> None:
        self.swarm = keys.validate_swarm_name(swarm)
        self.timeout_s = timeout_s
        self.address = address
        self.target = grpc_target(address)
        self.tls = tls
        self._channel: grpc.Channel | None = None
        self._stub: Any = None

    def open(self) -> None:
        if self._channel is None:
            if self.tls is not None:
                self._channel = grpc.secure_channel(self.target, channel_credentials(self.tls))
            else:
                self._channel = grpc.insecure_channel(self.target)
            self._stub = gateway_pb2_grpc.SwarmGatewayStub(self._channel)  # type: ignore[no-untyped-call]  # generated, untyped

    def close(self) -> None:
        if self._channel is not None:
            self._channel.close()
            self._channel = None
            self._stub = None

    @property
    def stub(self) -> Any:
        """The generated ``SwarmGatewayStub`` (streams: ``stub.WatchLoopClosures(...)``)."""
        if self._stub is None:
            raise SwarmrecError("use the client in a with block")
        return self._stub

    def _call(self, method: str, request: Message, timeout_s: float | None = None) -> Any:
        try:
            return getattr(self.stub, method)(request, timeout=timeout_s or self.timeout_s)
        except grpc.RpcError as e:
            raise grpc_error(e, f"{self.address} {method}") from None

    def members(self) -> list[Member]:
        reply = self._call("Members", gateway_pb2.MembersRequest())
        return sorted((member_of(m) for m in reply.members), key=lambda m: (m.kind, m.robot))

    def status(self) -> Any:
        """The gateway's StatusReply."""
        return self._call("Status", gateway_pb2.StatusRequest())

    def query(self, constellation: Constellation, *, preset: str = "paper") -> QueryResult:
        # Exact doubles: the gateway puts the positions on the swarm's wire as its preset says.
        wire = constellation_to_proto(constellation, 0, 0, exact=True)
        t0 = time.perf_counter()
        reply = self._call("Query", gateway_pb2.QueryRequest(constellation=wire, preset=preset))
        return QueryResult(
            matches=list(reply.matches),
            n_candidates=reply.n_candidates,
            verified_robots=list(reply.verified_robot_ids),
            failed_shards=list(reply.failed_shard_robot_ids),
            failed_verifiers=list(reply.failed_verifier_robot_ids),
            duration_ms=(time.perf_counter() - t0) * 1e3,
        )

    def loop_closures(self, robot: int, min_score: float = 0.0) -> list[pb.LoopClosure]:
        request = gateway_pb2.RobotLoopClosuresRequest(robot_id=robot, min_score=min_score)
        return list(self._call("LoopClosures", request).loop_closures)

    def explain(self, robot: int, frame: int) -> pb.ExplainReply:
        reply: pb.ExplainReply = self._call(
            "Explain", gateway_pb2.RobotExplainRequest(robot_id=robot, frame_index=frame)
        )
        return reply

    # --- the other methods ---------------------------------------------------------------

    def place_query(
        self,
        descriptor: Sequence[float] | np.ndarray | None = None,
        *,
        image: bytes | None = None,
        exclude_robot: int | None = None,
    ) -> gateway_pb2.PlaceQueryReply:
        """As :meth:`SwarmClient.place_query`; an ``image`` is described by the gateway."""
        if (descriptor is None) == (image is None):
            raise ConfigError("a place query takes exactly one of a descriptor or an image")
        request = gateway_pb2.PlaceQueryRequest(exclude_robot_id=exclude_robot)
        if image is not None:
            request.image = image
        else:
            request.descriptor.extend(float(v) for v in np.ravel(np.asarray(descriptor, np.float32)))
        reply: gateway_pb2.PlaceQueryReply = self._call("PlaceQuery", request)
        return reply

    def cluster_table(self) -> gateway_pb2.ClusterTableReply:
        reply: gateway_pb2.ClusterTableReply = self._call("ClusterTable", gateway_pb2.ClusterTableRequest())
        return reply

    def place_loop_closures(self, robot: int, min_score: float = 0.0) -> list[pb.LoopClosure]:
        request = gateway_pb2.RobotLoopClosuresRequest(robot_id=robot, min_score=min_score)
        return list(self._call("PlaceLoopClosures", request).loop_closures)

    def slam_team(self) -> list[pb.SlamStatus]:
        return list(self._call("SlamTeam", gateway_pb2.SlamTeamRequest()).robots)

    def slam_estimate(self, robot: int) -> pb.SlamEstimate:
        reply: pb.SlamEstimate = self._call("SlamRobotEstimate", gateway_pb2.SlamRobotRequest(robot_id=robot))
        return reply

    def watch_slam_estimate(self, robot: int, interval_s: float = 0.2) -> Iterator[pb.SlamEstimate]:
        request = gateway_pb2.WatchSlamEstimateRequest(robot_id=robot, interval_ms=round(interval_s * 1000))
        # No deadline: the stream lasts as long as the solve (it ends itself when the solve does).
        call = self.stub.WatchSlamEstimate(request)
        try:
            yield from call
        except grpc.RpcError as e:
            raise grpc_error(e, f"{self.address} WatchSlamEstimate") from None
        finally:
            call.cancel()

    def slam_map(self) -> gateway_pb2.SlamMapReply:
        reply: gateway_pb2.SlamMapReply = self._call("SlamMap", gateway_pb2.SlamMapRequest())
        return reply

    def landmark_round(self, round_id: int | None = None) -> gateway_pb2.LandmarkRoundReply:
        reply: gateway_pb2.LandmarkRoundReply = self._call(
            "LandmarkRound", gateway_pb2.LandmarkRoundRequest(round_id=round_id)
        )
        return reply
