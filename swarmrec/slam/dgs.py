"""The distributed two-stage Gauss-Seidel, run in process: :func:`solve_distributed`.

Choudhary et al. (ICRA 2016, reference [3] of the object-based SLAM paper)
estimate a multi-robot pose graph in two stages, each solved by a
distributed iterative method in which a robot only talks to the robots it
shares separators with: (1) rotations by chordal relaxation, (2) full poses
from one linearisation around the stage-1 rotations. This driver creates one
:class:`~swarmrec.slam.agent.DgsAgent` per robot, runs the stages as
synchronous rounds, delivers every message between agents and records it, so
a transport that carries the same messages (a Zenoh service wrapping the same
agent) can be checked against it message for message.

Modes. ``gauss-seidel``: robots take turns in :func:`~swarmrec.slam.ordering.order_robots`'s
order, each using its neighbours' newest estimates, those sent earlier in the
same iteration included (successive over-relaxation with ``gamma != 1``).
``jacobi``: every robot solves with the estimates of the previous iteration and
all messages are delivered at its end (Jacobi over-relaxation with ``gamma != 1``).

Stopping rule (per stage, as the public implementation): after iteration
``k`` every robot has solved, and the largest change over the robots,
``max_r ||x_r(k) - x_r(k-1)||`` (Euclidean norm over all of robot ``r``'s free
variables, 9 per rotation or 6 per pose update, solution before
over-relaxation), is below eta; never after the first iteration of a stage that
starts from flagged initialisation (its change is measured from an arbitrary
start), possibly after the first of a relinearised pose stage. A stage that
hits ``max_iterations`` ends unconverged and the next one starts anyway.

Pose stages. ``pose_linearisations = 1`` is the paper's method. Each further
one relinearises at the previous result (a distributed Gauss-Newton step on
the separable SO(3) x R^3 cost); the first relinearisation brings the estimate
within millimetres of gtsam's Gauss-Newton optimum on the shared data sets,
where the single linearisation stays decimetres away (``docs/slam.md``).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from swarmrec.errors import ConfigError
from swarmrec.slam.agent import DgsAgent, LocalProblem
from swarmrec.slam.errors import GraphError
from swarmrec.slam.graph import PoseGraph
from swarmrec.slam.lie import Pose
from swarmrec.slam.messages import DgsMessage, Stage, StepReport
from swarmrec.slam.ordering import ORDERINGS, Ordering, order_robots

__all__ = [
    "DEFAULT_ETA",
    "DEFAULT_GAMMA",
    "DEFAULT_LINEARISATIONS",
    "MODES",
    "DgsSettings",
    "DistributedResult",
    "Mode",
    "StageSummary",
    "TraceEntry",
    "make_agents",
    "run_dgs",
    "solve_distributed",
    "stage_converged",
]

Mode = Literal["gauss-seidel", "jacobi"]
MODES: tuple[Mode, ...] = ("gauss-seidel", "jacobi")


# swarmrec's defaults (``docs/slam.md``): successive over-relaxation, a tighter eta than the
# paper's and one relinearisation. On the shared data sets and the simulated worlds they bring the
# estimate within centimetres of gtsam's Gauss-Newton in about a hundred iterations, where the
# paper's settings stop within ten iterations but decimetres away (Gauss-Seidel's rate there is 0.97
# to 0.997 per iteration, so a small change is not yet a small error).
DEFAULT_GAMMA = 1.9
DEFAULT_ETA = 1e-2
DEFAULT_LINEARISATIONS = 2


@dataclass(frozen=True)
class DgsSettings:
    """Settings of the distributed solve (defaults: swarmrec's; :meth:`paper` for the paper's).

    - ``mode``: ``gauss-seidel`` (robots in turn, newest estimates) or ``jacobi`` (all at once).
    - ``order``: ``flagged`` (the public implementation's), ``greedy`` or ``natural``
      (:mod:`swarmrec.slam.ordering`); only Gauss-Seidel depends on it.
    - ``gamma``: over-relaxation factor in (0, 2); 1 is plain Gauss-Seidel/Jacobi; None takes
      the mode's default (:attr:`over_relaxation`). With Gauss-Seidel every value in (0, 2)
      converges on these symmetric positive definite systems (Ostrowski-Reich); Jacobi
      over-relaxation has no such guarantee and diverges at 1.9 on the test graphs.
    - ``eta_rotation``, ``eta_pose``: stopping thresholds on the largest change (paper: 0.1 or 0.01).
    - ``max_iterations``: per stage.
    - ``pose_linearisations``: pose stages (1 is the paper's method; 2 adds one relinearisation).
    """

    mode: Mode = "gauss-seidel"
    order: Ordering = "flagged"
    gamma: float | None = None
    eta_rotation: float = DEFAULT_ETA
    eta_pose: float = DEFAULT_ETA
    max_iterations: int = 1000
    pose_linearisations: int = DEFAULT_LINEARISATIONS

    @property
    def over_relaxation(self) -> float:
        """``gamma``, or the mode's default: 1.9 for Gauss-Seidel, 1 for Jacobi."""
        if self.gamma is not None:
            return self.gamma
        return DEFAULT_GAMMA if self.mode == "gauss-seidel" else 1.0

    @staticmethod
    def paper(eta: float = 1e-1) -> DgsSettings:
        """The paper's method: plain Gauss-Seidel, one linearisation, eta 0.1 (or 0.01)."""
        return DgsSettings(gamma=1.0, eta_rotation=eta, eta_pose=eta, pose_linearisations=1)

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ConfigError(f"mode must be one of {MODES}, got {self.mode!r}")
        if self.order not in ORDERINGS:
            raise ConfigError(f"order must be one of {ORDERINGS}, got {self.order!r}")
        if self.gamma is not None and not 0.0 < self.gamma < 2.0:
            raise ConfigError(f"gamma (over-relaxation) must be in (0, 2), got {self.gamma}")
        for name in ("eta_rotation", "eta_pose"):
            value = getattr(self, name)
            if not value > 0.0:
                raise ConfigError(f"{name} must be positive, got {value}")
        if self.max_iterations < 1:
            raise ConfigError(f"max_iterations must be at least 1, got {self.max_iterations}")
        if self.pose_linearisations < 1:
            raise ConfigError(f"pose_linearisations must be at least 1, got {self.pose_linearisations}")


def stage_converged(reports: Sequence[StepReport], eta: float, *, min_iterations: int) -> bool:
    """The stopping rule for one iteration's reports (every robot solved, every change below eta)."""
    if not reports or reports[0].iteration < min_iterations:
        return False
    return all(r.solved and r.change < eta for r in reports)


@dataclass(frozen=True)
class StageSummary:
    """One stage: iterations, whether it met its eta, each iteration's largest change, floats sent."""

    stage: Stage
    linearisation: int
    iterations: int
    converged: bool
    max_change: tuple[float, ...]
    floats: int


@dataclass(frozen=True)
class TraceEntry:
    """The team's merged estimate after one iteration (recorded with ``trace=True``)."""

    stage: Stage
    linearisation: int
    iteration: int
    poses: dict[int, Pose]


@dataclass(frozen=True)
class DistributedResult:
    """The distributed estimate and everything needed to check or replay the run.

    ``messages`` is every message in the order it was sent; ``reports`` every
    agent's step report in the order of the steps.
    """

    poses: dict[int, Pose]
    order: tuple[int, ...]
    settings: DgsSettings
    anchor: int
    stages: tuple[StageSummary, ...]
    messages: tuple[DgsMessage, ...]
    reports: tuple[StepReport, ...]
    trace: tuple[TraceEntry, ...]

    @property
    def rotation_iterations(self) -> int:
        return sum(s.iterations for s in self.stages if s.stage == "rotation")

    @property
    def pose_iterations(self) -> tuple[int, ...]:
        """Iterations of each pose stage."""
        return tuple(s.iterations for s in self.stages if s.stage == "pose")

    @property
    def total_iterations(self) -> int:
        return sum(s.iterations for s in self.stages)

    @property
    def converged(self) -> bool:
        return all(s.converged for s in self.stages)

    @property
    def total_floats(self) -> int:
        return sum(m.floats for m in self.messages)

    def floats_per_link(self) -> dict[tuple[int, int], int]:
        """Floats sent over each directed link ``(sender, receiver)`` during the whole solve."""
        counts: Counter[tuple[int, int]] = Counter()
        for m in self.messages:
            counts[(m.sender, m.receiver)] += m.floats
        return dict(sorted(counts.items()))

    def floats_per_iteration(self) -> list[dict[tuple[int, int], int]]:
        """Floats per directed link in each iteration, stages one after the other."""
        per: dict[tuple[Stage, int, int], Counter[tuple[int, int]]] = {}
        for m in self.messages:
            per.setdefault((m.stage, m.linearisation, m.iteration), Counter())[(m.sender, m.receiver)] += (
                m.floats
            )
        return [dict(sorted(c.items())) for _, c in sorted(per.items(), key=lambda kv: (kv[0][1], kv[0][2]))]


def make_agents(graph: PoseGraph, *, anchor: int | None = None, gamma: float = 1.0) -> dict[int, DgsAgent]:
    """One agent per robot of ``graph``; the owner of ``anchor`` (default: robot 0's first key) holds it."""
    robots = graph.robots
    if len(robots) < 1 or len(graph.poses) < 2:
        raise GraphError("a distributed solve needs robot keys (Symbols) and at least two vertices")
    unowned = [k for k in graph.keys if k not in {k2 for r in robots for k2 in graph.robot_keys(r)}]
    if unowned:
        raise GraphError(
            f"{len(unowned)} keys belong to no robot, e.g. {unowned[0]} (keys must be robot Symbols)"
        )
    if not graph.is_connected():
        raise GraphError("the team's pose graph is not connected: some robots share no frame with the anchor")
    anchor = graph.anchor_key() if anchor is None else anchor
    if anchor not in graph.poses:
        raise GraphError(f"anchor {anchor} is not a vertex of the graph")
    return {r: DgsAgent(LocalProblem.from_graph(graph, r, anchor=anchor), gamma=gamma) for r in robots}


def _merged(agents: Mapping[int, DgsAgent]) -> dict[int, Pose]:
    merged: dict[int, Pose] = {}
    for agent in agents.values():
        merged.update(agent.estimate())
    return merged


def _run_stage(
    agents: Mapping[int, DgsAgent],
    order: Sequence[int],
    settings: DgsSettings,
    eta: float,
    messages: list[DgsMessage],
    reports: list[StepReport],
    trace: list[TraceEntry] | None,
) -> StageSummary:
    first = agents[order[0]]
    stage, linearisation = first.stage, first.linearisation
    min_iterations = 1 if stage == "pose" and linearisation > 1 else 2
    max_change: list[float] = []
    floats = 0
    converged = False
    iteration = 0
    for iteration in range(1, settings.max_iterations + 1):
        round_reports: list[StepReport] = []
        pending: list[DgsMessage] = []
        for robot in order:
            report = agents[robot].step(iteration)
            round_reports.append(report)
            if settings.mode == "gauss-seidel":
                for message in report.messages:
                    agents[message.receiver].receive(message)
            else:
                pending.extend(report.messages)
        for message in pending:
            agents[message.receiver].receive(message)
        for report in round_reports:
            messages.extend(report.messages)
            floats += sum(m.floats for m in report.messages)
        reports.extend(round_reports)
        max_change.append(max(r.change for r in round_reports))
        if trace is not None:
            trace.append(TraceEntry(stage, linearisation, iteration, _merged(agents)))
        if stage_converged(round_reports, eta, min_iterations=min_iterations):
            converged = True
            break
    return StageSummary(stage, linearisation, iteration, converged, tuple(max_change), floats)


def run_dgs(
    graph: PoseGraph,
    settings: DgsSettings,
    *,
    order: Sequence[int] | None = None,
    anchor: int | None = None,
    trace: bool = False,
) -> DistributedResult:
    """Run the distributed two-stage Gauss-Seidel on ``graph`` with one in-process agent per robot.

    ``order`` overrides ``settings.order`` with an explicit sequence of every
    robot. ``trace`` records the merged estimate after every iteration (for
    studies of accuracy against iterations; it costs a copy each time).
    """
    agents = make_agents(graph, anchor=anchor, gamma=settings.over_relaxation)
    anchor_key = graph.anchor_key() if anchor is None else anchor
    if order is None:
        sequence = order_robots(
            agents, graph.separator_counts(), first=graph.robot_of(anchor_key), method=settings.order
        )
    else:
        sequence = tuple(order)
        if sorted(sequence) != sorted(agents):
            raise ConfigError(f"order {list(sequence)} must list every robot {sorted(agents)} once")
    messages: list[DgsMessage] = []
    reports: list[StepReport] = []
    entries: list[TraceEntry] | None = [] if trace else None
    stages = [_run_stage(agents, sequence, settings, settings.eta_rotation, messages, reports, entries)]
    for _ in range(settings.pose_linearisations):
        for agent in agents.values():
            agent.begin_pose_stage()
        stages.append(_run_stage(agents, sequence, settings, settings.eta_pose, messages, reports, entries))
    poses = _merged(agents)
    if not all(np.all(np.isfinite(p.translation)) for p in poses.values()):
        raise GraphError(
            "the distributed solve diverged (non-finite estimate); try gauss-seidel or gamma < 1"
        )
    return DistributedResult(
        poses,
        sequence,
        settings,
        anchor_key,
        tuple(stages),
        tuple(messages),
        tuple(reports),
        tuple(entries or ()),
    )


def solve_distributed(
    graph: PoseGraph,
    *,
    order: Ordering | Sequence[int] = "flagged",
    mode: Mode = "gauss-seidel",
    gamma: float | None = None,
    eta_rotation: float = DEFAULT_ETA,
    eta_pose: float = DEFAULT_ETA,
    max_iterations: int = 1000,
    pose_linearisations: int = DEFAULT_LINEARISATIONS,
    anchor: int | None = None,
    trace: bool = False,
) -> DistributedResult:
    """:func:`run_dgs` with the settings given one by one (``order``: a name or a robot sequence)."""
    named: Ordering = order if isinstance(order, str) else "flagged"
    settings = DgsSettings(mode, named, gamma, eta_rotation, eta_pose, max_iterations, pose_linearisations)
    return run_dgs(
        graph, settings, order=None if isinstance(order, str) else order, anchor=anchor, trace=trace
    )
