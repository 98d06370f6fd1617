"""One robot of a live distributed Gauss-Seidel team: the protocol as pure logic (:class:`TeamRobot`).

:func:`~swarmrec.slam.dgs.run_dgs` runs every agent in one process and hands
each message over at once. A team whose robots run apart (the ``slam``
service, one per robot, over zenoh) needs a protocol that gives every agent
exactly the same inputs in the same order, whatever the order in which the
bus delivers messages. :class:`TeamRobot` is that protocol for one robot,
without a bus: the service feeds it what arrives and sends what it returns.

::

    load    the robot's LocalProblem from its own g2o file; robot 0 holds the anchor
    hello   each robot tells every team member how many separators it shares with each
            robot; with every hello in, all compute the same turn order (order_robots)
            and check that the team's separators connect it
    turns   after each of its steps a robot sends every team member one Turn: its report
            (stage, linearisation, iteration, solved, change) and, to a neighbour, its
            separator estimates (a DgsMessage: 9 floats a key in the rotation stage, 6 in
            a pose stage), nothing else
    when    Gauss-Seidel: the robot at position p takes step k once it holds every
            report of iteration k - 1 and those of iteration k of the robots before it in
            the order; Jacobi: once it holds every report of k - 1
    inbox   before step k it gives its agent what run_dgs would have delivered by then:
            estimates of iterations < k, and in Gauss-Seidel those of iteration k from the
            robots before it (each neighbour's newest; the agent ignores older ones)
    stop    a stage ends after iteration k once every report of k is in and
            stage_converged says so, or k = max_iterations; the robot gives its agent the
            stage's remaining estimates, then begin_pose_stage()
    abort   a team member silent too long (the service's timeout) or gone (its liveliness
            token): each survivor tells the others the last position every robot completed
            as far as it knows, all end at the earliest one named, and each answers with
            its estimate there: the last consistent estimate

Messages are buffered by (linearisation, iteration, sender), so the order in
which they arrive does not matter, and each is checked before it is kept
(:meth:`TeamRobot.receive_turn` raises :class:`~swarmrec.slam.errors.TurnRejected`
with a reason and changes nothing): only the current solve, only team
members, only positions the protocol can produce next, never twice, estimates
only from a neighbour and exactly for the keys it shares. Fed the same graph
and settings, a team of TeamRobots sends exactly :func:`run_dgs`'s messages
and reports, bit for bit (tests/unit/test_slam_live.py delivers them in
shuffled order; tests/integration/test_slam_service.py over zenoh).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from enum import Enum
from types import MappingProxyType

from swarmrec.slam.agent import DgsAgent, LocalProblem
from swarmrec.slam.dgs import DgsSettings, StageSummary, stage_converged
from swarmrec.slam.errors import GraphError, TurnRejected
from swarmrec.slam.keys import describe_key
from swarmrec.slam.lie import Pose
from swarmrec.slam.messages import DgsMessage, Stage, StepReport
from swarmrec.slam.ordering import order_robots

__all__ = [
    "KEPT_SNAPSHOTS",
    "REJECT_REASONS",
    "Abort",
    "Hello",
    "Phase",
    "Position",
    "TeamRobot",
    "Turn",
    "stage_of",
]

#: (linearisation, iteration): 0 is the rotation stage, 1, 2, ... the pose stages;
#: iteration 0 is a stage's start (before any step), (0, 0) the initial estimate.
Position = tuple[int, int]

#: Why a message is refused (the values of the service's ``reason`` metric label).
REJECT_REASONS = (
    "other_solve",  # another solve's id (an earlier one, or a solve this robot did not load)
    "not_in_team",  # sender or receiver is not this team's robot (or the sender is the receiver)
    "vanished",  # from a robot already declared gone
    "wrong_stage",  # a stage / linearisation this robot is not in and will not be in next
    "out_of_turn",  # an iteration the sender cannot have reached yet, or one long past
    "duplicate",  # a second message for a position already heard from this sender
    "bad_report",  # a change that is NaN, negative, or finite for a robot that did not solve
    "bad_values",  # estimates that are not finite, of the wrong length, or name a key twice
    "not_shared",  # estimates from a robot that shares no separator, or of keys it does not share
    "missing_estimates",  # a neighbour that solved but sent no (or not all) estimates
    "bad_hello",  # a hello whose separator counts contradict this robot's own
    "finished",  # the solve is over
)

#: Own estimates kept per step (a consistent position is at most a few iterations back).
KEPT_SNAPSHOTS = 4


class Phase(Enum):
    """Where one robot's solve is."""

    GREETING = "greeting"  # hellos sent, waiting for every team member's
    SOLVING = "solving"
    DONE = "done"  # every stage ran (converged or not: see TeamRobot.converged)
    ABORTING = "aborting"  # a team member vanished; agreeing with the survivors where to stop
    ABORTED = "aborted"  # ended at the last consistent position
    FAILED = "failed"  # the team cannot solve (disconnected, robots disagree on separators)


def stage_of(linearisation: int) -> Stage:
    return "rotation" if linearisation == 0 else "pose"


@dataclass(frozen=True)
class Hello:
    """A robot's greeting: its separator count with each robot it shares separators with."""

    solve_id: int
    sender: int
    receiver: int
    separators: Mapping[int, int]


@dataclass(frozen=True)
class Turn:
    """What one robot tells one team member after one of its steps.

    The report (``solved``, ``change``) goes to every team member, for the turn
    order and the stopping rule; ``message`` (the separator estimates) only to a
    neighbour, and only when the sender solved.
    """

    solve_id: int
    sender: int
    receiver: int
    linearisation: int
    iteration: int
    solved: bool
    change: float
    message: DgsMessage | None = None

    @property
    def stage(self) -> Stage:
        return stage_of(self.linearisation)

    @property
    def position(self) -> Position:
        return (self.linearisation, self.iteration)


@dataclass(frozen=True)
class Abort:
    """A survivor's word that robots ``vanished``; ``consistent`` is the last position every
    robot of the team completed as far as the sender knows."""

    solve_id: int
    sender: int
    receiver: int
    vanished: tuple[int, ...]
    consistent: Position
    reason: str


@dataclass
class _Stage:
    linearisation: int
    max_change: list[float] = field(default_factory=list)
    floats: int = 0


class TeamRobot:
    """One robot's side of a live solve; see the module docstring.

    ``team`` is every robot of the solve (this one included); ``anchor_robot``
    holds the anchor (its problem must have it). The caller sends what
    :meth:`start`, :meth:`step`, :meth:`vanish` and :meth:`receive_abort` return,
    feeds what arrives to the ``receive_*`` methods, calls :meth:`step` whenever
    :meth:`ready` and :meth:`advance` after each step and each arrival.
    """

    def __init__(
        self,
        problem: LocalProblem,
        team: Iterable[int],
        settings: DgsSettings,
        solve_id: int,
        *,
        anchor_robot: int = 0,
    ) -> None:
        self.team = tuple(sorted(set(team)))
        self.robot = problem.robot
        if self.robot not in self.team or anchor_robot not in self.team:
            raise GraphError(
                f"robot {self.robot} and anchor robot {anchor_robot} must be in the team {self.team}"
            )
        strangers = sorted(set(problem.neighbours) - set(self.team))
        if strangers:
            raise GraphError(f"robot {self.robot} has separators with robots {strangers}, not in the team")
        if (problem.anchor is not None) != (self.robot == anchor_robot):
            raise GraphError(f"robot {anchor_robot} and only it must hold the anchor")
        self.problem = problem
        self.settings = settings
        self.solve_id = solve_id
        self.anchor_robot = anchor_robot
        self.agent = DgsAgent(problem, gamma=settings.over_relaxation)
        self.phase = Phase.GREETING
        self.reason = ""
        self.order: tuple[int, ...] = ()
        self.linearisation = 0
        self.iteration = 0  # this robot's last step in the current stage
        self._hellos: dict[int, Mapping[int, int]] = {self.robot: self.separator_counts()}
        self._reports: dict[Position, dict[int, tuple[bool, float]]] = {}
        self._inbox: dict[tuple[int, int, int], DgsMessage] = {}
        self._stage = _Stage(0)
        self._judged: Position = (0, 0)  # the last iteration the stopping rule was applied to
        self.stages: list[StageSummary] = []
        self.reports: list[StepReport] = []  # own, in order
        self.sent: list[DgsMessage] = []  # own estimates, in order
        self._snapshots: dict[Position, dict[int, Pose]] = {(0, 0): dict(problem.poses)}
        self.vanished: set[int] = set()
        self._aborts: dict[int, Position] = {}
        self.consistent: Position | None = None

    # ------------------------------------------------------------------ state
    def separator_counts(self) -> dict[int, int]:
        """Separators this robot shares with each neighbour (what its hello says)."""
        counts: dict[int, int] = {}
        for edge in self.problem.separators:
            other = edge.other(next(k for k in edge.keys if k in self.problem.poses))
            robot = next(r for r, ks in self.problem.neighbour_keys.items() if other in ks)
            counts[robot] = counts.get(robot, 0) + 1
        return dict(sorted(counts.items()))

    @property
    def finished(self) -> bool:
        return self.phase in (Phase.DONE, Phase.ABORTED, Phase.FAILED)

    @property
    def converged(self) -> bool:
        """Every stage met its eta (only when DONE)."""
        return self.phase is Phase.DONE and all(s.converged for s in self.stages)

    @property
    def position(self) -> Position:
        """This robot's last step: (linearisation, iteration)."""
        return (self.linearisation, self.iteration)

    @property
    def others(self) -> tuple[int, ...]:
        return tuple(r for r in self.team if r != self.robot)

    def survivors(self) -> tuple[int, ...]:
        return tuple(r for r in self.others if r not in self.vanished)

    def estimate(self) -> tuple[Position, dict[int, Pose]]:
        """The robot's answer: its final estimate (DONE), its estimate at the agreed last
        consistent position (ABORTED), else its estimate now."""
        if self.phase is Phase.ABORTED and self.consistent is not None:
            return self.consistent, dict(self._snapshots[self.consistent])
        if self.phase is Phase.FAILED:
            return (0, 0), dict(self._snapshots[(0, 0)])
        return self.position, self.agent.estimate()

    def waiting_for(self) -> tuple[int, ...]:
        """The robots whose message this robot waits for now (who is silent, when it lasts)."""
        if self.phase is Phase.GREETING:
            return tuple(r for r in self.others if r not in self._hellos)
        if self.phase is Phase.ABORTING:
            return tuple(r for r in self.survivors() if r not in self._aborts)
        if self.phase is not Phase.SOLVING:
            return ()
        missing = self._missing((self.linearisation, self.iteration), self.team)
        if self.iteration > 0 and missing:
            return missing
        if self.settings.mode == "gauss-seidel":
            before = self.order[: self.order.index(self.robot)]
            return self._missing((self.linearisation, self.iteration + 1), before)
        return ()

    def _missing(self, position: Position, robots: Iterable[int]) -> tuple[int, ...]:
        heard = self._reports.get(position, {})
        return tuple(r for r in robots if r not in heard)

    # ---------------------------------------------------------------- greeting
    def start(self) -> list[Hello]:
        """The hellos to send every other team member."""
        counts = MappingProxyType(self._hellos[self.robot])
        hellos = [Hello(self.solve_id, self.robot, r, counts) for r in self.others]
        self._after_hello()
        return hellos

    def receive_hello(self, hello: Hello) -> None:
        """Take a team member's hello; TurnRejected when it does not fit."""
        self._check_envelope(hello.solve_id, hello.sender, hello.receiver)
        if hello.sender in self._hellos:
            raise TurnRejected("duplicate", f"robot {hello.sender} already greeted robot {self.robot}")
        counts = dict(hello.separators)
        strangers = sorted(r for r in counts if r not in self.team or r == hello.sender)
        if strangers or any(n < 1 for n in counts.values()):
            raise TurnRejected(
                "bad_hello", f"robot {hello.sender}'s hello counts separators with robots {sorted(counts)}"
            )
        mine = self._hellos[self.robot].get(hello.sender, 0)
        if counts.get(self.robot, 0) != mine:
            raise TurnRejected(
                "bad_hello",
                f"robot {hello.sender} says it shares {counts.get(self.robot, 0)} separators with robot "
                f"{self.robot}, whose own file has {mine}",
            )
        self._hellos[hello.sender] = counts
        self._after_hello()

    def _after_hello(self) -> None:
        if self.phase is not Phase.GREETING or len(self._hellos) < len(self.team):
            return
        pairs: dict[tuple[int, int], int] = {}
        for robot, counts in self._hellos.items():
            for other, n in counts.items():
                pair = (min(robot, other), max(robot, other))
                if pairs.setdefault(pair, n) != n or self._hellos[other].get(robot) != n:
                    self._fail(
                        f"robots {pair[0]} and {pair[1]} disagree on their separators ("
                        f"{self._hellos[pair[0]].get(pair[1], 0)} vs {self._hellos[pair[1]].get(pair[0], 0)})"
                    )
                    return
        reached = {self.anchor_robot}
        frontier = [self.anchor_robot]
        while frontier:
            r = frontier.pop()
            for other in self._hellos[r]:
                if other not in reached:
                    reached.add(other)
                    frontier.append(other)
        apart = sorted(set(self.team) - reached)
        if apart:
            self._fail(
                f"robots {apart} share no chain of separators with robot {self.anchor_robot}, the anchor's"
            )
            return
        self.order = order_robots(self.team, pairs, first=self.anchor_robot, method=self.settings.order)
        self.phase = Phase.SOLVING

    def _fail(self, reason: str) -> None:
        self.phase = Phase.FAILED
        self.reason = reason

    # ------------------------------------------------------------------ turns
    def _check_envelope(self, solve_id: int, sender: int, receiver: int) -> None:
        if solve_id != self.solve_id:
            raise TurnRejected(
                "other_solve", f"solve {solve_id} is not robot {self.robot}'s solve {self.solve_id}"
            )
        if receiver != self.robot or sender not in self.team or sender == self.robot:
            raise TurnRejected(
                "not_in_team",
                f"from robot {sender} to robot {receiver}: not robot {self.robot}'s team {self.team}",
            )
        if sender in self.vanished:
            raise TurnRejected("vanished", f"robot {sender} was declared gone")
        if self.phase in (Phase.DONE, Phase.ABORTED, Phase.FAILED):
            raise TurnRejected("finished", f"robot {self.robot}'s solve {self.solve_id} is over")

    def _window(self) -> tuple[Position, ...]:
        """The positions another robot may report next (see the module docstring)."""
        lin, k = self.linearisation, self.iteration
        window = [(lin, k + 1)] if k + 1 <= self.settings.max_iterations else []
        if k >= 1:
            window.append((lin, k))
            if lin < self.settings.pose_linearisations:
                window.append((lin + 1, 1))
        return tuple(window)

    def receive_turn(self, turn: Turn) -> None:
        """Keep a team member's report and estimates; TurnRejected when they do not fit."""
        self._check_envelope(turn.solve_id, turn.sender, turn.receiver)
        if self.phase is Phase.ABORTING:
            raise TurnRejected(
                "finished", f"robot {self.robot} is ending solve {self.solve_id} (a robot vanished)"
            )
        if not 0 <= turn.linearisation <= self.settings.pose_linearisations or turn.iteration < 1:
            raise TurnRejected(
                "wrong_stage",
                f"{turn.stage} stage, linearisation {turn.linearisation}, iteration {turn.iteration} "
                f"is no position of this solve ({self.settings.pose_linearisations} pose stages)",
            )
        if turn.position not in self._window():
            lin = self.linearisation
            reason = "wrong_stage" if turn.linearisation != lin else "out_of_turn"
            raise TurnRejected(
                reason,
                f"robot {self.robot} is at linearisation {lin}, iteration {self.iteration}; robot "
                f"{turn.sender} cannot send linearisation {turn.linearisation}, "
                f"iteration {turn.iteration} now",
            )
        if turn.sender in self._reports.get(turn.position, {}):
            raise TurnRejected(
                "duplicate",
                f"robot {turn.sender} already reported linearisation {turn.linearisation}, "
                f"iteration {turn.iteration}",
            )
        if math.isnan(turn.change) or turn.change < 0 or turn.solved != math.isfinite(turn.change):
            raise TurnRejected(
                "bad_report",
                f"change {turn.change} does not fit solved={turn.solved} (finite >= 0 iff solved)",
            )
        expected = self.agent.expected_keys(turn.sender)
        message = turn.message
        if message is not None:
            if not expected:
                raise TurnRejected(
                    "not_shared", f"robot {turn.sender} shares no separator with robot {self.robot}"
                )
            keys = set(message.estimates)
            extra = sorted(keys - set(expected))
            if extra:
                raise TurnRejected(
                    "not_shared",
                    f"robot {turn.sender} sent estimates of {[describe_key(k) for k in extra[:5]]}, "
                    f"which it does not share with robot {self.robot}",
                )
            same = (message.sender, message.receiver, message.linearisation, message.iteration) == (
                turn.sender,
                turn.receiver,
                turn.linearisation,
                turn.iteration,
            )
            if not same or message.stage != turn.stage:
                raise TurnRejected("wrong_stage", "the estimates' stage or iteration is not the report's")
        if turn.solved and expected and (message is None or set(message.estimates) != set(expected)):
            raise TurnRejected(
                "missing_estimates",
                f"robot {turn.sender} solved but sent {0 if message is None else len(message.estimates)} "
                f"of the {len(expected)} estimates it shares with robot {self.robot}",
            )
        if message is not None and not turn.solved:
            raise TurnRejected("bad_report", f"robot {turn.sender} did not solve but sent estimates")
        self._reports.setdefault(turn.position, {})[turn.sender] = (turn.solved, turn.change)
        if message is not None:
            self._inbox[(turn.linearisation, turn.iteration, turn.sender)] = message

    # ------------------------------------------------------------------ steps
    def ready(self) -> bool:
        """Whether this robot may take its next step now."""
        if self.phase is not Phase.SOLVING:
            return False
        lin, k = self.linearisation, self.iteration
        if k >= 1 and self._missing((lin, k), self.team):
            return False
        if k >= self.settings.max_iterations:
            return False  # advance() ends the stage
        if self.settings.mode == "gauss-seidel":
            before = self.order[: self.order.index(self.robot)]
            return not self._missing((lin, k + 1), before)
        return True

    def _deliver(self, upto: int, before: Sequence[int]) -> None:
        """Give the agent the current stage's buffered estimates of iterations < ``upto``, and of
        ``upto`` from the robots in ``before``, oldest first."""
        lin = self.linearisation
        due = sorted(
            (k, s)
            for (stage, k, s) in self._inbox
            if stage == lin and (k < upto or (k == upto and s in before))
        )
        for k, s in due:
            self.agent.receive(self._inbox.pop((lin, k, s)))

    def step(self) -> list[Turn]:
        """Take the next step (only when :meth:`ready`); the turns to send every other team member."""
        if not self.ready():
            raise GraphError(
                f"robot {self.robot} is not ready to step (at {self.position}, {self.phase.value})"
            )
        k = self.iteration + 1
        before = self.order[: self.order.index(self.robot)] if self.settings.mode == "gauss-seidel" else ()
        self._deliver(k, before)
        report = self.agent.step(k)
        self.iteration = k
        self.reports.append(report)
        self.sent.extend(report.messages)
        self._stage.floats += sum(m.floats for m in report.messages)
        self._reports.setdefault(self.position, {})[self.robot] = (report.solved, report.change)
        self._snapshots[self.position] = self.agent.estimate()
        for old in sorted(self._snapshots)[1:-KEPT_SNAPSHOTS]:
            del self._snapshots[old]
        messages = {m.receiver: m for m in report.messages}
        return [
            Turn(
                self.solve_id,
                self.robot,
                r,
                self.linearisation,
                k,
                report.solved,
                report.change,
                messages.get(r),
            )
            for r in self.others
        ]

    def advance(self) -> bool:
        """End the current stage when its last iteration is complete (every report in) and the
        stopping rule or max_iterations says so; True when a stage ended."""
        if self.phase is not Phase.SOLVING or self.iteration == 0 or self._judged == self.position:
            return False
        lin, k = self.position
        heard = self._reports.get((lin, k), {})
        if len(heard) < len(self.team):
            return False
        self._judged = self.position
        reports = [StepReport(r, stage_of(lin), lin, k, heard[r][0], heard[r][1], ()) for r in self.order]
        self._stage.max_change.append(max(r.change for r in reports))
        eta = self.settings.eta_rotation if lin == 0 else self.settings.eta_pose
        min_iterations = 1 if lin > 1 else 2
        converged = stage_converged(reports, eta, min_iterations=min_iterations)
        if not converged and k < self.settings.max_iterations:
            return False
        self.stages.append(
            StageSummary(stage_of(lin), lin, k, converged, tuple(self._stage.max_change), self._stage.floats)
        )
        # The stage's last estimates (a neighbour after this robot in the order sent them
        # after this robot's last step) reach the agent before the stage closes.
        self._deliver(k + 1, ())
        if lin == self.settings.pose_linearisations:
            self.phase = Phase.DONE
            if not all(math.isfinite(v) for p in self.agent.estimate().values() for v in p.translation):
                self._fail(
                    "the distributed solve diverged (non-finite estimate); try gauss-seidel or gamma < 1"
                )
            return True
        self.agent.begin_pose_stage()
        self.linearisation, self.iteration = lin + 1, 0
        self._stage = _Stage(lin + 1)
        return True

    # ------------------------------------------------------------------ abort
    def _complete(self) -> Position:
        """The last position every team member reported: after a stage ended, its last
        iteration until the next stage's first is complete."""
        done = [p for p, heard in self._reports.items() if len(heard) == len(self.team)]
        return max(done, default=(0, 0))

    def vanish(self, robots: Iterable[int], reason: str) -> list[Abort]:
        """Team members ``robots`` are gone: end the solve with the survivors. Returns the aborts
        to send them (empty when this robot was already ending or finished)."""
        gone = {r for r in robots if r in self.team and r != self.robot}
        if not gone or self.finished:
            return []
        new = gone - self.vanished
        self.vanished |= gone
        if self.phase is Phase.ABORTING:
            for r in new:
                self._aborts.pop(r, None)
            self._settle()
            return []
        self.phase = Phase.ABORTING
        self.reason = reason
        own = self._complete()
        self._aborts = {self.robot: own}
        aborts = [
            Abort(self.solve_id, self.robot, r, tuple(sorted(self.vanished)), own, reason)
            for r in self.survivors()
        ]
        self._settle()
        return aborts

    def receive_abort(self, abort: Abort) -> list[Abort]:
        """A survivor's abort; the aborts this robot sends in turn (when it was not ending yet)."""
        if abort.solve_id != self.solve_id:
            raise TurnRejected(
                "other_solve", f"solve {abort.solve_id} is not robot {self.robot}'s solve {self.solve_id}"
            )
        if abort.receiver != self.robot or abort.sender not in self.team or abort.sender == self.robot:
            raise TurnRejected("not_in_team", f"abort from robot {abort.sender} to robot {abort.receiver}")
        if self.finished:
            raise TurnRejected("finished", f"robot {self.robot}'s solve {self.solve_id} is over")
        if abort.sender in self.vanished:
            raise TurnRejected("vanished", f"robot {abort.sender} was declared gone")
        lin, k = abort.consistent
        if not (0 <= lin <= self.settings.pose_linearisations and 0 <= k <= self.settings.max_iterations):
            raise TurnRejected("wrong_stage", f"abort names position {abort.consistent}, none of this solve")
        out: list[Abort] = []
        if self.phase is not Phase.ABORTING:
            reason = f"robot {abort.sender} ended the solve: {abort.reason}"
            out = self.vanish(abort.vanished, reason) or self._join_abort(abort, reason)
        self._aborts[abort.sender] = abort.consistent
        self._settle()
        return out

    def _join_abort(self, abort: Abort, reason: str) -> list[Abort]:
        # The named robots were already known gone here (no new vanish): abort all the same.
        self.phase = Phase.ABORTING
        self.reason = reason
        own = self._complete()
        self._aborts = {self.robot: own}
        return [
            Abort(self.solve_id, self.robot, r, tuple(sorted(self.vanished)), own, reason)
            for r in self.survivors()
        ]

    def _settle(self) -> None:
        if self.phase is Phase.ABORTING and all(r in self._aborts for r in self.survivors()):
            self.end_abort()

    def end_abort(self) -> None:
        """End at the earliest position any survivor named (those still silent count as gone)."""
        if self.phase is not Phase.ABORTING:
            return
        silent = [r for r in self.survivors() if r not in self._aborts]
        self.vanished |= set(silent)
        position = min(self._aborts.values())
        if position not in self._snapshots:
            position = max(p for p in self._snapshots if p <= position)
        self.consistent = position
        self.phase = Phase.ABORTED
        gone = ", ".join(map(str, sorted(self.vanished)))
        self.reason = (
            f"{self.reason}; robots gone: {gone}; ended at linearisation {position[0]}, iteration "
            f"{position[1]} (the last every robot completed)"
        )
