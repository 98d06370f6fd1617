"""Algorithm 1 of the WNBC paper (Sec. 3.3): multi-hop flooding of classifier outputs, as a
pure state machine with no network.

Each robot ``A_i`` broadcasts its own message ``S_i^i = [p(z_i|O^i), r = 0, phi_i, i]``
once per round. On receiving ``S_h^j`` from a neighbour ``A_j``, it keeps the message
only if it has not heard ``A_h`` yet this round: it records ``A_h``'s vector at
communication distance ``r + 1``, and rebroadcasts it with ``r + 1``. Anything else is
ignored. With synchronous steps the first copy to arrive has travelled a shortest path,
so the recorded distance is the hop distance on the communication graph.

The ``r`` carried by a message is the sender's distance to the origin (the origin sends
0, Algorithm 1 line 2); the receiver's distance is one more (line 8). A node may be
given the hop limit ``r_max`` of Sec. 3.4: it then never forwards a message that would
arrive further than ``r_max`` hops from its origin.

A node never raises on what it receives: a malformed message (wrong vector length,
NaN, negative or not summing to 1, absurd hop count, unknown origin or round) is
rejected and counted by :class:`Rejection` reason, because one faulty robot must not
stop the others' recognition.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from enum import StrEnum

import numpy as np
import numpy.typing as npt

from swarmrec.errors import ConfigError
from swarmrec.fusion.wnbc import N_LANDMARKS

__all__ = [
    "SUM_TOLERANCE",
    "FloodMessage",
    "FloodResult",
    "FloodingNode",
    "Heard",
    "Outcome",
    "Reception",
    "Rejection",
    "simulate_flooding",
]

FloatArray = npt.NDArray[np.float64]

#: How far from 1 a received probability vector may sum: float32 softmax outputs of 19
#: classes are within 1e-6, quantised wire formats within a few 1e-4.
SUM_TOLERANCE = 1e-3


@dataclass(frozen=True, eq=False)
class FloodMessage:
    """``S_origin^sender`` of Eq. 3 plus the round it belongs to.

    ``hops`` is ``r``: the sender's communication distance to ``origin`` (0 when the
    origin sends its own measurement). ``likelihood`` is ``p(z_origin | O^origin)``,
    ``yaw`` the origin's yaw ``phi_origin`` (rad). Fields are not validated here: a
    message comes from elsewhere and is checked by the receiving :class:`FloodingNode`.
    """

    round_id: int
    origin: int
    sender: int
    hops: int
    yaw: float
    likelihood: npt.ArrayLike


@dataclass(frozen=True, eq=False)
class Heard:
    """A measurement recorded by a node: ``origin``'s vector, at communication distance
    ``hops`` (``r_origin^i``), first delivered by neighbour ``sender``."""

    origin: int
    sender: int
    hops: int
    yaw: float
    likelihood: FloatArray


class Outcome(StrEnum):
    """What a node did with a received message."""

    ACCEPTED = "accepted"
    DUPLICATE = "duplicate"
    REJECTED = "rejected"


class Rejection(StrEnum):
    """Why a node rejected a malformed message."""

    NOT_NUMERIC = "not a vector of numbers"
    WRONG_LENGTH = "wrong length"
    NOT_FINITE = "not finite"
    NEGATIVE = "negative probability"
    NOT_NORMALISED = "does not sum to 1"
    BAD_HOPS = "absurd hop count"
    BAD_ORIGIN = "unknown origin"
    BAD_SENDER = "unknown sender"
    BAD_YAW = "yaw not finite"
    UNKNOWN_ROUND = "unknown round"
    BEYOND_R_MAX = "beyond r_max"


@dataclass(frozen=True)
class Reception:
    """The result of :meth:`FloodingNode.receive`: the outcome, the reason when rejected,
    what was recorded when accepted, and the message to broadcast (``None`` when nothing
    is to be forwarded)."""

    outcome: Outcome
    reason: Rejection | None = None
    heard: Heard | None = None
    forward: FloodMessage | None = None


class FloodingNode:
    """Robot ``robot_id``'s side of Algorithm 1 in a swarm of ``n_robots``.

    Call :meth:`start_round` with the robot's own classifier output and broadcast the
    message it returns, then hand every received message to :meth:`receive` and
    broadcast the ``forward`` of its result when there is one. :attr:`heard` lists the
    other robots' measurements in the order they were recorded, ready for a
    :class:`~swarmrec.fusion.wnbc.FusionState`.
    """

    def __init__(
        self, robot_id: int, n_robots: int, *, n_classes: int = N_LANDMARKS, r_max: int | None = None
    ) -> None:
        if n_robots < 1:
            raise ConfigError(f"n_robots must be >= 1, got {n_robots}")
        if not 0 <= robot_id < n_robots:
            raise ConfigError(f"robot_id must be in [0, {n_robots}), got {robot_id}")
        if n_classes < 2:
            raise ConfigError(f"n_classes must be >= 2, got {n_classes}")
        if r_max is not None and r_max < 1:
            raise ConfigError(f"r_max must be >= 1 or None, got {r_max}")
        self.robot_id = robot_id
        self.n_robots = n_robots
        self.n_classes = n_classes
        self.r_max = r_max
        self.round_id: int | None = None
        self._ids: set[int] = set()
        self._heard: list[Heard] = []
        #: Copies of already-recorded origins received this round (Algorithm 1 line 11).
        self.duplicates = 0
        #: Malformed messages received this round, by reason.
        self.rejected: Counter[Rejection] = Counter()

    def start_round(self, round_id: int, likelihood: npt.ArrayLike, yaw: float) -> FloodMessage:
        """Begin round ``round_id`` with this robot's own measurement (Algorithm 1 lines
        1-2): forget the previous round and return ``S_i^i`` to broadcast."""
        self.round_id = round_id
        self._ids = {self.robot_id}
        self._heard = []
        self.duplicates = 0
        self.rejected = Counter()
        own = np.array(likelihood, dtype=np.float64).reshape(-1)
        return FloodMessage(round_id, self.robot_id, self.robot_id, 0, float(yaw), own)

    @property
    def heard(self) -> Sequence[Heard]:
        """Other robots' measurements recorded this round, in arrival order."""
        return tuple(self._heard)

    @property
    def heard_all(self) -> bool:
        """Whether every robot's measurement has arrived (Algorithm 1's loop condition)."""
        return len(self._ids) == self.n_robots

    def receive(self, message: FloodMessage) -> Reception:
        """Algorithm 1 lines 4-11 for one received message; never raises.

        The header is checked first and a copy of an origin already heard is ignored
        before its vector is read: most deliveries of a flood are such copies.
        """
        reason = self._check_header(message)
        if reason is not None:
            return self._reject(reason)
        if message.origin in self._ids:
            self.duplicates += 1
            return Reception(Outcome.DUPLICATE)
        hops = int(message.hops) + 1
        if self.r_max is not None and hops > self.r_max:
            return self._reject(Rejection.BEYOND_R_MAX)
        reason, likelihood = self._check_likelihood(message.likelihood)
        if likelihood is None:
            return self._reject(reason or Rejection.NOT_NUMERIC)
        self._ids.add(message.origin)
        heard = Heard(int(message.origin), int(message.sender), hops, float(message.yaw), likelihood)
        self._heard.append(heard)
        forward = None
        if self.r_max is None or hops < self.r_max:
            forward = FloodMessage(
                message.round_id, heard.origin, self.robot_id, hops, heard.yaw, likelihood.copy()
            )
        return Reception(Outcome.ACCEPTED, heard=heard, forward=forward)

    def _reject(self, reason: Rejection) -> Reception:
        self.rejected[reason] += 1
        return Reception(Outcome.REJECTED, reason=reason)

    def _check_header(self, message: FloodMessage) -> Rejection | None:
        if self.round_id is None or message.round_id != self.round_id:
            return Rejection.UNKNOWN_ROUND
        if not _is_index(message.origin, self.n_robots):
            return Rejection.BAD_ORIGIN
        if not _is_index(message.sender, self.n_robots):
            return Rejection.BAD_SENDER
        # A node forwards each origin at most once, so a message's path is simple and its
        # sender at most n - 1 hops from the origin.
        if not _is_index(message.hops, self.n_robots):
            return Rejection.BAD_HOPS
        if not _is_finite_number(message.yaw):
            return Rejection.BAD_YAW
        return None

    def _check_likelihood(self, values: npt.ArrayLike) -> tuple[Rejection | None, FloatArray | None]:
        try:
            v = np.array(values, dtype=np.float64)
        except (TypeError, ValueError, OverflowError):
            return Rejection.NOT_NUMERIC, None
        if v.ndim != 1:  # None, a bare number or a matrix
            return Rejection.NOT_NUMERIC, None
        if v.shape[0] != self.n_classes:
            return Rejection.WRONG_LENGTH, None
        if not np.isfinite(v).all():
            return Rejection.NOT_FINITE, None
        if (v < 0).any():
            return Rejection.NEGATIVE, None
        if abs(float(v.sum()) - 1.0) > SUM_TOLERANCE:
            return Rejection.NOT_NORMALISED, None
        return None, v


def _is_finite_number(value: object) -> bool:
    try:
        return math.isfinite(float(value))  # type: ignore[arg-type]  # anything float() takes
    except (TypeError, ValueError, OverflowError):
        return False


def _is_index(value: object, n: int) -> bool:
    """``value`` is an integer (not a bool) in ``[0, n)``."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool) and bool(0 <= value < n)


@dataclass(frozen=True)
class FloodResult:
    """What :func:`simulate_flooding` observed.

    ``heard[i]`` is robot ``i``'s recorded measurements in order; ``deliveries`` every
    ``(step, sender, receiver, origin)`` transmission; ``duplicates[i]`` the copies robot
    ``i`` ignored; ``steps`` the number of synchronous steps until no message was left.
    """

    heard: tuple[tuple[Heard, ...], ...]
    deliveries: tuple[tuple[int, int, int, int], ...]
    duplicates: tuple[int, ...]
    steps: int

    def order(self, robot: int) -> list[tuple[int, int]]:
        """``(origin, hops)`` of robot ``robot``'s recorded measurements, in incorporation order."""
        return [(h.origin, h.hops) for h in self.heard[robot]]


def simulate_flooding(
    adjacency: npt.ArrayLike,
    likelihoods: npt.ArrayLike,
    yaws: npt.ArrayLike,
    *,
    round_id: int = 0,
    r_max: int | None = None,
) -> FloodResult:
    """Run Algorithm 1 on every robot of an undirected communication graph, in synchronous
    steps, deterministically.

    At step 0 every robot broadcasts its own message; at each step every message
    broadcast at the previous step reaches all the sender's neighbours, delivered in
    (sender id, broadcast order) order, and the forwards they cause are broadcast at the
    next step. ``adjacency`` is an n x n symmetric boolean matrix without self-loops;
    ``likelihoods`` an n x m array of classifier outputs; ``yaws`` n yaws.
    """
    adj = np.asarray(adjacency, dtype=bool)
    n = adj.shape[0]
    if adj.shape != (n, n) or not np.array_equal(adj, adj.T) or np.any(np.diag(adj)):
        raise ConfigError("adjacency must be a square symmetric boolean matrix without self-loops")
    lik = np.asarray(likelihoods, dtype=np.float64)
    yaw = np.asarray(yaws, dtype=np.float64).reshape(-1)
    if lik.ndim != 2 or lik.shape[0] != n or yaw.shape[0] != n:
        raise ConfigError(f"need {n} likelihood rows and {n} yaws, got {lik.shape} and {yaw.shape}")
    nodes = [FloodingNode(i, n, n_classes=lik.shape[1], r_max=r_max) for i in range(n)]
    outbox: list[list[FloodMessage]] = [
        [node.start_round(round_id, lik[i], float(yaw[i]))] for i, node in enumerate(nodes)
    ]
    neighbours = [np.flatnonzero(adj[i]).tolist() for i in range(n)]
    deliveries: list[tuple[int, int, int, int]] = []
    steps = 0
    while any(outbox):
        steps += 1
        next_outbox: list[list[FloodMessage]] = [[] for _ in range(n)]
        for sender in range(n):
            for message in outbox[sender]:
                for receiver in neighbours[sender]:
                    deliveries.append((steps, sender, receiver, message.origin))
                    result = nodes[receiver].receive(message)
                    if result.forward is not None:
                        next_outbox[receiver].append(result.forward)
        outbox = next_outbox
    return FloodResult(
        heard=tuple(tuple(node.heard) for node in nodes),
        deliveries=tuple(deliveries),
        duplicates=tuple(node.duplicates for node in nodes),
        steps=steps,
    )
