"""A typed client for a running swarm: request/response stubs over zenoh queries.

    from swarmrec.client import SwarmClient

    with SwarmClient(["tcp/127.0.0.1:7447"], swarm="lab") as swarm:
        for m in swarm.members():
            print(m.kind, m.robot, m.label_range, m.metrics_url)
        result = swarm.query(constellation)          # ranked matches, nothing stored
        closures = swarm.loop_closures(robot=3)

Every call raises :class:`~swarmrec.errors.CallError` (``NoReply``,
``ReplyTimeout``, ``RemoteError``) when the swarm does not answer as asked;
a query that reached only part of the swarm says which robots failed.
"""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from dataclasses import dataclass
from types import TracebackType
from typing import TypeVar

import numpy as np
import zenoh

# protobuf ships no type stubs (see swarmrec/runtime/rpc.py for the two codes).
from google.protobuf.message import Message  # type: ignore[import-untyped, unused-ignore]

from swarmrec.core.presets import get_preset
from swarmrec.core.types import Constellation
from swarmrec.errors import NoReply, SwarmrecError
from swarmrec.runtime import keys
from swarmrec.runtime.rpc import Caller
from swarmrec.services.protocol import QueryPlan, two_step_query
from swarmrec.services.registry import kind_of_wire
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import constellation_to_proto

__all__ = ["Member", "QueryResult", "SwarmClient"]

M = TypeVar("M", bound=Message)


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


class SwarmClient:
    """A zenoh client session bound to one swarm."""

    def __init__(self, connect: Sequence[str], swarm: str = "default", *, timeout_s: float = 5.0) -> None:
        self.swarm = keys.validate_swarm_name(swarm)
        self.timeout_s = timeout_s
        conf = zenoh.Config()
        conf.insert_json5("mode", '"client"')
        conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
        conf.insert_json5("scouting/multicast/enabled", "false")
        self._conf = conf
        self._session: zenoh.Session | None = None
        self.caller: Caller | None = None

    def __enter__(self) -> SwarmClient:
        self._session = zenoh.open(self._conf)
        self.caller = Caller(self._session, None, self.timeout_s)
        return self

    def __exit__(
        self, t: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        if self._session is not None:
            self._session.close()  # type: ignore[no-untyped-call]  # untyped in zenoh's stub
            self._session = None

    @property
    def session(self) -> zenoh.Session:
        if self._session is None:
            raise SwarmrecError("use SwarmClient in a with block")
        return self._session

    def _caller(self) -> Caller:
        if self.caller is None:
            raise SwarmrecError("use SwarmClient in a with block")
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

    def wait_for(self, expected: set[tuple[str, int]], timeout_s: float = 30.0) -> None:
        """Block until every ``(kind, robot)`` in ``expected`` is alive."""
        deadline = time.monotonic() + timeout_s
        while True:
            missing = expected - self.alive()
            if not missing:
                return
            if time.monotonic() > deadline:
                raise NoReply(
                    keys.alive_all(self.swarm), f"not alive after {timeout_s:g} s: {sorted(missing)}"
                )
            time.sleep(0.1)

    def members(self) -> list[Member]:
        """Every live service with what it says about itself, by kind and robot."""
        key = f"{keys.PREFIX}/{self.swarm}/*/*/info"
        replies = self.session.get(
            key,
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
            timeout=self.timeout_s,
        )
        out = []
        for rep in replies:
            if rep.ok is None:
                continue
            info = pb.MemberInfo.FromString(rep.ok.payload.to_bytes())
            shard = info.kind == pb.ServiceKind.SERVICE_KIND_INDEX_SHARD
            out.append(
                Member(
                    kind=kind_of_wire(info.kind),
                    robot=info.robot_id,
                    label_range=(info.label_lo, info.label_hi) if shard else None,
                    n_labels=info.n_labels,
                    version=info.version,
                    metrics_url=info.metrics_url,
                    stored_items=info.stored_items,
                )
            )
        return sorted(out, key=lambda m: (m.kind, m.robot))

    def plan(self, preset: str = "paper") -> QueryPlan:
        """What a query needs to know, from the live shards' label ranges."""
        shards = [m for m in self.members() if m.kind == "index-shard"]
        if not shards:
            raise NoReply(f"{keys.PREFIX}/{self.swarm}", "no index shard is alive")
        n_robots = max(m.robot for m in shards) + 1
        bounds = np.zeros(n_robots + 1, np.int64)
        for m in shards:
            assert m.label_range is not None
            bounds[m.robot], bounds[m.robot + 1] = m.label_range
        return QueryPlan(self.swarm, n_robots, bounds, shards[0].n_labels, get_preset(preset))

    # --- requests -----------------------------------------------------------

    def query(
        self, constellation: Constellation, *, preset: str = "paper", plan: QueryPlan | None = None
    ) -> QueryResult:
        """Ask the swarm where ``constellation`` was seen; nothing is stored."""
        plan = plan or self.plan(preset)
        # The verifiers read either form; a read-only lookup's last micrometres do not matter.
        wire = constellation_to_proto(constellation, 0, 0)
        t0 = time.perf_counter()
        report = two_step_query(
            self._caller(),
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
        self, key: str, request: Message, reply_cls: type[M], *, target_robot: int | None, endpoint: str = ""
    ) -> M:
        """One request to one service (``keys.endpoint(...)``) and its reply; raises CallError."""
        return self._caller().call(key, request, reply_cls, target_robot=target_robot, endpoint=endpoint)

    def loop_closures(self, robot: int, min_score: float = 0.0) -> list[pb.LoopClosure]:
        """The loop closures robot ``robot`` has found, oldest first."""
        key = keys.endpoint(self.swarm, "descriptor", robot, "loop_closures")
        reply = self._caller().call(
            key, pb.LoopClosuresRequest(min_score=min_score), pb.LoopClosureList, target_robot=robot
        )
        return list(reply.loop_closures)

    def step(self, step: int, timeout_s: float) -> list[pb.StepReply | Exception]:
        """Lock-step replay: every detector processes ``step``; one entry per answer."""
        key = keys.endpoint(self.swarm, "detector", "*", "step")
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
