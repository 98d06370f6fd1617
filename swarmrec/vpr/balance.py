"""Re-balancing cluster owners from observed load, beyond the paper.

The paper trades recall for balance: more clusters per robot, assigned at random, spread the
deployment's narrow part of the descriptor space over more robots, but every extra cell
boundary cuts true matches apart (its Fig. 7). Two observations make a better trade:

1. An owner searches *everything* it stores, across all its clusters, so a match cut by a
   boundary is still found when the same robot owns both sides.
2. Which clusters are busy, and which touch, can be *observed* during the mission: each
   owner counts the queries of each of its clusters, and for each query the pair (nearest
   centre, second-nearest centre), which every robot can compute since all know the centres.

So the mission starts with the paper's random assignment of ``c`` clusters per robot (many
small cells); after a warm-up share of the queries the owners publish those counts (``k``
loads and a sparse ``k x k`` adjacency: a few kB once), and every robot computes the same new
table with :func:`balanced_assignment`:

* clusters are taken from the busiest down; each goes to the robot, among those whose load
  stays under ``(1 + slack) x`` the even share, that already owns the most adjacent load
  (adjacency counts to its clusters); ties to the least loaded robot, then the lowest id; when
  no robot has room, to the least loaded one. Regions of touching cells thus grow on one
  owner up to its capacity, and boundaries between owners fall where few queries lie;
* a cluster busier than the capacity alone is first split (:func:`split_hot_clusters`): its
  owner runs 2-means on the descriptors it stored for it and publishes the two new centres.

Clusters that change owner move their stored descriptors to the new owner (counted by the
evaluation as bytes), so nothing seen before is lost. The function is deterministic: the same
counts give every robot the same table, with no coordinator.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from swarmrec.errors import ConfigError
from swarmrec.vpr.clusters import Assignment, nearest_centre, train_centres
from swarmrec.vpr.vectors import as_descriptors

__all__ = [
    "LoadReport",
    "balanced_assignment",
    "boundary_margin",
    "observe",
    "replica_owners",
    "split_hot_clusters",
]

Float32Array = npt.NDArray[np.float32]
FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True, eq=False)
class LoadReport:
    """What the owners publish after the warm-up: queries per cluster, and how often each pair
    of clusters was a query's nearest and second-nearest centre (symmetric)."""

    loads: IntArray
    adjacency: IntArray

    def __post_init__(self) -> None:
        k = len(self.loads)
        if self.adjacency.shape != (k, k):
            raise ConfigError(f"adjacency must be ({k}, {k}), got {self.adjacency.shape}")


def _two_nearest(centres: Float32Array, x: Float32Array) -> tuple[IntArray, IntArray, FloatArray]:
    """Nearest and second-nearest centre of each row, and the gap ``d2^2 - d1^2`` between them."""
    c = centres.astype(np.float64)
    cost = (c * c).sum(1)[None, :] - 2.0 * (x.astype(np.float64) @ c.T)
    order = np.argsort(cost, axis=1, kind="stable")
    rows = np.arange(len(x))
    gap = cost[rows, order[:, 1]] - cost[rows, order[:, 0]]
    return order[:, 0].astype(np.int64), order[:, 1].astype(np.int64), gap


def observe(centres: Float32Array, descriptors: npt.NDArray[np.floating]) -> LoadReport:
    """The counts of the warm-up queries ``descriptors`` (each owner counts its own; the sum is this)."""
    x = as_descriptors(descriptors, centres.shape[1])
    k = len(centres)
    if k < 2:
        raise ConfigError("observing adjacency needs at least two centres")
    first, second, _ = _two_nearest(centres, x)
    loads = np.bincount(first, minlength=k).astype(np.int64)
    adjacency = np.zeros((k, k), np.int64)
    np.add.at(adjacency, (first, second), 1)
    return LoadReport(loads, adjacency + adjacency.T)


def split_hot_clusters(
    centres: Float32Array, descriptors: npt.NDArray[np.floating], max_load: float, seed: int
) -> Float32Array:
    """Split every cluster holding more than ``max_load`` of the observed ``descriptors`` in two
    (2-means on its own descriptors), again until none does or a split would leave a half
    empty. Returns the new centres: the old ones first (unchanged indices, a split cluster's
    centre replaced by its first half), the second halves appended."""
    x = as_descriptors(descriptors, centres.shape[1])
    out = [c for c in np.asarray(centres, np.float32)]
    for _ in range(len(x)):  # each split adds a centre; this bounds the loop
        nearest = nearest_centre(np.stack(out), x)
        loads = np.bincount(nearest, minlength=len(out))
        hot = int(np.argmax(loads))
        members = x[nearest == hot]
        if loads[hot] <= max_load or len(np.unique(members, axis=0)) < 2:
            break
        halves = train_centres(members, 2, seed)
        out[hot] = halves[0]
        out.append(halves[1])
    return np.stack(out).astype(np.float32)


def balanced_assignment(
    report: LoadReport, n_robots: int, slack: float = 0.25, previous: Assignment | None = None
) -> Assignment:
    """The load- and adjacency-aware table of the module docstring. With ``previous``, a cluster
    stays with its previous owner when that is as good (equal adjacency), which saves moving
    its stored descriptors (clusters past the previous table's, new halves, have none)."""
    if n_robots < 1:
        raise ConfigError(f"n_robots must be >= 1, got {n_robots}")
    if not slack >= 0:
        raise ConfigError(f"slack must be >= 0, got {slack}")
    k = len(report.loads)
    loads = report.loads.astype(np.float64)
    capacity = (1.0 + slack) * loads.sum() / n_robots
    owners = np.full(k, -1, np.int64)
    robot_load = np.zeros(n_robots)
    # affinity[r, j]: adjacency of cluster j to the clusters robot r owns so far.
    affinity = np.zeros((n_robots, k))
    before = np.full(k, -1, np.int64)
    if previous is not None:
        known = min(k, previous.n_clusters)
        before[:known] = previous.owner_array()[:known]
    for cluster in np.lexsort((np.arange(k), -loads)).tolist():
        room = robot_load + loads[cluster] <= capacity
        candidates = np.flatnonzero(room) if room.any() else np.array([int(np.argmin(robot_load))])
        # Most adjacent load first, then the previous owner, then least loaded, then lowest id.
        moved = candidates != before[cluster]
        keys = (candidates, robot_load[candidates], moved, -affinity[candidates, cluster])
        best = candidates[np.lexsort(keys)[0]]
        owners[cluster] = best
        robot_load[best] += loads[cluster]
        affinity[best] += report.adjacency[cluster]
    return Assignment(
        tuple(int(o) for o in owners),
        n_robots,
        "load-adjacency",
        None,
        {"slack": slack, "observed_queries": int(loads.sum())},
    )


def boundary_margin(centres: Float32Array, descriptors: npt.NDArray[np.floating], share: float) -> float:
    """The gap ``d2^2 - d1^2`` under which ``share`` of ``descriptors`` lie: descriptors this close
    to a boundary between two cells are the ones whose true matches fall on the other side."""
    if not 0.0 <= share <= 1.0:
        raise ConfigError(f"share must be in [0, 1], got {share}")
    if share == 0.0:
        return -1.0
    _, _, gap = _two_nearest(centres, as_descriptors(descriptors, centres.shape[1]))
    return float(np.quantile(gap, share))


def replica_owners(
    centres: Float32Array, assignment: Assignment, descriptors: npt.NDArray[np.floating], margin: float
) -> IntArray:
    """For each descriptor, the owner of its second-nearest centre when the gap to it is at most
    ``margin`` and that owner is another robot than the nearest's; -1 otherwise. Storing such a
    descriptor there too (not querying there) lets a later query on the other side of the
    boundary find it, at the cost of one more upload and no extra search load."""
    first, second, gap = _two_nearest(centres, as_descriptors(descriptors, centres.shape[1]))
    owners = assignment.owner_array()
    near = (gap <= margin) & (owners[second] != owners[first])
    replicas: IntArray = np.where(near, owners[second], -1).astype(np.int64)
    return replicas
