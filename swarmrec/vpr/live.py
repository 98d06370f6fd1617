"""Re-balancing a live swarm's cluster owners: the tables, the owners' loads, the next table.

The offline re-balancing (:mod:`swarmrec.vpr.balance`) plays a rule over a whole mission's
descriptors. A live swarm has no such view: each owner sees the queries routed to it. So a
re-balancing (docs/vpr.md, "Re-balancing a live swarm") goes:

1. The coordinator (the lowest live place-owner) asks every owner for its load since the
   current table began (:func:`owner_load`): queries per cluster, how its queries lie between
   cells (nearest and second-nearest centre pairs, the gap between them), and the splits of
   its own clusters busier than the capacity (2-means on the descriptors they received, the
   offline :func:`~swarmrec.vpr.balance.split_hot_clusters` on that owner's queries).
2. It merges them (:func:`merge_loads`): the split centres replace and extend the table's,
   each owner's new halves numbered after the table's k in robot order.
3. It plans the next table (:func:`next_table`) with the offline rules: a new plan from the
   start table (:func:`~swarmrec.vpr.balance.balanced_assignment`), repairs after
   (:func:`~swarmrec.vpr.balance.repair_assignment`), and the copy margin
   (:func:`~swarmrec.vpr.balance.boundary_margin`'s quantile, of the gaps the owners sent).
4. Every owner adopts it and moves what it holds to where the table puts it
   (:meth:`LiveTable.holders`: each stored descriptor's owner and copy holders).

A :class:`LiveTable` is immutable, so a querier routes with one snapshot while an owner
adopts the next. Everything here is plain computation, the same for any caller; the service
(:mod:`swarmrec.services.place_owner`) does the talking.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from swarmrec.errors import ConfigError
from swarmrec.vpr.balance import (
    LoadReport,
    RebalanceRule,
    _two_nearest,
    balanced_assignment,
    repair_assignment,
    replica_owners,
    split_hot_clusters,
)
from swarmrec.vpr.clusters import Assignment, Router, nearest_centre
from swarmrec.vpr.quantize import Int8Quantizer

__all__ = [
    "MAX_CLUSTERS",
    "MAX_SPLITS",
    "MAX_WINDOW",
    "LiveTable",
    "MergedLoad",
    "OwnerLoad",
    "Window",
    "as_int8_exact",
    "merge_loads",
    "next_table",
    "owner_load",
    "split_allowed",
]

Float32Array = npt.NDArray[np.float32]
IntArray = npt.NDArray[np.int64]

#: A table may have at most this many clusters (a received one with more is refused; splits
#: stop there): 4096 x 128 float32 centres are 2 MiB.
MAX_CLUSTERS = 4096
#: A load request may split an owner's queries into at most this many more clusters: a
#: capacity below ``queries / MAX_SPLITS`` is refused (each split searches every query again).
#: A swarm's own capacity is ``1.25 x`` an even share, ``queries / n_robots`` or more.
MAX_SPLITS = 512
#: An owner keeps at most this many of a table's queries for its splits and gaps (2 kB each
#: at d = 128: 128 MiB at most); it counts every query.
MAX_WINDOW = 65536


def split_allowed(queries: int, split_above: float) -> bool:
    """Whether a load request's capacity ``split_above`` keeps the splits of ``queries`` under
    :data:`MAX_SPLITS` (inf, or 0 queries, always does)."""
    return queries == 0 or split_above * MAX_SPLITS >= queries


def as_int8_exact(rows: npt.NDArray[np.floating]) -> Float32Array:
    """``rows`` through the int8 code and back: values an int8 code carries exactly (a decoded
    code encodes to the same code)."""
    x = np.asarray(rows, np.float32).reshape(len(rows), -1)
    quantizer = Int8Quantizer(x.shape[1])
    return quantizer.decode(quantizer.encode(x)).astype(np.float32)


@dataclass(frozen=True, eq=False)
class LiveTable:
    """One version of a swarm's routing: centres and owners (the router), and the copy rule."""

    router: Router
    #: Copies go to next-nearest cells' owners within this gap (< 0: no copies; inf: all).
    copy_margin: float = -1.0
    #: At most this many other robots hold a copy.
    copy_neighbours: int = 1

    @property
    def version(self) -> int:
        return self.router.assignment.version

    @property
    def assignment(self) -> Assignment:
        return self.router.assignment

    @property
    def centres(self) -> Float32Array:
        return self.router.centres

    @property
    def copies(self) -> bool:
        return self.copy_margin >= 0 and self.assignment.n_robots > 1

    def copy_holders(self, descriptors: npt.NDArray[np.floating]) -> IntArray:
        """``(N, copy_neighbours)`` robots that also store each descriptor (-1: none)."""
        x = np.asarray(descriptors, np.float32).reshape(-1, self.router.dimension)
        if not self.copies:
            return np.full((len(x), 1), -1, np.int64)
        return replica_owners(self.centres, self.assignment, x, self.copy_margin, self.copy_neighbours)

    def holders(self, descriptors: npt.NDArray[np.floating]) -> list[set[int]]:
        """Per stored descriptor, every robot the table puts it at: its owner and copy holders."""
        x = np.asarray(descriptors, np.float32).reshape(-1, self.router.dimension)
        if len(x) == 0:
            return []
        _, owners = self.router.route_many(x)
        copies = self.copy_holders(x)
        return [{int(o)} | {int(r) for r in row if r >= 0} for o, row in zip(owners, copies, strict=True)]


@dataclass
class Window:
    """What an owner keeps of one table's queries (not thread-safe; the service locks)."""

    #: The table version the window belongs to.
    version: int
    queries: int = 0
    rows: list[Float32Array] = field(default_factory=list)

    def add(self, descriptor: Float32Array) -> None:
        self.queries += 1
        if len(self.rows) < MAX_WINDOW:
            self.rows.append(descriptor)

    def descriptors(self, dimension: int) -> Float32Array:
        if not self.rows:
            return np.zeros((0, dimension), np.float32)
        return np.stack(self.rows).astype(np.float32)


@dataclass(frozen=True, eq=False)
class OwnerLoad:
    """One owner's load since its table began (``swarmrec.v1.ClusterLoad`` on the wire):
    clusters ``k, k + 1, ...`` are its new halves, ``new_centres`` in order."""

    robot: int
    version: int
    #: Queries per cluster: the table's k, then the new halves.
    loads: IntArray
    #: Own clusters a split re-centred, and their new centres ``(len(replaced), d)``.
    replaced: tuple[int, ...]
    replaced_centres: Float32Array
    #: The second halves of the splits ``(m, d)``.
    new_centres: Float32Array
    #: How often (pair_a, pair_b) were a query's nearest and second-nearest cells.
    pair_a: IntArray
    pair_b: IntArray
    pair_count: IntArray
    #: Each query's gap d2^2 - d1^2.
    gaps: npt.NDArray[np.float32]


def owner_load(table: LiveTable, robot: int, window: Window, split_above: float, seed: int) -> OwnerLoad:
    """Robot ``robot``'s :class:`ClusterLoad` for ``table`` from the queries it received: its own
    clusters busier than ``split_above`` split (halves appended after the table's k), then per
    cluster loads, nearest/second-nearest pairs and gaps of the queries under those centres."""
    x = window.descriptors(table.router.dimension)
    k = table.assignment.n_clusters
    centres = table.centres
    own = set(table.assignment.clusters_of(robot))
    if len(x) and split_above >= 1 and k < MAX_CLUSTERS and own:
        # Split only this owner's clusters: hide the others' queries from the split, which picks
        # the busiest cluster of what it is given.
        mine = x[np.isin(nearest_centre(centres, x), sorted(own))]
        if len(mine):
            centres = split_hot_clusters(centres, mine, split_above, seed)[:MAX_CLUSTERS]
    changed = [c for c in range(len(centres)) if c >= k or not np.array_equal(centres[c], table.centres[c])]
    if changed:
        # New centres travel as int8 codes (132 B, not 512): make them exactly what a code decodes
        # to, here, so the owners' routing and the offline replay use the very same values.
        centres = centres.copy()
        centres[changed] = as_int8_exact(centres[changed])
    replaced = tuple(c for c in sorted(own) if not np.array_equal(centres[c], table.centres[c]))
    empty = np.zeros(0, np.int64)
    pairs: tuple[IntArray, IntArray, IntArray] = (empty, empty, empty)
    gaps = np.zeros(0, np.float32)
    loads = np.zeros(len(centres), np.int64)
    if len(x) and len(centres) >= 2:
        first, second, gap = _two_nearest(centres, x)
        loads = np.bincount(first, minlength=len(centres)).astype(np.int64)
        unique, counts = np.unique(np.stack([first, second], 1), axis=0, return_counts=True)
        pairs = (unique[:, 0].astype(np.int64), unique[:, 1].astype(np.int64), counts.astype(np.int64))
        gaps = gap.astype(np.float32)
    return OwnerLoad(
        robot, table.version, loads, replaced, centres[list(replaced)].astype(np.float32),
        centres[k:].astype(np.float32), *pairs, gaps,
    )  # fmt: skip


@dataclass(frozen=True, eq=False)
class MergedLoad:
    """The swarm's load on the next table's centres: the table's, split ones replaced, new halves after."""

    centres: Float32Array
    report: LoadReport
    gaps: npt.NDArray[np.float64]

    @property
    def queries(self) -> int:
        return int(self.report.loads.sum())


def merge_loads(table: LiveTable, loads: Sequence[OwnerLoad]) -> MergedLoad:
    """Merge the owners' reports (any order; ``ConfigError`` for one that does not fit
    ``table``): a replaced centre counts only from the cluster's owner, each owner's halves
    are numbered after k in robot order, loads and pair counts are summed on those numbers."""
    d, k = table.router.dimension, table.assignment.n_clusters
    centres = table.centres.copy()
    added: list[Float32Array] = []
    numbering: dict[int, IntArray] = {}
    for load in sorted(loads, key=lambda m: m.robot):
        if load.version != table.version:
            raise ConfigError(f"robot {load.robot}'s load is of version {load.version}, not {table.version}")
        new = load.new_centres.reshape(-1, d)
        swapped = load.replaced_centres.reshape(-1, d)
        if len(swapped) != len(load.replaced) or len(load.loads) != k + len(new) or load.robot in numbering:
            raise ConfigError(f"robot {load.robot}'s load does not fit a table of {k} clusters")
        if not (np.isfinite(new).all() and np.isfinite(swapped).all()):
            raise ConfigError(f"robot {load.robot}'s centres must be finite")
        for cluster, row in zip(load.replaced, swapped, strict=True):
            if cluster < k and table.assignment.owners[cluster] == load.robot:
                centres[cluster] = row
        start = k + sum(len(a) for a in added)
        numbering[load.robot] = np.concatenate([np.arange(k), start + np.arange(len(new))]).astype(np.int64)
        added.append(new)
    merged = np.concatenate([centres, *added]).astype(np.float32) if added else centres
    if len(merged) > MAX_CLUSTERS:
        raise ConfigError(f"the owners' splits would make {len(merged)} clusters, more than {MAX_CLUSTERS}")
    n = len(merged)
    totals = np.zeros(n, np.int64)
    adjacency = np.zeros((n, n), np.int64)
    gaps: list[npt.NDArray[np.float32]] = []
    for load in loads:
        index = numbering[load.robot]
        totals[index] += load.loads
        a, b, c = load.pair_a, load.pair_b, load.pair_count
        fits = len(a) == len(b) == len(c) and (
            len(a) == 0 or (min(a.min(), b.min()) >= 0 and max(a.max(), b.max()) < len(index))
        )
        if not fits or (len(c) and c.min() < 0) or load.loads.min(initial=0) < 0:
            raise ConfigError(f"robot {load.robot}'s pairs do not fit its clusters")
        np.add.at(adjacency, (index[a], index[b]), c)
        gaps.append(load.gaps)
    all_gaps = np.concatenate(gaps).astype(np.float64) if gaps else np.zeros(0)
    return MergedLoad(merged, LoadReport(totals, adjacency + adjacency.T), all_gaps[np.isfinite(all_gaps)])


def next_table(table: LiveTable, merged: MergedLoad, rule: RebalanceRule) -> LiveTable:
    """The table after ``table`` from the merged load, by the offline rules: a plan when
    ``table`` is the first (version 0), a repair otherwise; the copy margin is the
    ``rule.replica_share`` quantile of the queries' gaps (1: every descriptor, 0: none)."""
    n = table.assignment.n_robots
    if table.version == 0:
        assignment = balanced_assignment(merged.report, n, rule.slack, previous=table.assignment)
    else:
        assignment = repair_assignment(merged.report, table.assignment, rule.slack)
    if rule.replica_share == 0.0:
        margin = -1.0
    elif rule.replica_share == 1.0 or len(merged.gaps) == 0:
        margin = math.inf
    else:
        margin = float(np.quantile(merged.gaps, rule.replica_share))
    version = table.version + 1
    owners = Assignment(assignment.owners, n, assignment.method, None, assignment.extra, version)
    return LiveTable(Router(merged.centres, owners), margin, rule.neighbours)
