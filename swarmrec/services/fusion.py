"""The fusion service: cooperative landmark recognition over the robots' radio links.

Each robot runs one. A round (``start_round``) gives the robot its own classifier
output, its yaw and the robots it can hear *this round* (its neighbours in the
communication graph, which the simulator or the radio decides and which may change
from round to round). The service then runs Algorithm 1 of Brent, Yuan and Stegagno
(:class:`~swarmrec.fusion.flooding.FloodingNode`) over zenoh and folds every new
origin's output into a weighted naive Bayes posterior
(:class:`~swarmrec.fusion.wnbc.FusionState`)::

    start_round --> own ClassifierOutput (hop_count 0) --put--> fusion/<j>/inbox  for each neighbour j
    fusion/<i>/inbox --> subscriber callback enqueues --> worker: FloodingNode.receive
        new origin  -> FusionState.incorporate, event, put the forward (hop_count + 1) to every neighbour
        duplicate   -> counted, ignored (Algorithm 1 line 11)
        malformed   -> counted by reason, logged, ignored

A radio broadcast reaches exactly the robots in range; on a zenoh router every
robot could reach every other, so the service emulates the broadcast by putting
one copy on each current neighbour's inbox and by refusing anything whose sender
is not a current neighbour. A broadcast also reaches the robot it came from,
so forwards go to *every* neighbour, as Algorithm 1 and
:func:`~swarmrec.fusion.flooding.simulate_flooding` do (that copy comes back as a
duplicate).

Messages of a round this robot has not started yet are kept (at most
``fusion_early_messages`` per round, for at most :data:`MAX_EARLY_ROUNDS` rounds)
and processed, in arrival order, right after the robot's own message goes out
when the round starts: robots start a round at slightly different times, and
dropping what a faster neighbour already sent would make the result depend on
timing. Round ids must increase, so a message of a lower round than the current
one is late and rejected (``stale_round``).

The pure part (:class:`EarlyBuffer`, :class:`FusionRobot`) has no I/O and is
tested without a bus; :class:`FusionService` adapts it to the runner.
"""

from __future__ import annotations

import contextlib
import math
import queue
import threading
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np
import numpy.typing as npt
import zenoh

from swarmrec.errors import ConfigError, SwarmrecError, WireError
from swarmrec.fusion.flooding import SUM_TOLERANCE, FloodingNode, FloodMessage, Outcome
from swarmrec.fusion.wnbc import (
    FusionState,
    LikelihoodError,
    WeightLaw,
    make_weight_law,
    normalise_likelihood,
)
from swarmrec.services import keys
from swarmrec.services.common import invalid
from swarmrec.services.metrics import scope_between
from swarmrec.services.rpc import caller_robot, encoding_for, schema_of
from swarmrec.services.runner import Endpoint, RequestContext, RequestError, ServiceContext
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import decode, encode, schema_name

__all__ = [
    "INBOX_CAPACITY",
    "KEPT_ROUNDS",
    "MAX_EARLY_ROUNDS",
    "Broadcast",
    "EarlyBuffer",
    "FusionRobot",
    "FusionService",
    "Handled",
    "Handling",
    "Reason",
    "RoundError",
    "RoundRecord",
    "RoundStart",
    "Step",
    "classifier_output_to_flood",
    "flood_to_classifier_output",
    "round_law",
]

FloatArray = npt.NDArray[np.float64]

#: Future rounds whose early messages are kept; a robot is at most a round or two
#: behind its neighbours, and absurd round ids must not take unbounded memory.
MAX_EARLY_ROUNDS = 4
#: Finished rounds whose posterior the ``posterior`` endpoint can still report.
KEPT_ROUNDS = 8
#: Deliveries waiting for the worker; beyond it the zenoh callback drops (and counts)
#: rather than block zenoh's receive thread.
INBOX_CAPACITY = 65536

_CLASSIFIER_SCHEMA = schema_name(pb.ClassifierOutput)


class Reason(StrEnum):
    """Why the service rejected a flooded message: the ``reason`` label of
    ``swarmrec_fusion_rejected_total``. The core's own rejections
    (:class:`~swarmrec.fusion.flooding.Rejection`) appear under their lower-case
    names (``wrong_length``, ``not_finite``, ``bad_hops``, ...)."""

    MALFORMED = "malformed"
    WRONG_SCHEMA = "wrong_schema"
    TOO_LARGE = "too_large"
    SENDER_MISMATCH = "sender_mismatch"
    INBOX_FULL = "inbox_full"
    NOT_NEIGHBOUR = "not_neighbour"
    STALE_ROUND = "stale_round"
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

    When a message of a new round finds every slot taken, the highest buffered round
    makes way if the new one is lower (the lower round starts sooner, and a bogus far
    round id must not lock the buffer); otherwise the new message is refused.
    """

    def __init__(self, per_round: int, max_rounds: int = MAX_EARLY_ROUNDS) -> None:
        if per_round < 0 or max_rounds < 1:
            raise ValueError(f"need per_round >= 0 and max_rounds >= 1, got {per_round}, {max_rounds}")
        self.per_round = per_round
        self.max_rounds = max_rounds
        self._rounds: dict[int, list[FloodMessage]] = {}

    def add(self, message: FloodMessage) -> tuple[bool, int]:
        """Keep ``message``; returns (kept, messages of another round evicted for it)."""
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
            highest = max(self._rounds)
            if message.round_id > highest:
                return False, 0
            evicted = len(self._rounds.pop(highest))
        self._rounds[message.round_id] = [message]
        return True, evicted

    def take(self, round_id: int) -> tuple[list[FloodMessage], int]:
        """Round ``round_id``'s messages in arrival order, and the number of messages of
        lower rounds dropped (those rounds were skipped here and will never start)."""
        messages = self._rounds.pop(round_id, [])
        stale = [r for r in self._rounds if r < round_id]
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
    ) -> None:
        self.robot = robot
        self.n_robots = n_robots
        self.n_classes = n_classes
        self.law = law
        self.r_max = r_max
        self.node = FloodingNode(robot, n_robots, n_classes=n_classes, r_max=r_max)
        self.buffer = EarlyBuffer(early_per_round)
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
        if self.current is not None and round_id <= self.current.round_id:
            raise RoundError(
                f"round ids must increase: round {self.current.round_id} already started, got {round_id}"
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
        if cur is None or message.round_id > cur.round_id:
            kept, evicted = self.buffer.add(message)
            if kept:
                return Handled(Handling.BUFFERED, message, evicted=evicted)
            return self._reject(Reason.BUFFER_FULL, message)
        if message.round_id < cur.round_id:
            return self._reject(Reason.STALE_ROUND, message)
        return self._process(message)

    def note_rejected(self) -> None:
        """Count a message the service rejected before it got here (e.g. malformed bytes)."""
        if self.current is not None:
            self.current.rejected += 1

    def _reject(self, reason: str, message: FloodMessage) -> Handled:
        self.note_rejected()
        return Handled(Handling.REJECTED, message, reason=reason)

    def _process(self, message: FloodMessage) -> Handled:
        cur = self.current
        assert cur is not None and message.round_id == cur.round_id  # receive/start_round route here
        if message.sender not in cur.neighbours:
            # Over a radio this robot could not have heard it; on a router anyone can put.
            return self._reject(Reason.NOT_NEIGHBOUR, message)
        if (message.origin == message.sender) != (message.hops == 0):
            # Only an origin sends hop count 0, and no robot forwards its own output.
            return self._reject(Reason.BAD_HOPS, message)
        reception = self.node.receive(message)
        if reception.outcome is Outcome.DUPLICATE:
            cur.duplicates += 1
            return Handled(Handling.DUPLICATE, message)
        if reception.outcome is Outcome.REJECTED or reception.heard is None:
            name = reception.reason.name.lower() if reception.reason is not None else Reason.MALFORMED
            return self._reject(name, message)
        heard = reception.heard
        inc = cur.state.incorporate(heard.origin, heard.likelihood, heard.hops, heard.yaw)
        if inc is None:
            # FusionState ignores only its own id, seen origins and hops past r_max, which
            # the node has already filtered with the same r_max; kept as a guard.
            return self._reject(Reason.IGNORED, message)
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


def round_law(spec: pb.WeightLaw) -> WeightLaw:
    """The weight law a ``FusionRoundStart.weight_law`` names; ConfigError for an unknown
    name or a lambda that is negative or not a number."""
    lam = float(getattr(spec, "lambda")) if spec.HasField("lambda") else None  # a Python keyword
    return make_weight_law(spec.name, lam=lam)


def classifier_output_to_flood(msg: pb.ClassifierOutput) -> FloodMessage:
    """The core's view of a received ClassifierOutput (validated by the node, not here)."""
    return FloodMessage(
        round_id=msg.round_id,
        origin=msg.origin_robot_id,
        sender=msg.sender_robot_id,
        hops=msg.hop_count,
        yaw=msg.yaw_rad,
        likelihood=list(msg.probabilities),
    )


def flood_to_classifier_output(message: FloodMessage) -> pb.ClassifierOutput:
    """The wire form of a message to send; float32 on the wire, so a vector received
    and forwarded goes out bit-identical to what its origin sent."""
    return pb.ClassifierOutput(
        origin_robot_id=message.origin,
        round_id=message.round_id,
        probabilities=np.asarray(message.likelihood, dtype=np.float64).tolist(),
        yaw_rad=message.yaw,
        hop_count=message.hops,
        sender_robot_id=message.sender,
    )


def _step_to_proto(step: Step) -> pb.FusionStep:
    return pb.FusionStep(
        origin_robot_id=step.origin,
        sender_robot_id=step.sender,
        hops=step.hops,
        yaw_rad=step.yaw,
        weight=step.weight,
        decision_after=step.decision_after,
    )


@dataclass(frozen=True)
class _Delivery:
    """What the zenoh callback hands the worker: bytes and headers, nothing parsed."""

    data: bytes
    schema: str
    sender: int | None


class FusionService:
    """The runner's adapter around :class:`FusionRobot` (see the module docstring)."""

    def __init__(self, ctx: ServiceContext) -> None:
        s = ctx.settings
        self.ctx = ctx
        self.law = make_weight_law(s.fusion_law, lam=s.fusion_lambda)
        self.robot = FusionRobot(
            s.robot,
            s.n_robots,
            law=self.law,
            n_classes=s.n_classes,
            r_max=s.fusion_r_max or None,
            early_per_round=s.fusion_early_messages,
        )
        # One lock orders everything that touches the rounds: start_round (runner
        # workers), the inbox worker and posterior reads. Sends happen under it too,
        # so a robot's own message always leaves before any forward of the same round.
        self.lock = threading.Lock()
        self.inbox: queue.Queue[_Delivery | None] = queue.Queue(maxsize=INBOX_CAPACITY)
        self.attachment = str(s.robot).encode()
        self.event_key = keys.event(s.swarm, "fusion", s.robot)
        self.worker = threading.Thread(target=self._work, name="fusion-inbox", daemon=True)
        self.worker.start()
        self.subscriber = ctx.session.declare_subscriber(keys.fusion_inbox(s.swarm, s.robot), self._on_sample)
        ctx.log.info(
            "fusion ready",
            extra={
                "fields": {
                    "law": self.law.name,
                    "lambda": s.fusion_lambda,
                    "r_max": s.fusion_r_max,
                    "n_classes": s.n_classes,
                }
            },
        )

    def endpoints(self) -> Sequence[Endpoint]:
        return [
            Endpoint("start_round", pb.FusionRoundStart, self.start_round),
            Endpoint("posterior", pb.PosteriorRequest, self.posterior),
        ]

    def member_info(self) -> pb.MemberInfo:
        with self.lock:
            return pb.MemberInfo(stored_items=self.robot.rounds_kept)

    # --- endpoints ------------------------------------------------------------------

    def start_round(self, req: pb.FusionRoundStart, _ctx: RequestContext) -> pb.FusionRoundStarted:
        law = None
        if req.HasField("weight_law"):
            try:
                law = round_law(req.weight_law)
            except ConfigError as e:
                raise invalid(f"weight_law: {e}") from None
        with self.lock:
            try:
                started = self.robot.start_round(
                    req.round_id, list(req.probabilities), req.yaw_rad, list(req.neighbour_robot_ids), law
                )
            except RoundError as e:
                raise invalid(str(e)) from None
            self.ctx.metrics.fusion_rounds.inc()
            if started.stale:
                self.ctx.metrics.fusion_rejected.labels(Reason.STALE_ROUND.value).inc(started.stale)
            self._send(started.broadcast)
            for handled in started.early:
                self._apply(handled)
        self.ctx.log.info(
            "round started",
            extra={
                "fields": {
                    "round": req.round_id,
                    "neighbours": list(started.broadcast.targets),
                    "early": len(started.early),
                }
            },
        )
        return pb.FusionRoundStarted(
            robot_id=self.ctx.settings.robot,
            round_id=req.round_id,
            sent=len(started.broadcast.targets),
            early_messages=len(started.early),
        )

    def posterior(self, req: pb.PosteriorRequest, _ctx: RequestContext) -> pb.FusionPosterior:
        round_id = req.round_id if req.HasField("round_id") else None
        with self.lock:
            record = self.robot.record(round_id)
            if record is None:
                what = (
                    "no round started yet"
                    if round_id is None
                    else f"round {round_id} was not started or is past the last {KEPT_ROUNDS} rounds kept"
                )
                raise RequestError(pb.ErrorCode.ERROR_CODE_NOT_FOUND, what)
            return pb.FusionPosterior(
                robot_id=self.ctx.settings.robot,
                round_id=record.round_id,
                posterior=record.state.posterior.tolist(),
                decision=record.state.decision,
                incorporated=record.state.incorporated,
                duplicates=record.duplicates,
                rejected=record.rejected,
                heard_all=record.state.incorporated == self.robot.n_robots - 1,
                history=[_step_to_proto(s) for s in record.steps],
                neighbour_robot_ids=sorted(record.neighbours),
            )

    # --- the inbox ------------------------------------------------------------------

    def _on_sample(self, sample: zenoh.Sample) -> None:
        # zenoh's thread: copy the bytes out and return; the worker does the rest.
        delivery = _Delivery(
            sample.payload.to_bytes(), schema_of(sample.encoding), caller_robot(sample.attachment)
        )
        try:
            self.inbox.put_nowait(delivery)
        except queue.Full:
            self.ctx.metrics.fusion_rejected.labels(Reason.INBOX_FULL.value).inc()
            self.ctx.log.warning("fusion inbox full, message dropped")

    def _work(self) -> None:
        while True:
            delivery = self.inbox.get()
            if delivery is None:
                return
            try:
                self._deliver(delivery)
            except Exception as e:  # a bug must not end the inbox: log it and go on
                self.ctx.log.error("fusion inbox failed", exc_info=e)

    def _deliver(self, d: _Delivery) -> None:
        self.ctx.metrics.count_received(
            "ClassifierOutput", scope_between(self.ctx.settings.robot, d.sender), len(d.data)
        )
        message = self._parse(d)
        if message is not None:
            with self.lock:
                self._apply(self.robot.receive(message))

    def _parse(self, d: _Delivery) -> FloodMessage | None:
        """The delivery as the core's message; None (counted and logged) when it is not one."""
        if len(d.data) > self.ctx.settings.max_message_bytes:
            self._refuse(Reason.TOO_LARGE, f"{len(d.data)} bytes", d.sender)
            return None
        if d.schema and d.schema != _CLASSIFIER_SCHEMA:
            self._refuse(Reason.WRONG_SCHEMA, d.schema, d.sender)
            return None
        try:
            msg = decode(d.data, pb.ClassifierOutput)
        except WireError as e:
            self._refuse(Reason.MALFORMED, str(e), d.sender)
            return None
        if d.sender is not None and d.sender != msg.sender_robot_id:
            detail = f"sent by robot {d.sender}, claims {msg.sender_robot_id}"
            self._refuse(Reason.SENDER_MISMATCH, detail, d.sender)
            return None
        return classifier_output_to_flood(msg)

    def _refuse(self, reason: Reason, detail: str, sender: int | None) -> None:
        with self.lock:
            self.robot.note_rejected()
        self._count_rejection(reason.value, {"detail": detail[:300], "sender": sender})

    def _count_rejection(self, reason: str, fields: dict[str, object]) -> None:
        self.ctx.metrics.fusion_rejected.labels(reason).inc()
        self.ctx.log.warning("rejected fusion message", extra={"fields": {"reason": reason, **fields}})

    def _apply(self, handled: Handled) -> None:
        """Count, forward and publish what the robot did with one message (under the lock)."""
        m = self.ctx.metrics
        if handled.outcome is Handling.BUFFERED:
            m.fusion_early.inc()
            if handled.evicted:
                m.fusion_rejected.labels(Reason.BUFFER_FULL.value).inc(handled.evicted)
        elif handled.outcome is Handling.DUPLICATE:
            m.fusion_duplicates.inc()
        elif handled.outcome is Handling.REJECTED:
            msg = handled.message
            fields: dict[str, object] = {
                "round": msg.round_id,
                "origin": msg.origin,
                "sender": msg.sender,
                "hops": msg.hops,
            }
            self._count_rejection(handled.reason, fields)
        elif handled.step is not None:
            m.fusion_incorporated.inc()
            if handled.broadcast is not None:
                self._send(handled.broadcast)
            self._publish(handled.step)

    def _send(self, broadcast: Broadcast) -> None:
        msg = flood_to_classifier_output(broadcast.message)
        payload = encode(msg)
        s = self.ctx.settings
        for target in broadcast.targets:
            # BLOCK: a flooded message lost to congestion would be lost for every robot behind.
            self.ctx.session.put(
                keys.fusion_inbox(s.swarm, target),
                payload,
                encoding=encoding_for(msg),
                congestion_control=zenoh.CongestionControl.BLOCK,
                attachment=self.attachment,
            )
            self.ctx.metrics.count_sent("ClassifierOutput", scope_between(s.robot, target), len(payload))

    def _publish(self, step: Step) -> None:
        cur = self.robot.current
        assert cur is not None  # a step belongs to the current round
        update = pb.FusionUpdate(
            robot_id=self.ctx.settings.robot,
            round_id=cur.round_id,
            step=_step_to_proto(step),
            posterior=step.posterior.tolist(),
            decision=step.decision_after,
            # From the step, not the round: early messages are all folded in before
            # their events go out.
            incorporated=step.incorporated,
            heard_all=step.incorporated == self.robot.n_robots - 1,
        )
        self.ctx.publish(self.event_key, update)

    def close(self) -> None:
        self.subscriber.undeclare()  # type: ignore[no-untyped-call]  # untyped in zenoh's stub
        # After what is queued: the worker drains first. Full means the worker is stuck;
        # it is a daemon thread and ends with the process.
        with contextlib.suppress(queue.Full):
            self.inbox.put(None, timeout=5.0)
        self.worker.join(timeout=5.0)
