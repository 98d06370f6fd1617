"""Where the index's label groups should live under the load the shards observe.

:func:`rebalance` plans a placement in two steps, both deterministic:

1. **How many owners each group gets.** Every group starts at the placement's
   ``replicas``; then the group whose share on each of its owners is the largest gets
   one owner more, as long as that lowers the busiest shard of the packed plan (step 2)
   and lowers the group's share by ``min_replica_gain`` at least. A replica spreads a
   group's queries (each query goes to one owner) but every owner stores every slice,
   the ones it was not asked for as ShardStores of relative cost ``store_weight``
   (:func:`~swarmrec.core.placement.owner_load`), so each replica helps less than the
   last and none helps once a store costs what a query does.
2. **Which shards own them**: the groups' shares packed onto the members largest first,
   each share on the least loaded member that does not hold the group yet (longest
   processing time first, which is within 4/3 of the best packing). Then again, keeping
   each group's current owners wherever that does not make the busiest shard busier than
   the first packing's: the plan's quality is the packing's, and only the groups that must
   move do (every move is a handoff, and a placement every querier must learn).

The first rule of this module (``swarmrec.core.placement`` before it) was a greedy walk
that moved one group at a time off the busiest shard and stopped at the first move that
did not help: on the TUM sequence's load, at the store weight the shards measure, it
stopped at 1.35 times the mean where a packing reaches 1.17 (tests/unit/test_rebalance.py).

A placement already within ``target`` of the mean is left as it is: under a steady load
the plan is the same at every look, so the placement settles.
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Iterable, Mapping, Sequence

from swarmrec.core.placement import Placement, balance_ratio, owner_load, shard_loads
from swarmrec.errors import ConfigError

__all__ = ["RULES", "greedy_rebalance", "pack", "plan_replicas", "rebalance"]


def pack(
    shares: Sequence[float],
    counts: Sequence[int],
    members: Sequence[int],
    *,
    keep: Sequence[Sequence[int]] | None = None,
    cap: float = math.inf,
) -> tuple[list[list[int]], dict[int, float]]:
    """``counts[g]`` distinct owners for each group, its ``shares[g]`` on each: largest shares
    first, each on the least loaded member not holding the group yet (ties: the lower id).
    With ``keep`` (the current owners of each group), a current owner keeps its group as long
    as its load stays within ``cap``. Returns the owners of each group and each member's load."""
    if any(c > len(members) for c in counts):
        raise ConfigError("a group cannot have more owners than there are members")
    load = dict.fromkeys(members, 0.0)
    # A heap of (load, member); entries go stale when a member's load changes, and are
    # skipped when popped (the load they carry is no longer the member's).
    heap = [(0.0, m) for m in members]
    heapq.heapify(heap)
    owners: list[list[int]] = [[] for _ in shares]
    for g in sorted(range(len(shares)), key=lambda g: (-shares[g], g)):
        chosen = owners[g]
        share = shares[g]
        for m in keep[g] if keep is not None else ():
            if len(chosen) < counts[g] and m in load and load[m] + share <= cap:
                chosen.append(m)
        skipped: list[tuple[float, int]] = []
        while len(chosen) < counts[g]:
            entry = heapq.heappop(heap)
            level, m = entry
            if level != load[m]:
                continue  # stale
            if m in chosen:
                skipped.append(entry)
                continue
            chosen.append(m)
        for m in chosen:
            load[m] += share
            heapq.heappush(heap, (load[m], m))
        for entry in skipped:
            heapq.heappush(heap, entry)
    return owners, load


def plan_replicas(
    group_load: Sequence[float],
    floor: int,
    members: Sequence[int],
    *,
    store_weight: float,
    min_replica_gain: float,
    target: float,
) -> list[int]:
    """Owners per group (step 1 of the module docstring): ``floor`` each, then one more for the
    group with the largest share while that lowers the packed plan's busiest shard."""
    n = len(members)
    counts = [min(floor, n)] * len(group_load)

    def shares(c: Sequence[int]) -> list[float]:
        return [owner_load(q, k, store_weight) for q, k in zip(group_load, c, strict=True)]

    def busiest(c: Sequence[int]) -> float:
        return max(pack(shares(c), c, members)[1].values(), default=0.0)

    best = busiest(counts)
    # Each round adds one owner somewhere; there are at most n - floor rounds a group.
    for _ in range(len(group_load) * n):
        now = shares(counts)
        total = sum(s * k for s, k in zip(now, counts, strict=True))
        if total <= 0.0 or best <= target * total / n:
            break
        hot = max(range(len(counts)), key=lambda g: (now[g], -g))
        k = counts[hot]
        if k >= n or owner_load(group_load[hot], k + 1, store_weight) > (1.0 - min_replica_gain) * now[hot]:
            break
        trial = list(counts)
        trial[hot] = k + 1
        after = busiest(trial)
        if after >= best:
            break
        counts, best = trial, after
    return counts


def rebalance(
    current: Placement,
    group_load: Mapping[int, float],
    *,
    target: float = 1.5,
    store_weight: float = 0.0,
    min_replica_gain: float = 0.0,
) -> Placement:
    """A placement whose busiest shard under ``group_load`` (partial queries per group) is as
    low as the packing of the module docstring gets it, or ``current`` itself when its worst
    balance ratio is at most ``target`` already or the plan is not better. Every group keeps
    at least ``current.replicas`` owners (fewer only when there are fewer members), so a lost
    shard never takes a group with it. Deterministic."""
    _check(group_load.values(), store_weight, target)
    members = list(current.members)
    now = shard_loads(current, group_load, store_weight)
    if balance_ratio(now) <= target:
        return current
    loads = [float(group_load.get(g, 0.0)) for g in range(len(current.groups))]
    counts = plan_replicas(
        loads,
        current.replicas,
        members,
        store_weight=store_weight,
        min_replica_gain=min_replica_gain,
        target=target,
    )
    shares = [owner_load(q, k, store_weight) for q, k in zip(loads, counts, strict=True)]
    packed, packed_load = pack(shares, counts, members)
    cap = max(packed_load.values())
    kept, kept_load = pack(shares, counts, members, keep=current.owners, cap=cap)
    owners = kept if max(kept_load.values()) <= cap else packed
    # A group's current owners first, in their order (which owner answers a query is a hash
    # over the list), new ones after.
    ordered = tuple(
        tuple([m for m in current.owners[g] if m in own] + [m for m in own if m not in current.owners[g]])
        for g, own in enumerate(owners)
    )
    if ordered == current.owners or max(_loads_of(ordered, shares, members).values()) >= max(now.values()):
        return current
    return Placement(current.version + 1, current.groups, ordered, current.members, current.replicas)


def greedy_rebalance(
    current: Placement,
    group_load: Mapping[int, float],
    *,
    target: float = 1.5,
    max_changes: int = 64,
    store_weight: float = 0.0,
    min_replica_gain: float = 0.0,
) -> Placement:
    """The rule this module's :func:`rebalance` replaced, kept as the baseline the benchmarks
    measure it against (``IndexSettings.rebalance_rule = "greedy"``).

    While the worst balance ratio under ``group_load`` is above ``target``: the busiest
    shard's hottest group gets one more replica on the least loaded shard, or, when that
    does not help (a store costs as much as a query) or it is everywhere already, a group
    moves off the busiest shard. A step is taken only when it lowers the busiest shard's
    load and lifts no shard to it; a replica only when it also lowers each owner's share
    of its group by ``min_replica_gain``. At most ``max_changes`` steps; every group keeps
    at least its ``replicas`` owners. Deterministic."""
    _check(group_load.values(), store_weight, target)
    owners = [list(o) for o in current.owners]
    members = list(current.members)

    def share(g: int, n_owners: int) -> float:
        return owner_load(float(group_load.get(g, 0.0)), n_owners, store_weight)

    def loads() -> dict[int, float]:
        out = dict.fromkeys(members, 0.0)
        for g, own in enumerate(owners):
            for m in own:
                out[m] += share(g, len(own))
        return out

    def helps(now: dict[int, float], busiest: int, g: int, trial: list[int]) -> bool:
        """Whether ``g`` on ``trial`` instead lowers the busiest load and lifts none to it."""
        after = dict(now)
        for m in owners[g]:
            after[m] -= share(g, len(owners[g]))
        for m in trial:
            after[m] += share(g, len(trial))
        top = now[busiest]
        return after[busiest] < top and all(after[m] < top for m in set(trial) | set(owners[g]))

    for _ in range(max_changes):
        now = loads()
        if balance_ratio(now) <= target:
            break
        busiest = max(members, key=lambda m: (now[m], -m))
        idle = min(members, key=lambda m: (now[m], m))
        held = sorted(
            (g for g, own in enumerate(owners) if busiest in own),
            key=lambda g: (-share(g, len(owners[g])), g),
        )
        step = None
        for g in held:
            k = len(owners[g])
            if idle not in owners[g] and share(g, k + 1) <= (1.0 - min_replica_gain) * share(g, k):
                trial = owners[g] + [idle]
                if helps(now, busiest, g, trial):
                    step = (g, trial)
                    break
        if step is None:
            # No replica helps (every hot group is on the idle shard already, or stores cost
            # as much as the queries they would spread): move one replica off the busiest.
            for g in held:
                others = [m for m in members if m not in owners[g]]
                if not others:
                    continue
                dest = min(others, key=lambda m: (now[m], m))
                trial = [dest if m == busiest else m for m in owners[g]]
                if helps(now, busiest, g, trial):
                    step = (g, trial)
                    break
        if step is None:
            break
        g, trial = step
        owners[g] = trial
    new = tuple(tuple(o) for o in owners)
    version = current.version + 1 if new != current.owners else current.version
    return Placement(version, current.groups, new, current.members, current.replicas)


#: The rules by name (``IndexSettings.rebalance_rule``): the plan, and the rule it replaced.
RULES = {"pack": rebalance, "greedy": greedy_rebalance}


def _loads_of(
    owners: Sequence[Sequence[int]], shares: Sequence[float], members: Iterable[int]
) -> dict[int, float]:
    """Each member's load when group ``g`` puts ``shares[g]`` on each of ``owners[g]``."""
    out = dict.fromkeys(members, 0.0)
    for own, share in zip(owners, shares, strict=True):
        for m in own:
            out[m] += share
    return out


def _check(values: Iterable[float], store_weight: float, target: float) -> None:
    for v in values:
        if not math.isfinite(v) or v < 0:
            raise ConfigError(f"a load must be a finite number >= 0, got {v}")
    if not (math.isfinite(store_weight) and store_weight >= 0.0):
        raise ConfigError(f"a store's weight must be finite and at least 0, got {store_weight}")
    if not target > 0.0:
        raise ConfigError(f"a rebalancing target must be > 0, got {target}")
