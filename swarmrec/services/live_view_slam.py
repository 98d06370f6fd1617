"""What the live view shows of a SLAM team (:mod:`swarmrec.services.live_view`).

Each robot's slam service answers its state (``status``), its estimate of its own
vertices (``estimate``: poses and the objects it maps, gtsam Symbol keys) and the
separator estimates it sent (``sent``: per neighbour, the keys the two share). The
page draws every robot's trajectory from its estimate, its objects, and where the
robots' maps join: the separators, each at its vertex on the sender's trajectory,
labelled with the neighbour it joins. These are the inter-robot loop closures of
object-based SLAM (papers/multi-robot-object-based-slam.txt), placed where the poses
are known: in the team's own estimate.

Everything here reads answers a robot wrote and is bounded: a malformed estimate
(values that are not 12 a key, or not finite) draws nothing, and each robot gives at
most :data:`MAX_POSES` poses, :data:`MAX_OBJECTS` objects and :data:`MAX_SEPARATORS`
separators to the page.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

from swarmrec.wire import messages as pb

__all__ = ["MAX_OBJECTS", "MAX_POSES", "MAX_SEPARATORS", "separator_keys", "slam_robot_view", "trajectory"]

#: Poses of one robot drawn (a longer trajectory is thinned evenly, its last pose kept).
MAX_POSES = 400
#: Objects and separators of one robot drawn.
MAX_OBJECTS = 300
MAX_SEPARATORS = 200
#: Doubles per vertex in an estimate: the rotation row by row, then the translation.
_PER_KEY = 12
#: gtsam's Symbol layout (swarmrec.slam.keys): the character above the low 56 bits. Read here
#: without importing swarmrec.slam, whose solvers (scipy, gtsam) the gateway has no use for.
_INDEX_BITS = 56


def _xy(values: Sequence[float], i: int) -> tuple[float, float] | None:
    x, y = values[_PER_KEY * i + 9], values[_PER_KEY * i + 10]
    if not (math.isfinite(x) and math.isfinite(y)):
        return None
    return round(x, 4), round(y, 4)


def trajectory(
    estimate: pb.SlamEstimate,
) -> tuple[list[list[float]], list[list[float]], dict[int, list[float]]]:
    """``(poses, objects, where)`` of one robot's estimate: its poses in index order (thinned
    to at most MAX_POSES, the last one kept) and its objects as ``[x, y]``, and the plane
    position of every vertex by key. Nothing when the estimate is malformed."""
    keys, values = list(estimate.keys), list(estimate.values)
    if len(values) != _PER_KEY * len(keys):
        return [], [], {}
    poses: list[tuple[int, list[float]]] = []
    objects: list[list[float]] = []
    where: dict[int, list[float]] = {}
    for i, key in enumerate(keys):
        xy = _xy(values, i)
        if xy is None:
            return [], [], {}
        point = [xy[0], xy[1]]
        where[key] = point
        c = chr(key >> _INDEX_BITS)
        if "a" <= c <= "z":
            poses.append((key & ((1 << _INDEX_BITS) - 1), point))
        elif "A" <= c <= "Z" and len(objects) < MAX_OBJECTS:
            objects.append(point)
    poses.sort(key=lambda p: p[0])
    path = [p for _, p in poses]
    if len(path) > MAX_POSES:
        stride = math.ceil(len(path) / MAX_POSES)
        path = path[::stride] + ([path[-1]] if (len(path) - 1) % stride else [])
    return path, objects, where


def separator_keys(steps: Sequence[pb.SlamStep]) -> dict[int, list[int]]:
    """The keys a robot shares with each neighbour, from the steps it sent (each step to a
    neighbour lists the sender's separator keys with it; the first one per neighbour is enough)."""
    out: dict[int, list[int]] = {}
    for step in steps:
        if step.keys and step.receiver_robot_id not in out:
            out[step.receiver_robot_id] = list(step.keys)
    return out


def slam_robot_view(
    status: pb.SlamStatus | None,
    estimate: pb.SlamEstimate | None,
    shared: Mapping[int, Sequence[int]],
    robot: int,
    error: str = "",
) -> dict[str, Any]:
    """One robot's row and drawing for the page."""
    if status is None:
        return {"robot": robot, "state": "not answering", "error": error, "poses": [], "objects": [],
                "separators": []}  # fmt: skip
    poses, objects, where = trajectory(estimate) if estimate is not None else ([], [], {})
    separators = [
        {"with": neighbour, "at": where[key]}
        for neighbour in sorted(shared)
        for key in shared[neighbour]
        if key in where
    ][:MAX_SEPARATORS]
    return {
        "robot": robot,
        "solve": status.solve_id,
        "state": pb.SlamState.Name(status.state).removeprefix("SLAM_STATE_").lower(),
        "stage": "rotation" if status.linearisation == 0 else f"pose {status.linearisation}",
        "iteration": status.iteration,
        "converged": status.converged,
        "reason": status.reason,
        "error": error,
        "poses": poses,
        "objects": objects,
        "separators": separators,
    }
