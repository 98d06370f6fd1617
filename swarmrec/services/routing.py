"""Where a querier sends each slice of a frame's descriptor: the index placement, kept fresh.

A descriptor (or a client) holds the placement it routes with (:class:`Routing`):
version 0 until it learns better, refreshed from the shards (the newest
placement any confirmed shard follows) when a shard says the sender is stale.
A group's query goes to one of its owners (:func:`~swarmrec.core.placement.serving_owner`,
a stable choice that spreads a group's queries over its replicas), the other live
owners next; a shard that timed out is asked last for ``suspect_s`` seconds, so a
frozen shard costs one timeout, not one per query.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Iterable, Sequence

import zenoh

from swarmrec.core.placement import Placement, ring, serving_owner
from swarmrec.errors import WireError
from swarmrec.runtime import keys
from swarmrec.runtime.rpc import Caller
from swarmrec.wire import messages as pb
from swarmrec.wire.placement import placement_from_proto

__all__ = ["LiveShards", "Routing", "newest_placement", "version_of"]


class LiveShards:
    """The ids of the swarm's live index shards, kept by a liveliness subscriber (with
    the tokens already declared), so asking costs nothing.

    With ``needs_link`` (a session that connects to a router or peers), it also watches
    this session's own transports: while it has none, the empty set of live shards says
    nothing of the others (they vanished because this session did), and
    :meth:`reaches_swarm` is False until a transport opens again (:meth:`rejoined_at`).

    With ``watch_draining`` it also keeps the shards that declared they are stopping
    (:func:`keys.draining`), so a stopping shard knows whether anyone stays without
    asking every shard (:meth:`anyone_stays`)."""

    def __init__(
        self, session: zenoh.Session, swarm: str, *, needs_link: bool = False, watch_draining: bool = False
    ) -> None:
        self._lock = threading.Lock()
        self._alive: set[int] = set()
        self._draining: set[int] = set()
        # When each shard's token went away (monotonic): a shard seen only briefly, between
        # two looks of the coordinator, still counts as seen (not as one never started).
        self._gone_at: dict[int, float] = {}
        self._transports: set[str] = set()
        self._needs_link = needs_link
        self._rejoined_at = 0.0
        self._cut = False
        self._link_listener = (
            session.info.declare_transport_events_listener(self._on_transport, history=True)
            if needs_link
            else None
        )
        self._sub = session.liveliness().declare_subscriber(
            keys.alive(swarm, "index-shard", "*"), self._on_token, history=True
        )
        self._draining_sub = (
            session.liveliness().declare_subscriber(
                keys.draining(swarm, "index-shard", "*"), self._on_draining, history=True
            )
            if watch_draining
            else None
        )

    def _on_transport(self, event: zenoh.TransportEvent) -> None:
        zid = str(event.transport.zid)
        with self._lock:
            if event.kind == zenoh.SampleKind.PUT:
                self._transports.add(zid)
                if self._cut:
                    self._cut = False
                    self._rejoined_at = time.monotonic()
            else:
                self._transports.discard(zid)
                self._cut = not self._transports

    def reaches_swarm(self) -> bool:
        """Whether this session has a transport to the swarm (always, without ``needs_link``)."""
        with self._lock:
            return not self._needs_link or bool(self._transports)

    def rejoined_at(self) -> float:
        """When this session last got a transport back after having none (monotonic; 0: never cut)."""
        with self._lock:
            return self._rejoined_at

    def _on_token(self, sample: zenoh.Sample) -> None:
        parsed = keys.parse_alive(str(sample.key_expr))
        if parsed is None:
            return
        _kind, shard = parsed
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._alive.add(shard)
            else:
                self._alive.discard(shard)
                self._gone_at[shard] = time.monotonic()

    def _on_draining(self, sample: zenoh.Sample) -> None:
        shard = keys.parse_draining(str(sample.key_expr))
        if shard is None:
            return
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._draining.add(shard)
            else:
                self._draining.discard(shard)

    def ids(self) -> set[int]:
        with self._lock:
            return set(self._alive)

    def draining_ids(self) -> set[int]:
        """The live shards that declared they are stopping (needs ``watch_draining``)."""
        with self._lock:
            return self._draining & self._alive

    def anyone_stays(self, shard: int) -> bool:
        """Whether a live shard other than ``shard`` has not declared it is stopping
        (needs ``watch_draining``; a token not seen yet counts as staying)."""
        with self._lock:
            return bool(self._alive - self._draining - {shard})

    def gone_at(self) -> dict[int, float]:
        """When each shard not alive now was last seen going (monotonic time)."""
        with self._lock:
            return {m: t for m, t in self._gone_at.items() if m not in self._alive}

    def close(self) -> None:
        with contextlib.suppress(zenoh.ZError):  # the session closed first
            self._sub.undeclare()  # type: ignore[no-untyped-call]  # untyped in zenoh's stub
        if self._draining_sub is not None:
            with contextlib.suppress(zenoh.ZError):
                self._draining_sub.undeclare()  # type: ignore[no-untyped-call]  # untyped in zenoh's stub
        if self._link_listener is not None:
            with contextlib.suppress(zenoh.ZError):
                self._link_listener.undeclare()  # type: ignore[no-untyped-call]  # untyped in zenoh's stub


def version_of(state: pb.ShardState) -> int:
    """The version of the placement a shard follows, sent with the placement or alone
    (``PlacementRequest.known_version``)."""
    return state.placement.version if state.HasField("placement") else state.placement_version


def newest_placement(
    states: Sequence[pb.ShardState], groups: Sequence[tuple[int, int]] | None = None
) -> Placement | None:
    """The newest placement among confirmed shards' states (of ``groups`` when given)."""
    best: Placement | None = None
    for st in states:
        if not st.confirmed or not st.HasField("placement") or len(st.placement.group_bounds) < 2:
            continue
        try:
            p = placement_from_proto(st.placement, st.placement.group_bounds[-1])
        except WireError:
            continue
        if groups is not None and p.groups != tuple(groups):
            continue
        if best is None or p.version > best.version:
            best = p
    return best


class Routing:
    """The placement a querier routes with, and the order it asks a group's owners in."""

    def __init__(
        self,
        swarm: str,
        n_labels: int,
        groups: Sequence[tuple[int, int]],
        *,
        replicas: int,
        n_shards: int,
        live: LiveShards | None = None,
        suspect_s: float = 5.0,
        on_refresh: Callable[[], None] | None = None,
        placement: Placement | None = None,
    ) -> None:
        self.swarm, self.n_labels = swarm, n_labels
        self.groups = tuple(groups)
        self.live = live
        self.suspect_s = suspect_s
        self._lock = threading.Lock()
        # Until it learns better: version 0, the table every shard of a new swarm starts from.
        self._placement = placement or ring(self.groups, range(n_shards), replicas=replicas)
        self._suspects: dict[int, float] = {}
        self.refreshes = 0
        self._on_refresh = on_refresh

    @property
    def placement(self) -> Placement:
        with self._lock:
            return self._placement

    def update(self, placement: Placement) -> bool:
        """Route with ``placement`` if it is newer; whether it was."""
        with self._lock:
            if placement.groups != self.groups or placement.version <= self._placement.version:
                return False
            self._placement = placement
            return True

    def refresh(
        self,
        caller: Caller,
        timeout_s: float | None = None,
        *,
        from_shards: Iterable[int] = (),
        routed: int | None = None,
    ) -> Placement:
        """Route with the newest placement a confirmed shard follows, after a request routed
        with version ``routed`` was refused: nothing to ask when this querier has moved past
        it already (another refresh did). Else one of ``from_shards`` (the shards that just
        refused a request as routed with another placement: each usually follows the newer
        one), then the lowest live shard, the coordinator, which follows the newest placement
        (it publishes them). Every shard is asked only when neither gives anything newer:
        every refusing shard, or every shard, answering each querier of a hundred after each
        placement change was more bytes than the queries themselves. The shards on this
        querier's version, or an older one, answer without the placement."""
        before = self.placement.version
        if routed is not None and before > routed:
            return self.placement
        refusing = sorted(set(from_shards))[:1]
        live = self.live.ids() if self.live is not None else set()
        coordinator = [min(live)] if live and min(live) not in refusing else []
        for shards in (refusing, coordinator):
            if not shards:
                continue
            pendings = [
                caller.start(
                    keys.endpoint(self.swarm, "index-shard", shard, "placement"),
                    pb.PlacementRequest(known_version=before),
                    target_robot=shard,
                    endpoint="placement",
                    timeout_s=timeout_s,
                )
                for shard in shards
            ]
            states = [o.reply for p in pendings for o in p.gather(pb.ShardState) if o.reply is not None]
            newest = newest_placement(states, self.groups)
            if newest is not None and newest.version > before:
                self._refreshed(newest)
                return self.placement
        pending = caller.start(
            keys.endpoint(self.swarm, "index-shard", "*", "placement"),
            pb.PlacementRequest(known_version=before),  # only newer ones come back whole
            target_robot=None,
            endpoint="placement",
            scatter=True,
            timeout_s=timeout_s,
        )
        states = [o.reply for o in pending.gather(pb.ShardState) if o.reply is not None]
        self._refreshed(newest_placement(states, self.groups))
        return self.placement

    def _refreshed(self, newest: Placement | None) -> None:
        self.refreshes += 1
        if self._on_refresh is not None:
            self._on_refresh()
        if newest is not None:
            self.update(newest)

    def suspect(self, shard: int) -> None:
        """``shard`` did not answer in time: ask it last for a while."""
        with self._lock:
            self._suspects[shard] = time.monotonic() + self.suspect_s

    def _suspected(self, now: float) -> set[int]:
        with self._lock:
            for shard in [s for s, until in self._suspects.items() if until <= now]:
                del self._suspects[shard]
            return set(self._suspects)

    def owners_in_order(self, placement: Placement, group: int, robot: int, frame: int) -> list[int]:
        """``group``'s owners, the one that should answer this frame's query first: the
        stable choice among live, unsuspected owners, then the other live ones, then the
        suspected, then those not seen alive."""
        owners = list(placement.owners[group])
        live = self.live.ids() if self.live is not None else set(owners)
        suspected = self._suspected(time.monotonic())
        good = [o for o in owners if o in live and o not in suspected]
        first = serving_owner(placement, group, robot, frame, good)
        rest = [o for o in good if o != first]
        rest += [o for o in owners if o in live and o in suspected]
        rest += [o for o in owners if o not in live]
        return ([first] if first is not None else []) + rest

    def close(self) -> None:
        if self.live is not None:
            self.live.close()
