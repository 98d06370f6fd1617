"""The fusion service: cooperative landmark recognition over the robots' radio links.

Each robot runs one. A round (``start_round``) gives the robot its own classifier
output, its yaw and the robots it can hear *this round* (its neighbours in the
communication graph, which the simulator or the radio decides and which may change
from round to round). The robot's state (:class:`~swarmrec.fusion.robot.FusionRobot`:
Algorithm 1 of Brent, Yuan and Stegagno, a weighted naive Bayes posterior per
round, early messages, the neighbour check) is pure logic; this service adapts it
to the bus::

    start_round --> own ClassifierOutput (hop_count 0) --put--> fusion/<j>/inbox/<i>  for each neighbour j
    fusion/<i>/inbox/<sender> (a subscription: the runner decodes, checks and counts) --> FusionRobot.receive
        new origin  -> incorporated, event, the forward (hop_count + 1) put to every neighbour
        duplicate   -> counted, ignored (Algorithm 1 line 11)
        rejected    -> counted by reason, logged, ignored

A radio broadcast reaches exactly the robots in range; on a zenoh router every
robot could reach every other, so the service emulates the broadcast by putting
one copy on each current neighbour's inbox, and the robot refuses anything whose
sender is not a current neighbour. The sender is the last segment of the key, which
the router's access control lets each robot's certificate write with its own robot
only (as the SLAM inboxes): a message whose body, or attachment, names another
sender than its key is refused (``sender_mismatch``).

What a relay says about the *origin* of what it forwards is proven by the origin's
signature (``origin_signature``, :mod:`swarmrec.runtime.origin`): under mutual TLS
a robot signs its own output with its fusion certificate's key, relays forward the
signature unchanged, and every receiver checks it against the origin's certificate
(issued by the swarm's CA, named as the origin's fusion service) before the robot
sees the message: a copy without one is refused as ``unsigned``, one whose
signature is not the origin's over what it carries as ``bad_signature``. The
insecure mode has no keys: it neither signs nor checks.
"""

from __future__ import annotations

import threading
from collections import OrderedDict

from swarmrec.errors import ConfigError, InvalidArgument, NotFound
from swarmrec.fusion.robot import KEPT_ROUNDS, Broadcast, FusionRobot, Handled, Handling, Reason, RoundError
from swarmrec.fusion.wnbc import WeightLaw, make_weight_law
from swarmrec.runtime import Endpoint, RequestContext, ServiceBase, ServiceContext, Subscription, keys
from swarmrec.runtime.origin import OriginSigner, OriginVerifier
from swarmrec.runtime.settings import SecuritySettings
from swarmrec.services import registry
from swarmrec.services.metrics import FusionMetrics
from swarmrec.services.settings import FusionSettings, LandmarkSettings
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import check_fields, encode
from swarmrec.wire.fusion import (
    classifier_output_to_flood,
    flood_to_classifier_output,
    origin_statement,
    step_to_proto,
    weight_law_from_proto,
)

__all__ = ["FusionService"]


class FusionService(ServiceBase):
    """The runner's adapter around :class:`~swarmrec.fusion.robot.FusionRobot`."""

    def __init__(self, ctx: ServiceContext) -> None:
        self.ctx = ctx
        self.bus = ctx.bus
        fusion = ctx.settings(FusionSettings)
        self.metrics = ctx.metric_set(FusionMetrics)
        self.law = make_weight_law(fusion.fusion_law, lam=fusion.fusion_lambda)
        self.robot = FusionRobot(
            self.bus.robot,
            self.bus.n_robots,
            law=self.law,
            n_classes=ctx.settings(LandmarkSettings).n_classes,
            r_max=fusion.fusion_r_max or None,
            early_per_round=fusion.fusion_early_messages,
            max_round_jump=fusion.fusion_max_round_jump,
        )
        # One lock orders everything that touches the rounds: start_round (endpoint
        # workers), the inbox worker and posterior reads. Sends happen under it too,
        # so a robot's own message always leaves before any forward of the same round.
        self.lock = threading.Lock()
        self.event_key = keys.event(self.bus.swarm, "fusion", self.bus.robot)
        self.signer, self.verifier = _origin_proof(ctx)
        # Each origin's output of recent rounds, by (round, origin): the statement and the
        # signature checked (a duplicate carrying both again needs no second check; on a dense
        # graph most copies are duplicates), kept to forward with it. Bounded: a forward leaves
        # as soon as its message is folded in.
        self.signatures: OrderedDict[tuple[int, int], tuple[bytes, bytes]] = OrderedDict()
        self.max_signatures = 4 * self.bus.n_robots + fusion.fusion_early_messages + 64
        fields = {"law": self.law.name, "lambda": fusion.fusion_lambda, "r_max": fusion.fusion_r_max}
        ctx.log.info("fusion ready", extra={"fields": fields})

    def member_info(self) -> pb.MemberInfo:
        with self.lock:
            return pb.MemberInfo(stored_items=self.robot.rounds_kept)

    # --- endpoints ------------------------------------------------------------------

    def start_round(self, req: pb.FusionRoundStart, _ctx: RequestContext) -> pb.FusionRoundStarted:
        check_fields(req, "round_id")
        law: WeightLaw | None = None
        if req.HasField("weight_law"):
            try:
                law = weight_law_from_proto(req.weight_law)
            except ConfigError as e:
                raise InvalidArgument(f"weight_law: {e}") from None
        with self.lock:
            try:
                started = self.robot.start_round(
                    req.round_id, list(req.probabilities), req.yaw_rad, list(req.neighbour_robot_ids), law
                )
            except RoundError as e:
                raise InvalidArgument(str(e)) from None
            self.metrics.rounds.inc()
            if self.signer is not None:
                own = flood_to_classifier_output(started.broadcast.message)
                statement = origin_statement(self.bus.swarm, own)
                self._keep_signature(own, statement, self.signer.sign(statement))
            if started.stale:
                self.metrics.rejected.labels(Reason.STALE_ROUND.value).inc(started.stale)
            self._send(started.broadcast)
            for handled in started.early:
                self._apply(handled)
        fields = {
            "round": req.round_id,
            "neighbours": list(started.broadcast.targets),
            "early": len(started.early),
        }
        self.ctx.log.info("round started", extra={"fields": fields})
        return pb.FusionRoundStarted(
            robot_id=self.bus.robot,
            round_id=req.round_id,
            sent=len(started.broadcast.targets),
            early_messages=len(started.early),
        )

    def posterior(self, req: pb.PosteriorRequest, _ctx: RequestContext) -> pb.FusionPosterior:
        check_fields(req)  # an empty request asks for the latest round, which is harmless
        round_id = req.round_id if req.HasField("round_id") else None
        with self.lock:
            record = self.robot.record(round_id)
            if record is None:
                what = (
                    "no round started yet"
                    if round_id is None
                    else f"round {round_id} was not started or is past the last {KEPT_ROUNDS} rounds kept"
                )
                raise NotFound(what)
            return pb.FusionPosterior(
                robot_id=self.bus.robot,
                round_id=record.round_id,
                posterior=record.state.posterior.tolist(),
                decision=record.state.decision,
                incorporated=record.state.incorporated,
                duplicates=record.duplicates,
                rejected=record.rejected,
                heard_all=record.state.incorporated == self.robot.n_robots - 1,
                history=[step_to_proto(s) for s in record.steps],
                neighbour_robot_ids=sorted(record.neighbours),
            )

    # --- the inbox ------------------------------------------------------------------

    def inbox(self, msg: pb.ClassifierOutput, ctx: RequestContext) -> None:
        # Another message's bytes are refused here (MALFORMED); an empty one has no
        # probabilities and the robot refuses it (wrong_length).
        check_fields(msg)
        message = classifier_output_to_flood(msg)
        with self.lock:
            sender = keys.parse_sender(ctx.key)
            claimed = {msg.sender_robot_id} | ({ctx.caller_robot} - {None})
            if sender is None or claimed != {sender}:
                # The key says who put it (the router checked it against the certificate);
                # a body or attachment claiming another robot is refused.
                self._apply(self.robot.reject(Reason.SENDER_MISMATCH, message))
                return
            if self.verifier is not None:
                refused = self._check_origin(msg)
                if refused is not None:
                    self._apply(self.robot.reject(refused, message))
                    return
            self._apply(self.robot.receive(message))

    def _check_origin(self, msg: pb.ClassifierOutput) -> Reason | None:
        """Why the origin's signature does not vouch for ``msg``; None when it does (and
        then it is kept, to forward and to know a duplicate by)."""
        assert self.verifier is not None
        signature = msg.origin_signature
        if not signature:
            return Reason.UNSIGNED
        statement = origin_statement(self.bus.swarm, msg)
        if self.signatures.get((msg.round_id, msg.origin_robot_id)) == (statement, signature):
            return None  # a copy of what was checked already
        if self.verifier.verify(msg.origin_robot_id, statement, signature):
            return Reason.BAD_SIGNATURE
        self._keep_signature(msg, statement, signature)
        return None

    def _keep_signature(self, msg: pb.ClassifierOutput, statement: bytes, signature: bytes) -> None:
        self.signatures[(msg.round_id, msg.origin_robot_id)] = (statement, signature)
        while len(self.signatures) > self.max_signatures:
            self.signatures.popitem(last=False)

    def _apply(self, handled: Handled) -> None:
        """Count, forward and publish what the robot did with one message (under the lock)."""
        m = self.metrics
        if handled.outcome is Handling.BUFFERED:
            m.early.inc()
            if handled.evicted:
                m.rejected.labels(Reason.BUFFER_FULL.value).inc(handled.evicted)
        elif handled.outcome is Handling.DUPLICATE:
            m.duplicates.inc()
        elif handled.outcome is Handling.REJECTED:
            msg = handled.message
            m.rejected.labels(handled.reason).inc()
            fields = {
                "reason": handled.reason,
                "round": msg.round_id,
                "origin": msg.origin,
                "sender": msg.sender,
                "hops": msg.hops,
            }
            self.ctx.log.warning("rejected fusion message", extra={"fields": fields})
        elif handled.step is not None:
            m.incorporated.inc()
            if handled.broadcast is not None:
                self._send(handled.broadcast)
            self._publish(handled)

    def _send(self, broadcast: Broadcast) -> None:
        msg = flood_to_classifier_output(broadcast.message)
        if self.signer is not None:
            # The origin's own signature, as received (or made here for this robot's output).
            kept = self.signatures.get((msg.round_id, msg.origin_robot_id))
            msg.origin_signature = kept[1] if kept is not None else b""
        payload = encode(msg)
        for target in broadcast.targets:
            key = keys.endpoint(self.bus.swarm, "fusion", target, f"inbox/{self.bus.robot}")
            self.ctx.put(key, msg, target_robot=target, payload=payload)

    def _publish(self, handled: Handled) -> None:
        cur, step = self.robot.current, handled.step
        assert cur is not None and step is not None  # a step belongs to the current round
        update = pb.FusionUpdate(
            robot_id=self.bus.robot,
            round_id=cur.round_id,
            step=step_to_proto(step),
            posterior=step.posterior.tolist(),
            decision=step.decision_after,
            # From the step, not the round: early messages are all folded in before
            # their events go out.
            incorporated=step.incorporated,
            heard_all=step.incorporated == self.robot.n_robots - 1,
        )
        self.ctx.publish(self.event_key, update)

    ENDPOINTS = (
        Endpoint(
            "start_round",
            pb.FusionRoundStart,
            pb.FusionRoundStarted,
            start_round,
            "begin a round: send own output",
        ),
        Endpoint(
            "posterior", pb.PosteriorRequest, pb.FusionPosterior, posterior, "a round's fused posterior"
        ),
    )
    SUBSCRIPTIONS = (
        Subscription(
            "inbox/*", pb.ClassifierOutput, inbox, "outputs flooded by the current neighbours (key: sender)"
        ),
    )


def _origin_proof(ctx: ServiceContext) -> tuple[OriginSigner | None, OriginVerifier | None]:
    """This robot's signer and every origin's verifier under mutual TLS (the PKI folder holds
    this robot's fusion key, the CA and the other robots' fusion certificates); none in the
    insecure mode."""
    security = ctx.settings(SecuritySettings)
    if security.security != "mtls" or security.pki_dir is None:
        return None, None
    pki, swarm = security.pki_dir, ctx.bus.swarm
    entry = registry.spec("fusion")

    def cn(robot: int) -> str:
        return entry.common_name(swarm, robot)

    signer = OriginSigner(pki / f"{cn(ctx.bus.robot)}.key")
    n = ctx.bus.n_robots
    verifier = OriginVerifier(pki / "ca.pem", lambda robot: pki / f"{cn(robot)}.pem", cn, n_robots=n)
    return signer, verifier
