"""The swarm offline: robots, lock-step queries through real owner indexes, and what is scored.

**Robots.** One deployment sequence of N frames is cut into ``n`` consecutive
sub-trajectories of ``ceil(N / n)`` frames (the last one shorter): robot ``r`` owns frames
``[r * ceil(N / n), ...)``, as the paper split KITTI 00 and as the project's constellation
evaluation does.

**Arrival order.** The robots advance in lock-step: at step ``t`` robot 0, then 1, ... queries
with its ``t``-th frame. Each query is answered by its owner's :class:`~swarmrec.vpr.index.OwnerIndex`
(search, then store), so a query sees exactly the frames that arrived at its owner before it,
minus the querier's own frames. The centralized reference runs the same order through one index.

**Scoring (the PR/AUC protocol).** A query ``i`` *could* match frame ``j`` when ``j`` arrived
before ``i`` and belongs to another robot (:func:`eligible`); it has a true match when one of
those shows the same place (:mod:`swarmrec.vpr.places`: cameras <= 0.5 m and views <= 30 deg
apart; no frame window, since frames of different robots are never the same moment, except at
the cut between two sub-trajectories, which the paper keeps too). Each query's answer (its
owner's nearest entry) is its single best match; queries are walked from the smallest
distance up, a query whose answer is a true match is a true positive, any other answer a false
positive, and recall is over the queries with a true match among their eligible frames
(centralized and decentralized share this denominator, so a match cut off by a cluster
boundary is a miss). AUC is the trapezoid area under precision(recall), computed by
:func:`swarmrec.evaluation.pr.precision_recall` (see :func:`answers_curve`).

**Load.** ``load[r]`` counts the queries routed to robot ``r`` (its own included: it searches
them all). The *worst balance ratio* is ``max_r load[r] / (Q / n)``, Q the number of queries:
1 when perfectly even, ``n`` when one robot gets every query.

**Bytes** (the brief's model, not measured on a wire): a query whose owner is another robot
sends the descriptor (``4 d`` B as float32, or the quantised code) plus 5 B (querier 1 B,
frame 4 B) and gets 13 B back (squared distance 4 B, robot 1 B, frame 8 B); a query owned by
its own robot costs 0 B. Each copy stored at another robot than the querier costs the same
upload again, without an answer.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from swarmrec.errors import ConfigError
from swarmrec.evaluation.pr import PRCurve, precision_recall
from swarmrec.vpr.index import OwnerIndex
from swarmrec.vpr.places import MAX_SQUARED_DISTANCE
from swarmrec.vpr.vectors import as_descriptors

__all__ = [
    "ANSWER_BYTES",
    "QUERY_HEADER_BYTES",
    "Answers",
    "Reassignment",
    "answers_curve",
    "arrival_order",
    "bytes_per_query",
    "eligible",
    "robot_of_frames",
    "run_queries",
    "worst_balance_ratio",
]

Float32Array = npt.NDArray[np.float32]
FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

#: The byte model: querier id (1 B) and frame id (4 B) beside the descriptor; the answer.
QUERY_HEADER_BYTES = 5
ANSWER_BYTES = 13


def robot_of_frames(n_frames: int, n_robots: int) -> IntArray:
    """The robot owning each frame: consecutive runs of ``ceil(n_frames / n_robots)``."""
    if n_robots < 1 or n_frames < n_robots:
        raise ConfigError(f"need 1 <= n_robots <= n_frames, got {n_robots} robots for {n_frames} frames")
    per_robot = math.ceil(n_frames / n_robots)
    robots: IntArray = np.arange(n_frames, dtype=np.int64) // per_robot
    return robots


def arrival_order(robots: IntArray) -> IntArray:
    """Frame indices in lock-step order: step 0 of robots 0..n-1, then step 1, ..."""
    n_frames = len(robots)
    first = np.searchsorted(robots, np.arange(int(robots.max()) + 1))
    step = np.arange(n_frames) - first[robots]
    order: IntArray = np.lexsort((robots, step)).astype(np.int64)
    return order


def eligible(robots: IntArray, order: IntArray) -> BoolArray:
    """``(N, N)``: frame ``j`` arrived before frame ``i`` and belongs to another robot."""
    arrival = np.empty(len(order), np.int64)
    arrival[order] = np.arange(len(order))
    result: BoolArray = (arrival[None, :] < arrival[:, None]) & (robots[None, :] != robots[:, None])
    return result


@dataclass(frozen=True, eq=False)
class Answers:
    """Per frame (in frame order): the owner its query went to, the answer's frame (-1: none)
    and squared distance (inf: none); how many stored descriptors were moved or copied when
    owners changed; where else each frame was stored."""

    owners: IntArray
    matches: IntArray
    distances: FloatArray
    migrated: int = 0
    #: (N, m): per frame, the robots it was also stored at (-1: none).
    replicas: IntArray | None = None

    @property
    def n_queries(self) -> int:
        return len(self.owners)


@dataclass(frozen=True, eq=False)
class Reassignment:
    """From position ``at`` of the arrival order on, frame ``i`` goes to ``owners[i]`` (and is also
    stored at each robot of ``replicas[i]`` that is >= 0: one per frame, or a row of several);
    what was stored before moves to where each stored frame now belongs."""

    at: int
    owners: IntArray
    replicas: IntArray | None = None


def run_queries(
    descriptors: npt.NDArray[np.floating],
    robots: IntArray,
    owners: IntArray,
    order: IntArray,
    reassignments: Sequence[Reassignment] = (),
    replicas: IntArray | None = None,
) -> Answers:
    """Send every frame's query to ``owners[frame]`` in ``order``: one :class:`OwnerIndex` per
    owner, each query searched then stored (frames are stored under their own index), and stored
    without a search at ``replicas[frame]`` too when given (``(N,)`` or ``(N, m)``; -1: none;
    copies near a cell boundary, :mod:`swarmrec.vpr.balance`). At each reassignment's place in the
    order the owners change and stored entries move. ``Answers.migrated`` counts descriptors
    moved or copied."""
    x = as_descriptors(descriptors, descriptors.shape[1] if descriptors.ndim == 2 else -1)
    n = len(x)
    if not (len(robots) == len(owners) == n and sorted(order.tolist()) == list(range(n))):
        raise ConfigError("robots, owners and order must cover the same frames")
    switches = {r.at: r for r in reassignments}
    if len(switches) != len(reassignments) or any(
        len(r.owners) != n or not 0 <= r.at <= n for r in reassignments
    ):
        raise ConfigError(
            "each reassignment must give an owner to every frame and switch at its own place in the order"
        )
    current = owners.astype(np.int64)
    copies = _copy_table(replicas, n)
    width = max([copies.shape[1]] + [_copy_table(r.replicas, n).shape[1] for r in reassignments])
    indexes: dict[int, OwnerIndex] = {}
    used = np.empty(n, np.int64)
    matches = np.full(n, -1, np.int64)
    distances = np.full(n, np.inf)
    migrated = 0
    stored_at = np.full((n, width), -1, np.int64)
    for position, i in enumerate(order.tolist()):
        if position in switches:
            switch = switches[position]
            current = switch.owners.astype(np.int64)
            copies = _copy_table(switch.replicas, n)
            migrated += _migrate(indexes, current, copies, x.shape[1])
        owner = int(current[i])
        used[i] = owner
        match = indexes.setdefault(owner, OwnerIndex(x.shape[1])).query_then_store(x[i], int(robots[i]), i)
        if match is not None:
            matches[i], distances[i] = match.frame, match.distance
        for column, robot in enumerate(_others(copies[i], owner)):
            indexes.setdefault(robot, OwnerIndex(x.shape[1])).store(x[i], int(robots[i]), i)
            stored_at[i, column] = robot
    return Answers(used, matches, distances, migrated, stored_at)


def _copy_table(replicas: IntArray | None, n: int) -> IntArray:
    """Copies as an ``(n, m)`` table of robots (-1: none); one copy a frame is a column."""
    if replicas is None:
        return np.full((n, 1), -1, np.int64)
    table = np.asarray(replicas, np.int64)
    table = table[:, None] if table.ndim == 1 else table
    if table.ndim != 2 or len(table) != n:
        raise ConfigError(f"replicas must be ({n},) or ({n}, m), got {np.shape(replicas)}")
    return table


def _others(row: IntArray, owner: int) -> list[int]:
    """The distinct robots of a copy row other than the owner, in row order."""
    return list(dict.fromkeys(int(r) for r in row if r >= 0 and r != owner))


def _migrate(indexes: dict[int, OwnerIndex], owners: IntArray, replicas: IntArray, dimension: int) -> int:
    """Put every stored entry where its frame now belongs (its owner, and its replica if any), as
    owners would: export, store at the new places, remove the rest. Returns the copies made."""
    copied = 0
    for holder, index in list(indexes.items()):
        robots, frames, vectors = index.export()
        leaving = []
        for j, frame in enumerate(frames.tolist()):
            targets = {int(owners[frame])} | {int(r) for r in replicas[frame] if r >= 0}
            if holder not in targets:
                leaving.append(j)
            for target in targets - {holder}:
                destination = indexes.setdefault(target, OwnerIndex(dimension))
                copied += destination.store(vectors[j], int(robots[j]), frame)
        index.remove(robots[leaving], frames[leaving])
    return copied


def answers_curve(answers: Answers, closures: BoolArray, eligible_pairs: BoolArray) -> PRCurve:
    """The PR curve of the module docstring, through :func:`precision_recall`.

    That function takes a dense score matrix, picks each row's best column and reads a
    score < 0 as "not a possible closure". So: eligible pairs score 0 (possible, so a true
    one counts in recall), the answer scores ``1 + (4 - d^2) / 4`` in [1, 2] (the best of
    its row, ordered by distance), ineligible pairs -1, and an extra last column scores 0.5
    and is never a closure: a query without an answer picks it and becomes a false positive
    at the end of the walk, which adds no area (recall no longer grows there)."""
    n = answers.n_queries
    if closures.shape != (n, n) or eligible_pairs.shape != (n, n):
        raise ConfigError(f"closures and eligible pairs must be ({n}, {n})")
    scores = np.full((n, n + 1), -1.0)
    scores[:, :n][eligible_pairs] = 0.0
    scores[:, n] = 0.5
    answered = np.flatnonzero(answers.matches >= 0)
    scores[answered, answers.matches[answered]] = (
        1.0
        + (MAX_SQUARED_DISTANCE - np.minimum(answers.distances[answered], MAX_SQUARED_DISTANCE))
        / MAX_SQUARED_DISTANCE
    )
    truth = np.zeros((n, n + 1), np.bool_)
    truth[:, :n] = closures & eligible_pairs
    return precision_recall(scores, truth)


def worst_balance_ratio(owners: IntArray, n_robots: int) -> float:
    """The busiest robot's queries over a perfectly even share, ``max load / (Q / n)``."""
    load = np.bincount(owners, minlength=n_robots)
    if len(load) != n_robots or len(owners) == 0:
        raise ConfigError(f"owners must be robots in [0, {n_robots}) and at least one query")
    return float(load.max() * n_robots / len(owners))


def bytes_per_query(answers: Answers, robots: IntArray, code_bytes: int) -> dict[str, float]:
    """Mean bytes a query sends and receives under the byte model (``code_bytes``: the
    descriptor on the wire, 4 d for float32), copies included (``replica_share``: copies sent
    to another robot per query)."""
    remote = answers.owners != robots
    share = float(remote.mean()) if len(remote) else 0.0
    copies = 0.0
    if answers.replicas is not None and len(remote):
        table = _copy_table(answers.replicas, len(remote))
        copies = float(((table >= 0) & (table != robots[:, None])).sum() / len(remote))
    up = (share + copies) * (code_bytes + QUERY_HEADER_BYTES)
    down = share * ANSWER_BYTES
    return {"remote_share": share, "replica_share": copies, "up": up, "down": down, "total": up + down}
