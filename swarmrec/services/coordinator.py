"""The elastic index's coordinator: the lowest index shard present keeps the placement.

Every shard runs one :class:`Coordinator`; it acts only while its shard is the
lowest id among the shards present: the live ones (liveliness tokens) and the
members within their grace (:func:`present_members`), so exactly one acts once
membership has settled, and another takes over ``member_grace_s`` after it goes.
A new coordinator's first look at the load only starts its window, and it
rebalances only on the states of every present member. Each
tick (``placement_tick_s``) the acting coordinator:

1. asks every live shard for its state (placement version, groups copied, load);
2. on taking over, and whenever a shard follows a newer one, starts from the newest
   placement any shard follows;
3. sends the placement to every shard that follows an older one (or has not
   been confirmed since it restarted);
4. with a handoff in progress, promotes it once every live learner has copied
   its groups (:func:`~swarmrec.core.placement.promote`);
5. otherwise follows membership (:func:`~swarmrec.core.placement.follow_members`:
   a gone shard's groups stay answered by their other replicas and get new
   ones) and, once ``rebalance_min_queries`` (and 20 a member shard) partial queries were served since
   the last look, the observed load (:func:`~swarmrec.core.rebalance.rebalance`,
   to ``rebalance_target``), and starts the handoff
   (:func:`~swarmrec.core.placement.transition`). The load is every query the
   shards served since they started, not the last window's: a robot crossing
   a room shifts the window's load from label to label, and a placement that
   chases the window moves groups at every look. A rebalancing that would
   lower the busiest shard's load by less than ``MIN_GAIN`` moves nothing.
   A group's every replica stores every slice of it, so the load model weighs
   those stores with the CPU time the shards measured for a store against a
   query (:func:`store_weight`): where a store costs as much as a query, a
   replica spreads nothing and a rebalancing moves groups instead of copying them;
   a replica is added only if it lowers its group's share on each owner by
   ``MIN_REPLICA_GAIN``, which bounds a hot group's replicas.

Every shard, coordinator or not, first checks on start that the swarm is not
further along than the placement it loaded (:meth:`Coordinator.confirm_on_start`).

A shard whose session lost its link to the router (a router restart, a cable) sees no
shard alive. It does not coordinate while cut off, and once back it gives the other
members the start grace again, as they come back one by one (:meth:`Coordinator._cut_off`).
Otherwise the first shard back after a router restart would take the others for gone
and publish a placement none of them follows.

In a mesh (``hold_when_away``, a router per robot, docs/mesh.md "Partitions") a member
out of sight is **away**: the team is split, or that robot's router or shard died, and
from here these look the same. While any member is away the coordinator of
each part (the lowest shard present there) changes no placement: no group moves, none
is re-placed, nothing is rebalanced. Each part goes on with the placement it had: a
query goes to a group's owners in its part, a store to an owner away waits on its robot
(pending stores). So no two placements are ever made apart, and there is none to merge
when the team heals: every shard still follows the same version.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Protocol

import zenoh

from swarmrec.core.placement import (
    Placement,
    balance_ratio,
    follow_members,
    groups_from_bounds,
    promote,
    shard_loads,
    transition,
)
from swarmrec.core.rebalance import RULES
from swarmrec.errors import CallError, WireError
from swarmrec.runtime import ServiceContext, keys
from swarmrec.runtime.settings import BusSettings
from swarmrec.services.metrics import ShardMetrics
from swarmrec.services.routing import LiveShards, version_of
from swarmrec.services.settings import IndexSettings, PlaceSettings
from swarmrec.wire import messages as pb
from swarmrec.wire.placement import placement_from_proto, placement_to_proto

#: Partial queries a rebalancing looks at, at least, per member shard (beside
#: ``rebalance_min_queries``): 200 for 10 shards, 2000 for 100.
QUERIES_PER_SHARD = 20

#: Whole windows of load a coordinator looks at, asking every shard at every tick, before it
#: asks only every ``state_interval_s`` (Coordinator._rebalanced): each may publish a
#: rebalancing (two placement versions), so at most 2 x (LEARNING_LOOKS - 1) versions follow
#: the first rebalancing while it learns.
LEARNING_LOOKS = 3

#: A starting shard asks this many of the lowest live shards whether the swarm is further
#: along than the placement it loaded, before it asks every shard (Coordinator._states_on_start).
CONFIRM_SAMPLE = 3

#: A rebalancing must lower the busiest shard's share of the load by at least this
#: fraction, or nothing moves: every move is a handoff, and a placement every querier
#: must learn (stores routed with the old one are refused until their sender refreshes).
MIN_GAIN = 0.1

#: A replica must lower each owner's share of its group by at least this fraction (every
#: replica is a ShardStore more on every query of its group, each helping less than the last).
#: At 10 % the TUM sequence's hottest group never got its third owner at the weight measured
#: early in a run (0.6-0.7: the index nearly empty, queries cheap), and the busiest shard stayed
#: at 1.44 times the mean; at 5 % it gets it, and the run's busiest / mean is 1.28.
MIN_REPLICA_GAIN = 0.05

#: A store's cost relative to a partial query's until the shards have measured both
#: (``MIN_COST_SAMPLES`` of each): as costly, so that no replica is added on a guess
#: (every replica is a ShardStore more on every query of its group). Measured in a
#: 10-robot TUM swarm on the 2-core machine: a store costs about half a query (both
#: are mostly the cost of a message; the search is the rest).
DEFAULT_STORE_WEIGHT = 1.0
MIN_COST_SAMPLES = 100
#: The measured weight is kept within this (a shard's report is not trusted further).
MAX_STORE_WEIGHT = 4.0


@dataclass(frozen=True)
class Costs:
    """Partial queries and ShardStores the shards served, and the CPU seconds they took, summed."""

    query_calls: int = 0
    query_cpu_s: float = 0.0
    store_calls: int = 0
    store_cpu_s: float = 0.0

    def minus(self, earlier: Costs) -> Costs:
        return Costs(
            self.query_calls - earlier.query_calls,
            self.query_cpu_s - earlier.query_cpu_s,
            self.store_calls - earlier.store_calls,
            self.store_cpu_s - earlier.store_cpu_s,
        )

    def weight(self) -> float | None:
        """A store's mean cost over a query's; None until each was measured ``MIN_COST_SAMPLES``
        times (or when a shard's restart made a difference of sums negative)."""
        if self.query_calls < MIN_COST_SAMPLES or self.store_calls < MIN_COST_SAMPLES:
            return None
        if self.query_cpu_s <= 0.0 or self.store_cpu_s < 0.0:
            return None
        return min(
            MAX_STORE_WEIGHT, (self.store_cpu_s / self.store_calls) / (self.query_cpu_s / self.query_calls)
        )


def cost_totals(states: Iterable[pb.ShardState]) -> Costs:
    """The shards' measured costs summed; a report that is not finite or is negative is left out."""
    q_n = s_n = 0
    q_s = s_s = 0.0
    for st in states:
        if not all(math.isfinite(v) and v >= 0.0 for v in (st.query_cpu_s, st.store_cpu_s)):
            continue
        q_n, q_s = q_n + st.query_calls, q_s + st.query_cpu_s
        s_n, s_s = s_n + st.store_calls, s_s + st.store_cpu_s
    return Costs(q_n, q_s, s_n, s_s)


def store_weight(states: Iterable[pb.ShardState], since: Costs | None = None) -> float:
    """A ShardStore's CPU cost over a partial query's, from what the shards measured: over the
    window since ``since`` (the sums at the last look) where it has enough of both, else since
    they started; ``DEFAULT_STORE_WEIGHT`` until each was measured ``MIN_COST_SAMPLES`` times.
    The window first: a query searches every stored slice of its group, so it costs more as the
    index fills, and the first queries of a run (an index nearly empty) overstate a store's
    weight, which would keep a hot group from the replica it needs."""
    now = cost_totals(states)
    recent = now.minus(since).weight() if since is not None else None
    if recent is not None:
        return recent
    overall = now.weight()
    return DEFAULT_STORE_WEIGHT if overall is None else overall


class ShardSettings:
    """What a shard reads from its settings, and the coordinator's view of one with it:
    the Python shard and a compiled shard's coordinator (``shard_coordinator``) alike."""

    def read_settings(self, ctx: ServiceContext) -> None:
        self.ctx = ctx
        self.bus = ctx.bus
        self.places = ctx.settings(PlaceSettings)
        self.index_settings = ctx.settings(IndexSettings)
        self.metrics = ctx.metric_set(ShardMetrics)
        self.shard = self.bus.robot
        self.groups = groups_from_bounds(self.places.bounds(self.bus).tolist())


class Shard(Protocol):
    """What the coordinator needs of the shard it runs in (an IndexShard)."""

    shard: int
    bus: BusSettings
    places: PlaceSettings
    index_settings: IndexSettings
    ctx: ServiceContext
    metrics: ShardMetrics
    groups: tuple[tuple[int, int], ...]
    placement: Placement
    confirmed: bool
    ready: set[int]

    def state(self) -> pb.ShardState: ...

    def follow(self, placement: Placement, *, confirm: bool = True) -> bool: ...

    def follow_own(self, placement: Placement, reason: int) -> None: ...


__all__ = [
    "Coordinator",
    "Costs",
    "Shard",
    "ShardSettings",
    "View",
    "cost_totals",
    "group_changes",
    "must_look",
    "present_members",
    "reason_name",
    "served_load",
]

#: What the coordinator sees without asking anyone: the live shards, the draining ones, and
#: the members that keep their groups (the live ones and those within a grace).
View = tuple[frozenset[int], frozenset[int], frozenset[int]]


def must_look(
    *,
    acting: bool,
    settled: bool,
    confirmed: bool,
    view: View,
    last_view: View | None,
    dirty: bool,
    learning: bool,
    since_look_s: float,
    interval_s: float,
) -> bool:
    """Whether this tick asks every shard for its state. A hundred shards' states every
    second were most of a large swarm's index traffic (194 B a query at 100 robots), and in
    a settled swarm nothing in them changes: so they are asked for on taking over, during a
    handoff (the learners' progress), when a shard came, went, or began draining (the view),
    after an adoption a shard did not confirm (``dirty``), for the coordinator's first
    ``LEARNING_LOOKS`` windows of load (``learning``: the first rebalancing comes as early as
    the load allows, and the next ones plan on loads that have settled), and otherwise every
    ``interval_s`` (a shard on another placement, the load for the next rebalancing look)."""
    if not acting or not settled or not confirmed or dirty or learning or view != last_view:
        return True
    return since_look_s >= interval_s


def present_members(
    members: Iterable[int],
    live: set[int],
    seen: dict[int, float],
    *,
    started: float,
    now: float,
    grace_s: float,
    start_grace_s: float,
) -> set[int]:
    """The members that keep their groups: the live ones, those gone for less than
    ``grace_s`` (a restart keeps its groups), and those never seen alive while the
    coordinator has run for less than ``start_grace_s`` (a swarm still starting)."""
    present = set(live)
    for m in members:
        last = seen.get(m)
        if last is None:
            if now - started < start_grace_s:
                present.add(m)
        elif now - last < grace_s:
            present.add(m)
    return present


def reason_name(reason: int) -> str:
    """A ``PlacementReason`` as the metrics, logs and reports name it (``handoff_done``)."""
    try:
        name = str(pb.PlacementReason.Name(pb.PlacementReason.ValueType(reason)))
    except ValueError:  # a value this schema does not know
        return "unspecified"
    return name.removeprefix("PLACEMENT_REASON_").lower()


def group_changes(before: Placement, after: Placement) -> list[pb.GroupChange]:
    """The groups whose holders changed from ``before`` to ``after``: the shards that now store
    a group and did not (new learners; owners added at once), and those that let it go or will
    (owners gone, or leaving once the handoff is done)."""
    out = []
    for g in range(min(len(before.groups), len(after.groups))):
        held_before = set(before.store_targets(g))
        gained = sorted(set(after.store_targets(g)) - held_before)
        lost = sorted(
            (set(before.owners[g]) - set(after.store_targets(g)))
            | (set(after.leaving[g]) - set(before.leaving[g]))
        )
        if gained or lost:
            out.append(pb.GroupChange(group=g, gained=gained, lost=lost))
    return out


def served_load(state: pb.ShardState, n_groups: int) -> dict[int, int]:
    """The partial queries a shard says it served, by group (only groups with any are sent).
    Raises WireError when the two lists differ in length, or name a group twice or one
    beyond ``n_groups``: a shard's report is not trusted further than it checks out."""
    groups, counts = state.served_groups, state.served_queries
    if len(groups) != len(counts):
        raise WireError(f"served_groups has {len(groups)} entries, served_queries {len(counts)}")
    out: dict[int, int] = {}
    for g, n in zip(groups, counts, strict=True):
        if g >= n_groups or g in out:
            raise WireError(f"served_groups names group {g} twice or beyond the {n_groups} groups")
        out[g] = int(n)
    return out


class Coordinator:
    """The coordinator loop of one shard (see the module docstring)."""

    def __init__(self, shard: Shard) -> None:
        self.shard = shard
        self.settings = shard.index_settings
        self.log = shard.ctx.log
        self.live: LiveShards | None = None
        # The members away at the last tick (logged when that changes).
        self._away: frozenset[int] = frozenset()
        self.acting = False
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        # The group loads summed over the shards at the last rebalancing look.
        # None once it takes over: the next look only marks the window's start.
        self._load_mark: dict[int, int] | None = {}
        # When each shard was last seen alive (a member never seen: see present_members).
        self._seen: dict[int, float] = {}
        self._started = time.monotonic()
        # The last time this shard's session got its link to the swarm back (monotonic).
        self._rejoined = 0.0
        # The last look at every shard's state (monotonic), what it saw without asking, and
        # whether an adoption since went unconfirmed (see must_look).
        self._looked = -math.inf
        self._view: View | None = None
        self._dirty = False
        # Whether this coordinator still looks at the load every tick (see _rebalanced), and
        # how many whole windows of load it has looked at since it took over.
        self._learning = True
        self._learning_looks = 0
        # The shards' measured costs at the last rebalancing look (a store's weight is read
        # over the window since).
        self._cost_mark: Costs | None = None
        # The load the last rebalancing was planned on (for its PlacementChange event).
        self._plan: pb.PlacementChange | None = None

    def start(self) -> None:
        if self._thread is not None:
            return
        # A shard that connects to a router (or peers) can be cut off from the swarm: then it
        # sees no shard, and must not take that for the others having gone.
        needs_link = bool(self.shard.bus.connect)
        self.live = LiveShards(
            self.shard.ctx.session, self.shard.bus.swarm, needs_link=needs_link, watch_draining=True
        )
        self._thread = threading.Thread(target=self._run, name="index-coordinator", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)
        if self.live is not None:
            self.live.close()
            self.live = None

    def anyone_stays(self) -> bool:
        """Whether another live shard has not declared it is stopping (False before start)."""
        return self.live is not None and self.live.anyone_stays(self.shard.shard)

    def lowest_live(self) -> int:
        """The lowest shard id this shard sees alive (itself included)."""
        live = self.live.ids() if self.live is not None else set()
        return min(live | {self.shard.shard})

    def _stopping(self) -> bool:
        # Not the service's stop event: a coordinator that is draining its own shard keeps
        # coordinating until the shard is drained (stop() ends it then).
        return self._stop.is_set()

    def _run(self) -> None:
        self.confirm_on_start()
        # One tick before acting: the liveliness subscriber's view of the others (its history)
        # arrives by then, so a shard does not take itself for the lowest while it is not.
        self._stop.wait(self.settings.placement_tick_s)
        while not self._stopping():
            try:
                self.tick()
            except Exception:
                self.log.exception("coordinator tick failed")
            self._stop.wait(self.settings.placement_tick_s)

    # --- talking to the shards ------------------------------------------------------------

    def states(self, known_version: int | None = None) -> dict[int, pb.ShardState]:
        """Every live shard's state, by shard id (one scatter request; this shard's own
        state is read directly). With ``known_version``, a shard following that version
        sends its version without the placement (:func:`version_of`)."""
        s = self.shard
        out = {s.shard: s.state()}
        pending = s.ctx.caller.start(
            keys.endpoint(s.bus.swarm, "index-shard", "*", "placement"),
            pb.PlacementRequest(known_version=known_version),
            target_robot=None,
            endpoint="placement",
            scatter=True,
        )
        for outcome in pending.gather(pb.ShardState):
            if outcome.reply is not None and outcome.reply.shard_id != s.shard:
                out[outcome.reply.shard_id] = outcome.reply
        return out

    def _placement_of(self, state: pb.ShardState) -> Placement | None:
        if not state.HasField("placement"):
            return None
        try:
            p = placement_from_proto(state.placement, self.shard.places.n_labels)
        except WireError:
            return None
        return p if p.groups == self.shard.groups else None

    def confirm_on_start(self) -> None:
        """Answer only with the swarm's placement: if a live shard follows a newer one, wait
        for the coordinator to send it; otherwise the one loaded (or version 0) is it."""
        s = self.shard
        try:
            states = self._states_on_start()
        except CallError:
            states = {}
        newest = max(
            (
                p.version
                for st in states.values()
                if st.confirmed and (p := self._placement_of(st)) is not None
            ),
            default=-1,
        )
        if newest <= s.placement.version:
            s.follow(s.placement, confirm=True)
            self.log.info("placement confirmed", extra={"fields": {"version": s.placement.version}})
        else:
            self.log.info(
                "the swarm is further along: waiting for the coordinator",
                extra={"fields": {"version": s.placement.version, "swarm_version": newest}},
            )

    def _states_on_start(self) -> dict[int, pb.ShardState]:
        """What a starting shard asks to learn whether the swarm is further along: the
        ``CONFIRM_SAMPLE`` lowest live shards first (the lowest present is the coordinator,
        which follows the newest placement), every shard only when none of those is confirmed
        (a swarm starting, or the lowest ones restarting with it). Every shard of a starting
        hundred asking every other was 10,000 states, most of a short run's index traffic.
        Only a newer placement matters: the shards on this one leave it out of their answer."""
        s = self.shard
        known = s.placement.version
        live: set[int] = set()
        for rep in s.ctx.session.liveliness().get(
            keys.alive(s.bus.swarm, "index-shard", "*"), timeout=s.bus.request_timeout_s
        ):
            if rep.ok is not None and (parsed := keys.parse_alive(str(rep.ok.key_expr))) is not None:
                live.add(parsed[1])
        sample = sorted(live - {s.shard})[:CONFIRM_SAMPLE]
        if sample:
            states = self._ask_states(sample, known)
            if any(st.confirmed for st in states.values()):
                return states
        return self.states(known)

    def _ask_states(self, shards: list[int], known_version: int) -> dict[int, pb.ShardState]:
        """The states of ``shards``, asked all at once; one that does not answer is left out."""
        s = self.shard
        asked = [
            (
                m,
                s.ctx.caller.start(
                    keys.endpoint(s.bus.swarm, "index-shard", m, "placement"),
                    pb.PlacementRequest(known_version=known_version),
                    target_robot=m,
                    endpoint="placement",
                ),
            )
            for m in shards
        ]
        out = {}
        for m, pending in asked:
            try:
                out[m] = pending.result(pb.ShardState)
            except CallError:
                continue
        return out

    def _adopt(self, shards: list[int], placement: Placement) -> None:
        """Send ``placement`` to ``shards`` (all at once); a shard that does not answer gets
        it again next tick."""
        s = self.shard
        msg = pb.AdoptRequest(placement=placement_to_proto(placement))
        asked = [
            (
                m,
                s.ctx.caller.start(
                    keys.endpoint(s.bus.swarm, "index-shard", m, "adopt"),
                    msg,
                    target_robot=m,
                    endpoint="adopt",
                ),
            )
            for m in shards
        ]
        for m, pending in asked:
            try:
                pending.result(pb.ShardState)
            except CallError as e:
                self._dirty = True  # look again next tick: it gets the placement then
                self.log.info(f"shard {m} did not adopt placement {placement.version}: {e}")

    def publish(
        self,
        placement: Placement,
        live: set[int],
        reason: int,
        plan: pb.PlacementChange | None = None,
    ) -> None:
        """Follow ``placement`` here, send it to every other live shard, and say so: a
        ``PlacementChange`` event with the ``reason`` (and a rebalancing's ``plan``: the load
        it was planned on), the placement's history as a run's report and any watcher read it."""
        s = self.shard
        before = s.placement
        s.follow_own(placement, reason)
        change = pb.PlacementChange()
        if plan is not None:
            change.CopyFrom(plan)
        change.version, change.coordinator = placement.version, s.shard
        change.reason = pb.PlacementReason.ValueType(reason)
        change.changes.extend(group_changes(before, placement))
        change.unix_time_ns = time.time_ns()
        fields = {
            "version": placement.version,
            "reason": reason_name(reason),
            "owners": [list(o) for o in placement.owners],
            "learners": [list(x) for x in placement.learners],
        }
        self.log.info("placement published", extra={"fields": fields})
        self._adopt(sorted(live - {s.shard}), placement)
        try:
            s.ctx.publish(keys.event(s.bus.swarm, "placement", s.shard), change)
        except zenoh.ZError as e:  # the session closing under a stopping shard: nobody to tell
            self.log.info(f"placement change not announced: {e}")

    # --- one tick -----------------------------------------------------------------------

    def _cut_off(self) -> bool:
        """Whether this shard's session has no link to the swarm now. Cut off, it sees no
        shard alive, which says nothing of them: it does not coordinate (one that did would
        drop every other member and publish a placement no other shard could follow). Back,
        it counts the others as a starting swarm's (``member_start_grace_s`` from now): the
        others reconnect one by one, each after its own retry delay."""
        assert self.live is not None
        if not self.live.reaches_swarm():
            if self.acting:
                self.log.warning("cut off from the swarm: not coordinating until the link is back")
            self.acting = False
            return True
        rejoined = self.live.rejoined_at()
        if rejoined > self._rejoined:
            self._rejoined = self._started = rejoined
            self._seen = {m: t for m, t in self._seen.items() if t >= rejoined}
            self.log.info("back in the swarm: the other members get the start grace")
        return False

    def _present(self, placement: Placement, live: set[int], now: float) -> set[int]:
        return present_members(
            placement.members,
            live,
            self._seen,
            started=self._started,
            now=now,
            grace_s=self.settings.member_grace_s,
            start_grace_s=self.settings.member_start_grace_s,
        )

    def tick(self) -> None:
        s = self.shard
        assert self.live is not None
        now = time.monotonic()
        if self._cut_off():
            return
        live = self.live.ids() | {s.shard}
        for m, t in self.live.gone_at().items():
            if t >= self._rejoined:  # tokens that went with this shard's own link say nothing
                self._seen[m] = max(self._seen.get(m, t), t)
        for m in live:
            self._seen[m] = now
        # The lowest shard here coordinates: here are the live ones and the members within
        # their grace (gone a moment, or not seen since this shard started or came back).
        # A shard that has not seen the lower ones' tokens yet, just started or just back
        # after its link was cut, does not take itself for the lowest.
        here = live | self._present(s.placement, live, now)
        if s.shard != min(here):
            self.acting = False
            return
        view: View = (
            frozenset(live),
            frozenset(self.live.draining_ids()),
            frozenset(self._present(s.placement, live, now)),
        )
        look = must_look(
            acting=self.acting,
            settled=s.placement.settled,
            confirmed=s.confirmed,
            view=view,
            last_view=self._view,
            dirty=self._dirty,
            learning=self._learning,
            since_look_s=now - self._looked,
            interval_s=self.settings.state_interval_s,
        )
        self._view = view
        if not look:
            return
        self._looked, self._dirty = now, False
        # Acting, it knows the placement: the shards following it need not send it back.
        known = s.placement.version if self.acting else None
        states = {m: st for m, st in self.states(known).items() if m in live}
        # The newest placement any live shard follows is the swarm's: on taking over, and
        # while acting too (a shard that did not see this one, say one back first after a
        # router restart, may have published one). Every placement is a safe step from the
        # one before it (owners stay until their learners have copied), so following the
        # newest loses nothing.
        newest = max(
            (p for st in states.values() if st.confirmed and (p := self._placement_of(st)) is not None),
            key=lambda p: p.version,
            default=s.placement,
        )
        if not self.acting or newest.version > s.placement.version:
            if newest.version > s.placement.version or not s.confirmed:
                s.follow(newest)
            fields = {"fields": {"version": s.placement.version}}
            if self.acting:
                self.log.warning(
                    "a shard follows a newer placement than the coordinator's: following it", extra=fields
                )
            else:
                self.log.info("acting as the index coordinator", extra=fields)
                # A new coordinator looks at a window of its own before it rebalances.
                self._load_mark = None
                self._learning, self._learning_looks, self._cost_mark = True, 0, None
            self.acting = True
        current = s.placement
        # Members gone for less than the grace (or not started yet) still count: a shard
        # restarting, or a swarm still starting, moves no group. Queries do not wait for
        # this: they go to a group's other owners as soon as one does not answer.
        present = self._present(current, live, now)
        # Draining shards are stopping: their groups go elsewhere while they still answer.
        draining = {m for m, st in states.items() if st.draining}
        present -= draining
        behind = sorted(
            m
            for m, st in states.items()
            if m != s.shard and (not st.confirmed or version_of(st) != current.version)
        )
        if behind:
            self._adopt(behind, current)
        if self._split(current, live):
            return  # no placement is made while part of the team is out of reach
        if not present:
            return  # every shard is stopping: nowhere to move anything
        if not current.settled:
            ready = {
                m: list(st.ready_groups) for m, st in states.items() if version_of(st) == current.version
            }
            ready[s.shard] = sorted(s.ready)
            done = promote(current, ready, present)
            if done is not None:
                self.publish(done, live, pb.PlacementReason.PLACEMENT_REASON_HANDOFF_DONE)
            return
        target = follow_members(current, present)
        reason = pb.PlacementReason.PLACEMENT_REASON_MEMBERS
        self._plan = None
        # The load of every present member, or no rebalancing: one on part of the swarm's
        # load (states lost to a timeout in an overloaded swarm) moves groups by mistake.
        if (
            target.owners == current.owners
            and set(target.members) == set(current.members)
            and present <= set(states)
        ):
            balanced = self._rebalanced(current, states)
            if balanced is not None:
                target, reason = balanced, pb.PlacementReason.PLACEMENT_REASON_REBALANCE
        # Owners gone for less than the grace stay owners (a restart keeps its groups);
        # draining ones are leaving: they answer and are copied from until the learners own.
        step = transition(current, target, alive=present | draining | live)
        if step is not None:
            plan = self._plan if reason == pb.PlacementReason.PLACEMENT_REASON_REBALANCE else None
            self.publish(step, live, reason, plan)

    def away(self, placement: Placement, live: set[int]) -> frozenset[int]:
        """The members of ``placement`` out of sight (not among the ``live`` shards) in a mesh
        (``hold_when_away``; empty otherwise). From here a robot in another part of a split
        team, one whose router died and one whose shard alone died look alike, so none of
        them is taken for gone. (The routers' own liveliness tokens would tell the last from
        the others, but a subscriber to them, and liveliness queries of them at each look,
        left zenoh 1.10 routers of a changing mesh whose own admin space stopped answering.)"""
        if not self.settings.hold_when_away:
            return frozenset()
        return frozenset(m for m in placement.members if m not in live)

    def _split(self, current: Placement, live: set[int]) -> bool:
        """Whether part of the team is away: then this coordinator changes nothing (module
        docstring); said once in the log each time the set of away members changes."""
        away = self.away(current, live)
        if away != self._away:
            fields = {"fields": {"away": sorted(away), "version": current.version}}
            if away:
                self.log.warning("part of the team is out of reach: placement held", extra=fields)
            else:
                self.log.info("the whole team is in reach again", extra=fields)
            self._away = away
        return bool(away)

    def _rebalanced(self, current: Placement, states: dict[int, pb.ShardState]) -> Placement | None:
        """A placement with a better balance under every partial query the shards served,
        looked for once ``rebalance_min_queries`` more were served since the last look, and
        taken when it lowers the busiest shard's load by ``MIN_GAIN`` at least; None otherwise."""
        totals: dict[int, int] = {}
        for st in states.values():
            try:
                served = served_load(st, len(current.groups))
            except WireError as e:
                self.log.warning(f"shard {st.shard_id}'s load ignored: {e}")
                continue
            for g, n in served.items():
                totals[g] = totals.get(g, 0) + n
        if self._load_mark is None:
            # Taking over: the load served so far is the window's start, not a reason to move.
            self._load_mark = totals
            return None
        # A shard that restarted counts from 0 again: never a negative load.
        window = {g: max(0, n - self._load_mark.get(g, 0)) for g, n in totals.items()}
        # A window of a few queries a shard is noise: it would move groups back and forth
        # (and every move is a handoff and a placement every querier must learn). So at
        # least QUERIES_PER_SHARD a member as well: a large swarm looks at a longer window.
        needed = max(self.settings.rebalance_min_queries, QUERIES_PER_SHARD * len(current.members))
        if sum(window.values()) < needed:
            return None
        self._load_mark = totals
        # Learning (asking every tick) ends once the load is within the target, or after
        # LEARNING_LOOKS windows: the first windows of a run see an index still nearly empty
        # (queries cheap, so a store's weight high) and loads still shifting, and the next
        # window may well plan better; under a steady load the plan no longer changes.
        self._learning_looks += 1
        self._learning = self._learning_looks < LEARNING_LOOKS
        load = {g: float(n) for g, n in totals.items()}
        weight = store_weight(states.values(), self._cost_mark)
        self._cost_mark = cost_totals(states.values())
        if balance_ratio(shard_loads(current, load, weight)) <= self.settings.rebalance_target:
            self._learning = False
            return None
        balanced = RULES[self.settings.rebalance_rule](
            current,
            load,
            target=self.settings.rebalance_target,
            store_weight=weight,
            min_replica_gain=MIN_REPLICA_GAIN,
        )
        if balanced.owners == current.owners:
            return None
        before = max(shard_loads(current, load, weight).values())
        after = max(shard_loads(balanced, load, weight).values())
        fields = {
            "queries": sum(totals.values()),
            "store_weight": round(weight, 3),
            "busiest_before": before,
            "busiest_after": after,
        }
        if after > (1.0 - MIN_GAIN) * before:
            self.log.info("rebalancing skipped: too small a gain", extra={"fields": fields})
            return None
        self.log.info("rebalancing", extra={"fields": fields})
        self._plan = pb.PlacementChange(
            queries=sum(totals.values()),
            store_weight=weight,
            busiest_before=before,
            busiest_after=after,
            mean_load=sum(shard_loads(balanced, load, weight).values()) / len(balanced.members),
        )
        return balanced
