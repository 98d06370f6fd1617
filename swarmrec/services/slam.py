"""The slam service: one robot's part of the distributed two-stage Gauss-Seidel, over the bus.

Each robot runs one. It holds only its own pose graph (``<slam_folder>/<robot>.g2o``:
its vertices, its edges, its separators) and talks to the other robots only in
separator estimates and reports. The protocol is pure logic in
:class:`~swarmrec.slam.live.TeamRobot`; this service adapts it to the bus::

    load   (operator)  read the robot's g2o file, build its TeamRobot for the solve's settings
    solve  (operator)  put a hello on every team member's control/<self>, start the solver thread
    control/<sender>   SlamControl: hellos and aborts        --> TeamRobot.receive_hello / receive_abort
    inbox/<sender>     SlamStep: reports and estimates       --> TeamRobot.receive_turn
    solver thread      whenever TeamRobot.ready(): step, put one SlamStep on every team member's
                       inbox/<self>; a team member silent for slam_peer_timeout_s while waited for,
                       or whose liveliness token goes away, is declared gone (TeamRobot.vanish)
    status, estimate, sent   what the robot did, its estimate, the estimates it sent

The sender of a put is the last segment of its key, and the router's access
control lets only that robot's slam service put there (mutual TLS), so a robot
cannot speak for another; the body's sender must agree. Every refused message
is counted by reason (``swarmrec_slam_rejected_total``) and by the runner
(``swarmrec_rejected_requests_total``) and changes nothing. Bytes per peer and
stage, and floats by the 9/6 model, are counted when sent
(``swarmrec_slam_sent_bytes_total``, ``swarmrec_slam_sent_floats_total``).
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Sequence
from typing import Any

import zenoh

from swarmrec.errors import ConfigError, FailedPrecondition, InvalidArgument, NotFound, SwarmrecError
from swarmrec.runtime import Endpoint, RequestContext, ServiceBase, ServiceContext, Subscription, keys
from swarmrec.services.metrics import SlamMetrics
from swarmrec.services.settings import SlamServiceSettings
from swarmrec.slam.agent import LocalProblem
from swarmrec.slam.errors import TurnRejected
from swarmrec.slam.g2o import robot_file_name
from swarmrec.slam.live import Abort, Hello, Phase, TeamRobot, Turn
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import check_fields, encode
from swarmrec.wire.slam import (
    abort_to_proto,
    control_from_proto,
    estimate_to_proto,
    hello_to_proto,
    report_to_proto,
    settings_from_proto,
    stage_summary_to_proto,
    stage_to_proto,
    turn_from_proto,
    turn_to_proto,
)

__all__ = ["SlamService"]

_STATES = {
    Phase.GREETING: pb.SlamState.SLAM_STATE_GREETING,
    Phase.SOLVING: pb.SlamState.SLAM_STATE_SOLVING,
    Phase.DONE: pb.SlamState.SLAM_STATE_DONE,
    Phase.ABORTING: pb.SlamState.SLAM_STATE_ABORTING,
    Phase.ABORTED: pb.SlamState.SLAM_STATE_ABORTED,
    Phase.FAILED: pb.SlamState.SLAM_STATE_FAILED,
}
#: Estimates per page of the ``sent`` endpoint's answer are cut at this share of max_message_bytes.
_PAGE_SHARE = 0.5


class SlamService(ServiceBase):
    """The runner's adapter around :class:`~swarmrec.slam.live.TeamRobot` (see the module docstring)."""

    def __init__(self, ctx: ServiceContext) -> None:
        self.ctx = ctx
        self.bus = ctx.bus
        self.settings = ctx.settings(SlamServiceSettings)
        self.metrics = ctx.metric_set(SlamMetrics)
        # One lock for the TeamRobot: the solver thread, the two subscription workers and the
        # endpoints take it; sends happen outside it.
        self.lock = threading.Lock()
        self.wake = threading.Event()
        self.team: TeamRobot | None = None
        self.started = False
        self.rejected = 0
        self.last_heard = time.monotonic()
        # Robots whose liveliness token went away during a solve (zenoh's thread puts, the solver takes).
        self.gone: queue.SimpleQueue[int] = queue.SimpleQueue()
        self.thread: threading.Thread | None = None
        self.closing = threading.Event()
        self.alive_sub = ctx.session.liveliness().declare_subscriber(
            keys.alive(self.bus.swarm, "slam", "*"), self._on_alive
        )
        folder = self.settings.slam_folder
        ctx.log.info("slam ready", extra={"fields": {"folder": str(folder) if folder else None}})

    def close(self) -> None:
        self.closing.set()
        self.wake.set()
        if self.thread is not None:
            self.thread.join(timeout=5.0)
        self.alive_sub.undeclare()  # type: ignore[no-untyped-call]  # untyped in zenoh's stub

    # --- endpoints --------------------------------------------------------------------

    def load(self, req: pb.SlamLoadRequest, _ctx: RequestContext) -> pb.SlamProblem:
        check_fields(req)
        if req.solve_id == 0:
            raise InvalidArgument("solve_id must be > 0")
        try:
            settings = settings_from_proto(req.settings)
        except ConfigError as e:
            raise InvalidArgument(f"settings: {e}") from None
        if settings.max_iterations > self.settings.slam_max_iterations:
            raise InvalidArgument(
                f"max_iterations {settings.max_iterations} is above this service's slam_max_iterations "
                f"{self.settings.slam_max_iterations}"
            )
        folder = self.settings.slam_folder
        if folder is None:
            raise FailedPrecondition("this slam service has no slam_folder (its robot's g2o files)")
        with self.lock:
            team = self.team
            if team is not None and self.started and not team.finished:
                raise FailedPrecondition(f"solve {team.solve_id} is running ({team.phase.value})")
            if team is not None and team.solve_id == req.solve_id:
                raise InvalidArgument(f"solve {req.solve_id} was loaded already; use a new solve_id")
        try:
            problem = LocalProblem.from_robot_file(folder / robot_file_name(self.bus.robot), self.bus.robot)
            loaded = TeamRobot(problem, range(self.bus.n_robots), settings, req.solve_id)
        except SwarmrecError as e:
            raise FailedPrecondition(f"robot {self.bus.robot}'s graph: {e}") from None
        with self.lock:
            self.team, self.started, self.rejected = loaded, False, 0
        fields = {
            "solve": req.solve_id,
            "vertices": len(problem.poses),
            "neighbours": list(problem.neighbours),
        }
        self.ctx.log.info("solve loaded", extra={"fields": fields})
        return pb.SlamProblem(
            robot_id=self.bus.robot,
            solve_id=req.solve_id,
            vertices=len(problem.poses),
            edges=len(problem.edges),
            separators=[
                pb.SeparatorCount(robot_id=r, separators=n) for r, n in loaded.separator_counts().items()
            ],
            anchor=problem.anchor is not None,
        )

    def solve(self, req: pb.SlamSolveRequest, _ctx: RequestContext) -> pb.SlamSolveStarted:
        check_fields(req)
        with self.lock:
            team = self.team
            if team is None or team.solve_id != req.solve_id:
                loaded = "none" if team is None else str(team.solve_id)
                raise NotFound(f"solve {req.solve_id} is not loaded (loaded: {loaded})")
            if self.started:
                raise FailedPrecondition(f"solve {req.solve_id} was started already")
            self.started = True
            self.last_heard = time.monotonic()
            while not self.gone.empty():  # departures before this solve are not this solve's
                self.gone.get_nowait()
            hellos = team.start()
        for hello in hellos:
            self._send_control(hello)
        self.thread = threading.Thread(target=self._run, args=(team,), name="slam-solver", daemon=True)
        self.thread.start()
        self.ctx.log.info("solve started", extra={"fields": {"solve": req.solve_id}})
        return pb.SlamSolveStarted(robot_id=self.bus.robot, solve_id=req.solve_id)

    def status(self, req: pb.SlamStatusRequest, _ctx: RequestContext) -> pb.SlamStatus:
        check_fields(req)
        with self.lock:
            team = self.team
            if team is None:
                return pb.SlamStatus(robot_id=self.bus.robot, state=pb.SlamState.SLAM_STATE_IDLE)
            consistent = team.consistent or (0, 0)
            return pb.SlamStatus(
                robot_id=self.bus.robot,
                solve_id=team.solve_id,
                state=self._state(team),  # type: ignore[arg-type]  # an enum value
                stage=stage_to_proto("rotation" if team.linearisation == 0 else "pose"),  # type: ignore[arg-type]
                linearisation=team.linearisation,
                iteration=team.iteration,
                order=list(team.order),
                stages=[stage_summary_to_proto(s) for s in team.stages],
                converged=team.converged,
                reason=team.reason,
                vanished_robot_ids=sorted(team.vanished),
                consistent_linearisation=consistent[0],
                consistent_iteration=consistent[1],
                reports=[report_to_proto(r) for r in team.reports],
                rejected=self.rejected,
            )

    def estimate(self, req: pb.SlamEstimateRequest, _ctx: RequestContext) -> pb.SlamEstimate:
        check_fields(req)
        with self.lock:
            team = self.team
            if team is None:
                raise NotFound("no solve loaded")
            position, poses = team.estimate()
            return estimate_to_proto(self.bus.robot, team.solve_id, self._state(team), position, poses)

    def sent(self, req: pb.SlamSentRequest, _ctx: RequestContext) -> pb.SlamSentPage:
        check_fields(req)
        with self.lock:
            team = self.team
            if team is None:
                raise NotFound("no solve loaded")
            messages = list(team.sent)
            reports = {(r.linearisation, r.iteration): r for r in team.reports}
        if req.offset > len(messages):
            raise InvalidArgument(f"offset {req.offset} is past the {len(messages)} messages sent")
        page = pb.SlamSentPage(
            robot_id=self.bus.robot, solve_id=team.solve_id, total=len(messages), offset=req.offset
        )
        budget = int(_PAGE_SHARE * self.bus.max_message_bytes)
        size = 0
        for m in messages[req.offset :]:
            report = reports[(m.linearisation, m.iteration)]
            turn = Turn(
                team.solve_id, m.sender, m.receiver, m.linearisation, m.iteration, True, report.change, m
            )
            step = turn_to_proto(turn)
            size += step.ByteSize() + 8
            if size > budget and len(page.steps) > 0:
                break
            page.steps.append(step)
        return page

    def _state(self, team: TeamRobot) -> int:
        if not self.started:
            return pb.SlamState.SLAM_STATE_LOADED
        return _STATES[team.phase]

    # --- between robots ---------------------------------------------------------------

    def _refuse(self, e: TurnRejected) -> None:
        """Count a refused message (under the lock) and refuse it to the runner, which counts and logs it."""
        self.metrics.rejected.labels(e.reason).inc()
        self.rejected += 1
        raise InvalidArgument(f"{e.reason}: {e}") from None

    def _check_sender(self, key: str, sender: int) -> None:
        if keys.parse_sender(key) != sender:
            raise TurnRejected(
                "not_in_team", f"a message put on {key} says it is from robot {sender}: not the key's robot"
            )

    def inbox(self, msg: pb.SlamStep, ctx: RequestContext) -> None:
        check_fields(msg)
        with self.lock:
            try:
                self._check_sender(ctx.key, msg.sender_robot_id)
                turn = turn_from_proto(msg)
                if self.team is None:
                    raise TurnRejected("other_solve", f"no solve is loaded; got solve {msg.solve_id}")
                self.team.receive_turn(turn)
            except TurnRejected as e:
                self._refuse(e)
            self.last_heard = time.monotonic()
        self.wake.set()

    def control(self, msg: pb.SlamControl, ctx: RequestContext) -> None:
        check_fields(msg)
        replies: list[Abort] = []
        with self.lock:
            try:
                self._check_sender(ctx.key, msg.sender_robot_id)
                body = control_from_proto(msg)
                if self.team is None:
                    raise TurnRejected("other_solve", f"no solve is loaded; got solve {msg.solve_id}")
                if isinstance(body, Hello):
                    self.team.receive_hello(body)
                else:
                    replies = self.team.receive_abort(body)
            except TurnRejected as e:
                self._refuse(e)
            self.last_heard = time.monotonic()
        for abort in replies:
            self._send_control(abort)
        self.wake.set()

    def _on_alive(self, sample: zenoh.Sample) -> None:
        # zenoh's thread: note who went away, let the solver thread act on it.
        if sample.kind == zenoh.SampleKind.DELETE and self.thread is not None and self.thread.is_alive():
            parsed = keys.parse_alive(str(sample.key_expr))
            if parsed is not None:
                self.gone.put(parsed[1])
                self.wake.set()

    def _send_control(self, item: Hello | Abort) -> None:
        msg = hello_to_proto(item) if isinstance(item, Hello) else abort_to_proto(item)
        key = keys.endpoint(self.bus.swarm, "slam", item.receiver, f"control/{self.bus.robot}")
        self.ctx.put(key, msg, target_robot=item.receiver)

    def _send_turns(self, turns: Sequence[Turn]) -> None:
        for turn in turns:
            msg = turn_to_proto(turn)
            payload = encode(msg)
            key = keys.endpoint(self.bus.swarm, "slam", turn.receiver, f"inbox/{self.bus.robot}")
            self.ctx.put(key, msg, target_robot=turn.receiver, payload=payload)
            peer, carries = str(turn.receiver), "estimates" if turn.message is not None else "report"
            self.metrics.sent_bytes.labels(peer, turn.stage, carries).inc(len(payload))
            self.metrics.sent_messages.labels(peer, turn.stage, carries).inc()
            if turn.message is not None:
                self.metrics.sent_floats.labels(peer, turn.stage).inc(turn.message.floats)

    # --- the solver thread ------------------------------------------------------------

    def _run(self, team: TeamRobot) -> None:
        timeout = self.settings.slam_peer_timeout_s
        aborting_since: float | None = None
        try:
            while not self.closing.is_set():
                self.wake.clear()
                turns: list[Turn] = []
                aborts: list[Abort] = []
                wait = timeout
                with self.lock:
                    if self.team is not team:
                        return  # another solve was loaded
                    gone = []
                    while not self.gone.empty():
                        gone.append(self.gone.get_nowait())
                    if gone:
                        aborts = team.vanish(gone, f"robots {sorted(set(gone))}' liveliness tokens went away")
                    while team.advance():
                        pass
                    if team.finished:
                        break
                    now = time.monotonic()
                    if team.ready():
                        t0 = time.perf_counter()
                        turns = team.step()
                        self.metrics.step_seconds.labels(turns[0].stage if turns else "rotation").observe(
                            time.perf_counter() - t0
                        )
                        self.metrics.steps.labels(team.reports[-1].stage).inc()
                        self.last_heard = now
                        while team.advance():
                            pass
                    elif team.phase is Phase.ABORTING:
                        aborting_since = aborting_since or now
                        if now - aborting_since >= timeout:
                            team.end_abort()
                        wait = max(timeout - (now - aborting_since), 0.0)
                    elif now - self.last_heard >= timeout:
                        silent = team.waiting_for()
                        aborts = team.vanish(silent, f"robots {list(silent)} silent for {timeout:g} s")
                    else:
                        wait = timeout - (now - self.last_heard)
                for abort in aborts:
                    self._send_control(abort)
                if turns:
                    self._send_turns(turns)
                elif not aborts:
                    self.wake.wait(timeout=wait)
        except Exception as e:  # a bug or a broken graph must end the solve, not hang it
            self.ctx.log.error("solve failed", exc_info=e)
            with self.lock:
                team.phase, team.reason = Phase.FAILED, f"{type(e).__name__}: {e}"
        self._finished(team)

    def _finished(self, team: TeamRobot) -> None:
        with self.lock:
            outcome = {Phase.DONE: "converged" if team.converged else "unconverged"}.get(
                team.phase, team.phase.value
            )
            fields: dict[str, Any] = {
                "solve": team.solve_id,
                "outcome": outcome,
                "stages": [(s.stage, s.linearisation, s.iterations, s.converged) for s in team.stages],
                "reason": team.reason,
            }
        if team.phase in (Phase.DONE, Phase.ABORTED, Phase.FAILED):
            self.metrics.solves.labels(outcome).inc()
        self.ctx.log.info("solve ended", extra={"fields": fields})

    ENDPOINTS = (
        Endpoint(
            "load", pb.SlamLoadRequest, pb.SlamProblem, load, "read this robot's g2o file for a new solve"
        ),
        Endpoint("solve", pb.SlamSolveRequest, pb.SlamSolveStarted, solve, "start the loaded solve"),
        Endpoint(
            "status",
            pb.SlamStatusRequest,
            pb.SlamStatus,
            status,
            "where the solve is, its stages, own reports",
        ),
        Endpoint("estimate", pb.SlamEstimateRequest, pb.SlamEstimate, estimate, "this robot's estimate"),
        Endpoint("sent", pb.SlamSentRequest, pb.SlamSentPage, sent, "the separator estimates it sent, paged"),
    )
    SUBSCRIPTIONS = (
        Subscription(
            "inbox/*", pb.SlamStep, inbox, "team members' reports and separator estimates (key: sender)"
        ),
        Subscription("control/*", pb.SlamControl, control, "team members' hellos and aborts (key: sender)"),
    )
