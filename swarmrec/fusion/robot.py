"""One robot's cooperative recognition, without a bus: Algorithm 1 flooding plus
weighted naive Bayes fusion, round after round.

:class:`FusionRobot` wraps a :class:`~swarmrec.fusion.flooding.FloodingNode`
(Algorithm 1) and one :class:`~swarmrec.fusion.wnbc.FusionState` per round, and adds
what a robot on a shared bus needs:

* the neighbour check: over a radio a robot hears only robots in range; on a router
  anyone can put, so a message whose sender is not a current neighbour is rejected;
* early messages: robots start a round at slightly different times, and dropping
  what a faster neighbour already sent would make the result depend on timing, so
  messages of a round not started yet are kept (at most ``early_per_round`` per
  round, for at most :data:`MAX_EARLY_ROUNDS` rounds) and processed, in arrival
  order, right after the robot's own message goes out when the round starts;
* round order: a new round must come after the current one, so a message of an
  earlier round is late and rejected (``stale_round``). Round ids are uint32 on
  the wire and count modulo 2^32, like TCP sequence numbers (RFC 1982): a new
  round is 1 to ``max_round_jump`` ahead of the current one, after 2^32 - 1
  comes 0. So no round id can lock the robot (with plain order, round
  2^32 - 1 left no higher id until a restart), and one request cannot move it
  further than ``max_round_jump`` ahead; a message more than that far ahead
  is refused (``too_far_ahead``) rather than kept;
* the records of the last :data:`KEPT_ROUNDS` rounds, for the ``posterior`` endpoint.

A radio broadcast reaches exactly the robots in range, including the one a message
came from, so forwards go to *every* neighbour (:class:`Broadcast`), as Algorithm 1
and :func:`~swarmrec.fusion.flooding.simulate_flooding` do. The fusion service
(:mod:`swarmrec.services.fusion`) puts each broadcast on the neighbours' inboxes.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np
import numpy.typing as npt

from swarmrec.errors import SwarmrecError
from swarmrec.fusion.flooding import SUM_TOLERANCE, FloodingNode, FloodMessage, Outcome
from swarmrec.fusion.wnbc import FusionState, LikelihoodError, WeightLaw, normalise_likelihood

__all__ = [
    "DEFAULT_MAX_ROUND_JUMP",
    "KEPT_ROUNDS",
    "MAX_EARLY_ROUNDS",
    "ROUND_MODULUS",
    "Broadcast",
    "EarlyBuffer",
    "FusionRobot",
    "Handled",
    "Handling",
    "Reason",
    "RoundError",
    "RoundRecord",
    "RoundStart",
    "Step",
    "rounds_ahead",
]

FloatArray = npt.NDArray[np.float64]

#: Future rounds whose early messages are kept; a robot is at most a round or two
#: behind its neighbours, and absurd round ids must not take unbounded memory.
MAX_EARLY_ROUNDS = 4
#: Finished rounds whose posterior the ``posterior`` endpoint can still report.
KEPT_ROUNDS = 8
#: Round ids are uint32 on the wire and count modulo this.
ROUND_MODULUS = 2**32
#: How far ahead of the current round a new one may be, unless configured.
DEFAULT_MAX_ROUND_JUMP = 1024


def rounds_ahead(round_id: int, current: int) -> int:
    """How many rounds ``round_id`` is after ``current``, modulo 2^32 (0: the same round;
    an earlier round reads as nearly 2^32 ahead)."""
    return (round_id - current) % ROUND_MODULUS


class Reason(StrEnum):
    """Why a robot rejected a flooded message that decoded: the ``reason`` label of
    ``swarmrec_fusion_rejected_total``. The core's own rejections
    (:class:`~swarmrec.fusion.flooding.Rejection`) appear under their lower-case
    names (``wrong_length``, ``not_finite``, ``bad_hops``, ...). Bytes that do not
    decode never get here: the service runner refuses and counts them."""

    SENDER_MISMATCH = "sender_mismatch"
    #: No origin signature where one is required (mutual TLS), or one that is not the origin's.
    UNSIGNED = "unsigned"
    BAD_SIGNATURE = "bad_signature"
    NOT_NEIGHBOUR = "not_neighbour"
    STALE_ROUND = "stale_round"
    TOO_FAR_AHEAD = "too_far_ahead"
    BUFFER_FULL = "buffer_full"
    BAD_HOPS = "bad_hops"
    IGNORED = "ignored"


class RoundError(SwarmrecError, ValueError):
    """A ``start_round`` request that cannot start a round (answered INVALID_ARGUMENT)."""


class Handling(StrEnum):
    """What the service did with one flooded message."""

    ACCEPTED = "accepted"
    DUPLICATE = "duplicate"
    REJECTED = "rejected"
    BUFFERED = "buffered"


@dataclass(frozen=True, eq=False)
class Step:
    """One message folded into the posterior, and what it left (``incorporated``:
    messages folded in this round, this one included)."""

    origin: int
    sender: int
    hops: int
    yaw: float
    weight: float
    decision_after: int
    posterior: FloatArray
    incorporated: int


@dataclass(frozen=True)
class Broadcast:
    """One message to put on the inbox of each of ``targets`` (a radio broadcast)."""

    message: FloodMessage
    targets: tuple[int, ...]


@dataclass(frozen=True)
class Handled:
    """The result of :meth:`FusionRobot.receive`.

    ``message`` is the message handled (for the log); ``reason`` is set when
    rejected; ``step`` and ``broadcast`` (None when the hop limit stops the forward)
    when accepted; ``evicted`` counts early messages of another round dropped to keep
    this one (they count as ``buffer_full``).
    """

    outcome: Handling
    message: FloodMessage
    reason: str = ""
    step: Step | None = None
    broadcast: Broadcast | None = None
    evicted: int = 0


@dataclass(frozen=True)
class RoundStart:
    """The result of :meth:`FusionRobot.start_round`: the robot's own message to send
    first, then what became of the round's early messages, and how many early messages
    of lower rounds (never started here) were dropped as stale."""

    broadcast: Broadcast
    early: tuple[Handled, ...]
    stale: int


@dataclass
class RoundRecord:
    """One round's fusion as the ``posterior`` endpoint reports it."""

    round_id: int
    neighbours: frozenset[int]
    state: FusionState
    steps: list[Step] = field(default_factory=list)
    duplicates: int = 0
    rejected: int = 0


class EarlyBuffer:
    """Messages of rounds not started yet: at most ``per_round`` per round, for at most
    ``max_rounds`` rounds.

    When a message of a new round finds every slot taken, the furthest buffered round
    makes way if the new one is nearer (the nearer round starts sooner, and a bogus far
    round id must not lock the buffer); otherwise the new message is refused. Rounds
    are ordered by how far they are ahead of ``origin``, the robot's current round
    (modulo 2^32), or by their id before the robot's first round.
    """

    def __init__(
        self, per_round: int, max_rounds: int = MAX_EARLY_ROUNDS, max_ahead: int = DEFAULT_MAX_ROUND_JUMP
    ) -> None:
        if per_round < 0 or max_rounds < 1 or not 1 <= max_ahead < ROUND_MODULUS // 2:
            raise ValueError(
                f"need per_round >= 0, max_rounds >= 1 and 1 <= max_ahead < 2^31, "
                f"got {per_round}, {max_rounds}, {max_ahead}"
            )
        self.per_round = per_round
        self.max_rounds = max_rounds
        self.max_ahead = max_ahead
        self._rounds: dict[int, list[FloodMessage]] = {}

    def add(self, message: FloodMessage, origin: int | None = None) -> tuple[bool, int]:
        """Keep ``message`` (``origin``: the robot's current round, None before the first);
        returns (kept, messages of another round evicted for it)."""
        kept = self._rounds.get(message.round_id)
        if kept is not None:
            if len(kept) >= self.per_round:
                return False, 0
            kept.append(message)
            return True, 0
        if self.per_round == 0:
            return False, 0
        evicted = 0
        if len(self._rounds) >= self.max_rounds:

            def distance(r: int) -> int:
                return r if origin is None else rounds_ahead(r, origin)

            furthest = max(self._rounds, key=distance)
            if distance(message.round_id) > distance(furthest):
                return False, 0
            evicted = len(self._rounds.pop(furthest))
        self._rounds[message.round_id] = [message]
        return True, evicted

    def take(self, round_id: int) -> tuple[list[FloodMessage], int]:
        """Round ``round_id``'s messages in arrival order, and the number of messages
        dropped of rounds that are not 1 to ``max_ahead`` rounds after it (earlier rounds
        were skipped here and will never start; far ones cannot start from here)."""
        messages = self._rounds.pop(round_id, [])
        stale = [r for r in self._rounds if not 1 <= rounds_ahead(r, round_id) <= self.max_ahead]
        dropped = sum(len(self._rounds.pop(r)) for r in stale)
        return messages, dropped

    def __len__(self) -> int:
        return sum(len(m) for m in self._rounds.values())

    def rounds(self) -> list[int]:
        """The rounds with messages waiting, lowest first."""
        return sorted(self._rounds)


class FusionRobot:
    """One robot's rounds of flooding and fusion, without a bus.

    Wraps a :class:`FloodingNode` (Algorithm 1) and one :class:`FusionState` per round,
    and adds what the bus needs: the neighbour check, early-message buffering and
    the records of the last :data:`KEPT_ROUNDS` rounds. Not thread-safe; the service
    calls it under one lock.
    """

    def __init__(
        self,
        robot: int,
        n_robots: int,
        *,
        law: WeightLaw,
        n_classes: int,
        r_max: int | None = None,
        early_per_round: int = 1024,
        max_round_jump: int = DEFAULT_MAX_ROUND_JUMP,
    ) -> None:
        if not 1 <= max_round_jump < ROUND_MODULUS // 2:
            raise ValueError(f"max_round_jump must be in [1, 2^31), got {max_round_jump}")
        self.max_round_jump = max_round_jump
        self.robot = robot
        self.n_robots = n_robots
        self.n_classes = n_classes
        self.law = law
        self.r_max = r_max
        self.node = FloodingNode(robot, n_robots, n_classes=n_classes, r_max=r_max)
        self.buffer = EarlyBuffer(early_per_round, max_ahead=max_round_jump)
        self.current: RoundRecord | None = None
        self._rounds: OrderedDict[int, RoundRecord] = OrderedDict()

    def start_round(
        self,
        round_id: int,
        probabilities: npt.ArrayLike,
        yaw: float,
        neighbours: Sequence[int],
        law: WeightLaw | None = None,
    ) -> RoundStart:
        """Begin ``round_id`` (Algorithm 1 lines 1-2); raises RoundError for a bad request.

        ``law`` weighs this round's messages instead of the robot's own law (the
        flooding does not depend on it, so one swarm can compare laws on the same views).

        The own output must already be a probability vector (as neighbours will check
        it, :data:`~swarmrec.fusion.flooding.SUM_TOLERANCE`): a robot whose every
        message its neighbours reject would silently drop out of the swarm's fusion.
        """
        if not 0 <= round_id < ROUND_MODULUS:
            raise RoundError(f"round ids are 32-bit unsigned integers, got {round_id}")
        if self.current is not None:
            current = self.current.round_id
            if not 1 <= rounds_ahead(round_id, current) <= self.max_round_jump:
                raise RoundError(
                    f"round ids must advance: round {current} runs now, so a new round is "
                    f"{(current + 1) % ROUND_MODULUS} to {(current + self.max_round_jump) % ROUND_MODULUS} "
                    f"(at most {self.max_round_jump} ahead, modulo 2^32), got {round_id}"
                )
        own = self._own_probabilities(probabilities)
        if not math.isfinite(yaw):
            raise RoundError(f"yaw must be finite, got {yaw}")
        ids = frozenset(int(n) for n in neighbours)
        bad = sorted(n for n in ids if not 0 <= n < self.n_robots or n == self.robot)
        if bad:
            raise RoundError(
                f"neighbours must be other robots of the swarm of {self.n_robots} "
                f"(robot {self.robot} is this one), got {bad}"
            )
        message = self.node.start_round(round_id, own, float(yaw))
        state = FusionState(own, float(yaw), law or self.law, own_id=self.robot, r_max=self.r_max)
        record = RoundRecord(round_id, ids, state)
        self.current = record
        self._rounds[round_id] = record
        while len(self._rounds) > KEPT_ROUNDS:
            self._rounds.popitem(last=False)
        broadcast = Broadcast(message, tuple(sorted(ids)))
        early, stale = self.buffer.take(round_id)
        return RoundStart(broadcast, tuple(self._process(m) for m in early), stale)

    def _own_probabilities(self, probabilities: npt.ArrayLike) -> FloatArray:
        try:
            v = np.array(probabilities, dtype=np.float64).reshape(-1)
            normalise_likelihood(v, self.n_classes)  # length, NaN, negative, all-zero
        except LikelihoodError as e:
            raise RoundError(f"own probabilities: {e}") from None
        if abs(float(v.sum()) - 1.0) > SUM_TOLERANCE:
            raise RoundError(f"own probabilities must sum to 1, got {float(v.sum()):.6g}")
        return v

    def receive(self, message: FloodMessage) -> Handled:
        """Handle one flooded message; never raises for anything a peer can send."""
        cur = self.current
        ahead = None if cur is None else rounds_ahead(message.round_id, cur.round_id)
        if ahead == 0:
            return self._process(message)
        if ahead is not None and ahead > self.max_round_jump:
            # Modulo 2^32 an earlier round is nearly 2^32 ahead: the lower half is "ahead".
            late = ahead >= ROUND_MODULUS // 2
            return self.reject(Reason.STALE_ROUND if late else Reason.TOO_FAR_AHEAD, message)
        kept, evicted = self.buffer.add(message, None if cur is None else cur.round_id)
        if kept:
            return Handled(Handling.BUFFERED, message, evicted=evicted)
        return self.reject(Reason.BUFFER_FULL, message)

    def reject(self, reason: str, message: FloodMessage) -> Handled:
        """Refuse ``message`` for ``reason`` (also for a check the caller made, such as
        a sender the bus says is someone else); counted in the current round's record,
        whichever round the message names."""
        if self.current is not None:
            self.current.rejected += 1
        return Handled(Handling.REJECTED, message, reason=reason)

    def _process(self, message: FloodMessage) -> Handled:
        cur = self.current
        assert cur is not None and message.round_id == cur.round_id  # receive/start_round route here
        if message.sender not in cur.neighbours:
            # Over a radio this robot could not have heard it; on a router anyone can put.
            return self.reject(Reason.NOT_NEIGHBOUR, message)
        if (message.origin == message.sender) != (message.hops == 0):
            # Only an origin sends hop count 0, and no robot forwards its own output.
            return self.reject(Reason.BAD_HOPS, message)
        reception = self.node.receive(message)
        if reception.outcome is Outcome.DUPLICATE:
            cur.duplicates += 1
            return Handled(Handling.DUPLICATE, message)
        if reception.outcome is Outcome.REJECTED or reception.heard is None:
            name = reception.reason.name.lower() if reception.reason is not None else Reason.IGNORED
            return self.reject(name, message)
        heard = reception.heard
        inc = cur.state.incorporate(heard.origin, heard.likelihood, heard.hops, heard.yaw)
        if inc is None:
            # FusionState ignores only its own id, seen origins and hops past r_max, which
            # the node has already filtered with the same r_max; kept as a guard.
            return self.reject(Reason.IGNORED, message)
        step = Step(
            heard.origin,
            heard.sender,
            heard.hops,
            heard.yaw,
            inc.weight,
            cur.state.decision,
            inc.posterior,
            cur.state.incorporated,
        )
        cur.steps.append(step)
        forward = reception.forward
        broadcast = None if forward is None else Broadcast(forward, tuple(sorted(cur.neighbours)))
        return Handled(Handling.ACCEPTED, message, step=step, broadcast=broadcast)

    def record(self, round_id: int | None = None) -> RoundRecord | None:
        """Round ``round_id``'s record (None: the current round); None when not kept."""
        if round_id is None:
            return self.current
        return self._rounds.get(round_id)

    @property
    def rounds_kept(self) -> int:
        return len(self._rounds)
