"""Which index shards hold which label groups: placement, replicas, failover, rebalancing.

The descriptor index is cut into **groups** of labels (by default the paper's even
label ranges, one per robot). A query's partial descriptor goes group by group, and
a group's partial score depends only on the group, never on which shard computes
it: so the shards that hold a group can change, a group can have several replicas,
and a query may ask any one of them, without a single score changing. This module
decides *where* groups live; nothing here touches a score.

* :func:`place`: each group on ``replicas`` distinct shards, by rendezvous hashing
  (highest random weight): a deterministic function of the members, with minimal
  movement when a member joins or leaves (only the groups it held, or will hold, move).
* :func:`follow_members`: the next placement when members join or leave: every
  group keeps its live owners and gets new ones by rendezvous order, so a lost
  shard's groups are served at once by their other replicas.
* :func:`owner_load` and :func:`shard_loads`: the load a placement puts on each shard
  under observed load (partial queries per group). A query is spread over a group's
  replicas by :func:`serving_owner`, so a group of load ``L`` on ``r`` replicas puts
  ``L / r`` queries on each; but every replica also stores every slice of the group,
  the ``r - 1`` it was not asked for as a ``ShardStore`` of relative cost
  ``store_weight``. A replica only lightens its owners when a store costs less than a
  query (``store_weight < 1``), and less so the more there are. Where groups should
  live under that load is :mod:`swarmrec.core.rebalance`'s.
* :func:`serving_owner`: the replica of a group that answers a given query, chosen
  by a stable hash of (robot, frame, group) among the live owners.

Every placement has a ``version``; a shard answers only requests of its current
version (a stale sender is told to refresh), so no query is answered from a table
the shard no longer follows.

Changing owners is a handoff in two versions, so that no stored descriptor is ever
missing from a shard that answers for its group:

* :func:`transition` (version ``v + 1``): the shards a group gains are its
  *learners* (they take every new store of the group, and copy what the owners
  hold, but answer no query yet); the shards it will lose are *leaving* (they still
  answer). Owners that are gone are dropped at once: the other replicas answer.
* :func:`promote` (version ``v + 2``), once every live learner has copied its groups:
  learners become owners and the leaving owners let go.

A store goes to every owner and learner of its group (:meth:`Placement.store_targets`);
a shard switches version under the same lock its stores take, and serves a copy only
once it follows the new version, so a store acknowledged under the old version is in
the copy and one under the new version reached the learner directly.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

from swarmrec.errors import ConfigError

__all__ = [
    "Placement",
    "balance_ratio",
    "follow_members",
    "group_of_label",
    "groups_from_bounds",
    "owner_load",
    "place",
    "promote",
    "ring",
    "serving_owner",
    "shard_loads",
    "stable_hash",
    "transition",
]

_MASK = (1 << 64) - 1


def stable_hash(*values: int) -> int:
    """A 64-bit hash of integers that is the same in every process and every run
    (Python's ``hash`` is salted per process): one splitmix64 step per value, the value
    mixed into the state first (a single 0 gives splitmix64's first output from seed 0)."""
    x = 0
    for v in values:
        z = ((x ^ (v & _MASK)) + 0x9E3779B97F4A7C15) & _MASK
        z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & _MASK
        z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & _MASK
        x = z ^ (z >> 31)
    return x


def _unit(*values: int) -> float:
    """A stable pseudo-random number in (0, 1)."""
    return (stable_hash(*values) + 0.5) / float(1 << 64)


@dataclass(frozen=True)
class Placement:
    """Groups of labels, and the shards that hold each, primary first.

    ``groups[g]`` is the label range ``[lo, hi)`` of group ``g``; ``owners[g]`` the
    ids of the shards that store it (all of them store every descriptor of the
    group; any of them may answer a query for it).
    """

    version: int
    groups: tuple[tuple[int, int], ...]
    owners: tuple[tuple[int, ...], ...]
    members: tuple[int, ...]
    replicas: int = 2
    #: Per group, shards copying it before they own it (empty tuples: none); see :func:`transition`.
    learners: tuple[tuple[int, ...], ...] = ()
    #: Per group, owners that let go of it at the next :func:`promote`.
    leaving: tuple[tuple[int, ...], ...] = ()

    def __post_init__(self) -> None:
        n = len(self.groups)
        if not self.learners:
            object.__setattr__(self, "learners", ((),) * n)
        if not self.leaving:
            object.__setattr__(self, "leaving", ((),) * n)
        problems = []
        if len(self.owners) != n:
            problems.append(f"{len(self.groups)} groups but {len(self.owners)} owner lists")
        if len(self.learners) != n or len(self.leaving) != n:
            problems.append("learners and leaving must list every group")
        if self.version < 0:
            problems.append(f"version must be >= 0, got {self.version}")
        prev = 0
        for g, (lo, hi) in enumerate(self.groups):
            if lo != prev or hi <= lo:
                problems.append(f"group {g} is [{lo}, {hi}); groups must tile the labels in order")
            prev = hi
        members = set(self.members)
        if len(members) != len(self.members):
            problems.append("a member is listed twice")
        for g, own in enumerate(self.owners):
            if not own:
                problems.append(f"group {g} has no owner")
            if len(set(own)) != len(own):
                problems.append(f"group {g} lists an owner twice")
            if not set(own) <= members:
                problems.append(f"group {g} is owned by non-members {sorted(set(own) - members)}")
        for g, (learn, leave) in enumerate(zip(self.learners, self.leaving, strict=False)):
            owned: set[int] = set(self.owners[g]) if g < len(self.owners) else set()
            if set(learn) & owned or not set(learn) <= members or len(set(learn)) != len(learn):
                problems.append(f"group {g}'s learners must be members that do not own it yet")
            if not set(leave) <= owned or (owned and set(leave) == owned and not learn):
                problems.append(f"group {g}'s leaving owners must be owners, and not all of them")
        if problems:
            raise ConfigError("invalid placement: " + "; ".join(problems))

    @property
    def n_labels(self) -> int:
        return self.groups[-1][1] if self.groups else 0

    def groups_of(self, shard: int) -> list[int]:
        """The groups ``shard`` owns (answers queries for)."""
        return [g for g, own in enumerate(self.owners) if shard in own]

    def learning(self, shard: int) -> list[int]:
        """The groups ``shard`` is copying (stores them, answers no query for them)."""
        return [g for g, learn in enumerate(self.learners) if shard in learn]

    def store_targets(self, group: int) -> tuple[int, ...]:
        """Every shard that must store a descriptor of ``group``: owners, then learners."""
        return self.owners[group] + self.learners[group]

    @property
    def settled(self) -> bool:
        """No handoff in progress (no learner, no leaving owner)."""
        return not any(self.learners) and not any(self.leaving)

    def group_of_range(self, lo: int, hi: int) -> int | None:
        """The group whose label range is exactly ``[lo, hi)``, or None."""
        for g, rng in enumerate(self.groups):
            if rng == (lo, hi):
                return g
        return None

    def moved(self, other: Placement) -> dict[int, tuple[set[int], set[int]]]:
        """Per group, the shards that gain it and that lose it going from ``self`` to ``other``."""
        out = {}
        for g, (a, b) in enumerate(zip(self.owners, other.owners, strict=True)):
            gained, lost = set(b) - set(a), set(a) - set(b)
            if gained or lost:
                out[g] = (gained, lost)
        return out


def group_of_label(groups: Sequence[tuple[int, int]], label: int) -> int:
    """The group whose range holds ``label``."""
    for g, (lo, hi) in enumerate(groups):
        if lo <= label < hi:
            return g
    raise ValueError(f"label {label} is in no group")


def _rendezvous(group: int, candidates: Iterable[int], count: int) -> list[int]:
    """The ``count`` candidates with the highest rendezvous score for ``group``."""
    ranked = sorted(candidates, key=lambda m: (-_unit(group, m), m))
    return ranked[:count]


def place(
    groups: Sequence[tuple[int, int]], members: Iterable[int], *, replicas: int = 2, version: int = 0
) -> Placement:
    """Each group on ``min(replicas, members)`` shards by rendezvous hashing."""
    ids = tuple(sorted(set(members)))
    if not ids:
        raise ConfigError("a placement needs at least one member")
    if replicas < 1:
        raise ConfigError(f"replicas must be >= 1, got {replicas}")
    r = min(replicas, len(ids))
    owners = tuple(tuple(_rendezvous(g, ids, r)) for g in range(len(groups)))
    return Placement(version, tuple(groups), owners, ids, replicas)


def ring(groups: Sequence[tuple[int, int]], members: Sequence[int], *, replicas: int = 2) -> Placement:
    """Version 0, the placement every shard of a new swarm starts from without asking
    anyone: group ``g`` on members ``g, g + 1, ...`` (``replicas`` of them, wrapping). With
    one group per member and one replica, shard ``k`` holds label range ``k``: the
    paper's layout."""
    ids = tuple(sorted(set(members)))
    if not ids:
        raise ConfigError("a placement needs at least one member")
    if replicas < 1:
        raise ConfigError(f"replicas must be >= 1, got {replicas}")
    r = min(replicas, len(ids))
    owners = tuple(tuple(ids[(g + i) % len(ids)] for i in range(r)) for g in range(len(groups)))
    return Placement(0, tuple(groups), owners, ids, replicas)


def transition(
    current: Placement, target: Placement, *, alive: Iterable[int] | None = None
) -> Placement | None:
    """The first step from the settled ``current`` towards ``target``'s owners (same
    groups): version ``current.version + 1`` where owners that are not ``alive`` (default:
    ``target``'s members) go at once (a gone owner answers nothing), the owners ``target``
    adds are learners and the live ones it drops are leaving (they answer, and are copied
    from, until the learners own: a shard draining before it stops is one). A group whose
    every owner is gone keeps them listed (they come back with their stored records) and
    learns from nobody. None when there is nothing to do."""
    if not current.settled:
        raise ConfigError("a handoff is in progress: promote it first")
    if current.groups != target.groups:
        raise ConfigError("a placement keeps its groups")
    live = set(target.members) if alive is None else set(alive)
    owners: list[tuple[int, ...]] = []
    learners: list[tuple[int, ...]] = []
    leaving: list[tuple[int, ...]] = []
    for g, own in enumerate(current.owners):
        kept = tuple(m for m in own if m in live)
        if not kept:
            # Every owner gone: nobody to copy from; keep listing them until one comes back.
            owners.append(own)
            learners.append(())
            leaving.append(())
            continue
        want = target.owners[g]
        owners.append(kept)
        learners.append(tuple(m for m in want if m not in kept))
        leaving.append(tuple(m for m in kept if m not in want))
    members = tuple(sorted(set(target.members) | {m for own in owners for m in own}))
    if (
        tuple(owners) == current.owners
        and members == current.members
        and not any(learners)
        and not any(leaving)
    ):
        return None
    return Placement(
        current.version + 1,
        current.groups,
        tuple(owners),
        members,
        current.replicas,
        tuple(learners),
        tuple(leaving),
    )


def promote(current: Placement, ready: Mapping[int, Iterable[int]], alive: Iterable[int]) -> Placement | None:
    """The second step of a handoff, once every live learner is ``ready`` (shard ->
    the groups it has copied): learners become owners, leaving owners let go (never the
    last one that answers), gone learners are forgotten. None while a live learner is
    still copying, or when ``current`` is settled."""
    if current.settled:
        return None
    live = set(alive)
    done = {m: set(gs) for m, gs in ready.items()}
    owners = []
    for g, own in enumerate(current.owners):
        learn = [m for m in current.learners[g] if m in live]
        if any(g not in done.get(m, set()) for m in learn):
            return None
        new = tuple(m for m in own if m not in current.leaving[g]) + tuple(learn)
        owners.append(new or own)
    members = tuple(sorted(live | {m for own in owners for m in own}))
    return Placement(current.version + 1, current.groups, tuple(owners), members, current.replicas)


def follow_members(current: Placement, members: Iterable[int]) -> Placement:
    """The placement after members joined or left: live owners stay, lost replicas are
    replaced by the next live members in rendezvous order, and a joining member takes
    the groups rendezvous gives it (only those move). The version goes up when anything
    changed."""
    ids = tuple(sorted(set(members)))
    if not ids:
        raise ConfigError("a placement needs at least one member")
    joined = set(ids) - set(current.members)
    owners = []
    for g, own in enumerate(current.owners):
        want = max(min(current.replicas, len(ids)), min(len(own), len(ids)))
        kept = [m for m in own if m in ids]
        # A joining member that rendezvous ranks above a kept owner takes that owner's place.
        ranked = _rendezvous(g, ids, len(ids))
        for m in sorted(joined, key=ranked.index):
            if len(kept) >= want and kept:
                weakest = max(kept, key=ranked.index)
                if ranked.index(m) < ranked.index(weakest):
                    kept.remove(weakest)
                    kept.append(m)
            elif m not in kept:
                kept.append(m)
        for m in ranked:
            if len(kept) >= want:
                break
            if m not in kept:
                kept.append(m)
        owners.append(tuple(kept[:want]))
    changed = tuple(owners) != current.owners or ids != current.members
    version = current.version + 1 if changed else current.version
    return Placement(version, current.groups, tuple(owners), ids, current.replicas)


def owner_load(queries: float, owners: int, store_weight: float = 0.0) -> float:
    """The load one of ``owners`` replicas of a group bears when the group is queried
    ``queries`` times: ``queries / owners`` partial queries (each a search and a store),
    and the ``queries * (owners - 1) / owners`` slices the others were asked for, each a
    ``ShardStore`` costing ``store_weight`` of a query. So one more replica changes every
    owner's load by ``queries * (store_weight - 1) / (owners * (owners + 1))``: it helps
    only while a store is cheaper than a query."""
    return queries / owners * (1.0 + store_weight * (owners - 1))


def shard_loads(
    placement: Placement, group_load: Mapping[int, float], store_weight: float = 0.0
) -> dict[int, float]:
    """Expected load of each member when a group's queries are spread evenly over its owners
    and each owner stores the slices the others were asked for (:func:`owner_load`)."""
    _check_weight(store_weight)
    out = dict.fromkeys(placement.members, 0.0)
    for g, own in enumerate(placement.owners):
        share = owner_load(float(group_load.get(g, 0.0)), len(own), store_weight)
        for m in own:
            out[m] += share
    return out


def balance_ratio(loads: Mapping[int, float] | Sequence[float]) -> float:
    """Worst balance ratio: the busiest member's load over the mean (1.0 is perfect; 0 when idle)."""
    values = list(loads.values()) if isinstance(loads, Mapping) else list(loads)
    mean = sum(values) / len(values) if values else 0.0
    return max(values) / mean if mean > 0 else 0.0


def serving_owner(
    placement: Placement, group: int, robot: int, frame: int, alive: Iterable[int]
) -> int | None:
    """The owner of ``group`` that answers the query of ``robot``'s ``frame``: a stable choice
    among the live owners (None when none is alive)."""
    live = [m for m in placement.owners[group] if m in set(alive)]
    if not live:
        return None
    return live[stable_hash(robot, frame, group) % len(live)]


def groups_from_bounds(bounds: Sequence[int]) -> tuple[tuple[int, int], ...]:
    """Groups from range boundaries ``[0, b1, ..., n_labels]``; an empty range is no group.

    With more robots than labels the paper's split leaves some ranges empty: a group
    holds at least one label, so group ``g`` is the ``g``-th non-empty range."""
    pairs = ((int(bounds[i]), int(bounds[i + 1])) for i in range(len(bounds) - 1))
    return tuple((lo, hi) for lo, hi in pairs if hi > lo)


def _check_weight(store_weight: float) -> None:
    if not (math.isfinite(store_weight) and store_weight >= 0.0):
        raise ConfigError(f"a store's weight must be finite and at least 0, got {store_weight}")
