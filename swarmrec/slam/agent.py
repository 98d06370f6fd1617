"""One robot's part of the distributed two-stage Gauss-Seidel: :class:`DgsAgent`.

An agent holds only its :class:`LocalProblem`: its own vertices and edges and
its separators (edges to a neighbour's key). It never sees a neighbour's
graph, only the estimates of the neighbour's separator keys that arrive in
:class:`~swarmrec.slam.messages.DgsMessage`. Each :meth:`DgsAgent.step` solves
the robot's local linear system with the neighbours' latest estimates held
fixed and returns the messages carrying its own new separator estimates.

The agent runs a sequence of *stages*, each a Gauss-Seidel loop that the
caller ends (see :mod:`swarmrec.slam.dgs` for the stopping rule):

1. ``rotation`` (linearisation 0): chordal relaxation, 9 floats per separator key;
2. ``pose`` linearisation 1: poses linearised at the projected stage-1
   rotations and zero translations, 6 floats per key (the paper's stage 2);
3. ``pose`` linearisations 2, 3, ...: optional relinearisations at the previous
   pose stage's result (:meth:`DgsAgent.begin_pose_stage` again).

Moving to a pose stage needs no communication: each agent projects or
retracts its copies of the neighbours' last estimates exactly as their owners
do, so both ends of a separator linearise at the same point.

Flagged initialisation (stage 1 and the first pose stage): a separator is used
only once the neighbour has sent an estimate in the current stage, so no one
solves against a neighbour's meaningless starting value; a robot with neither
the anchor nor an estimated neighbour waits. In the relinearised pose stages
every neighbour's update starts at zero, a meaningful value (its last
estimate), so every separator is used from the first iteration.

Over-relaxation: from an agent's second solve in a stage on, its estimate
moves to ``(1 - gamma) x_old + gamma x_solved``; its first solve is taken as is.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType

import numpy as np

from swarmrec.slam.errors import GraphError, MessageError
from swarmrec.slam.g2o import read_robot_file
from swarmrec.slam.graph import Edge, PoseGraph
from swarmrec.slam.keys import describe_key, robot_of_key
from swarmrec.slam.lie import FloatArray, Pose, project_to_so3
from swarmrec.slam.messages import DgsMessage, Stage, StepReport
from swarmrec.slam.two_stage import (
    BlockSystem,
    pose_system,
    retract,
    rotation_system,
    rotation_vector,
    solve_pose_updates,
    solve_rotations,
)

__all__ = ["DgsAgent", "LocalProblem"]


def _canonical(edges: Iterable[Edge]) -> tuple[Edge, ...]:
    return tuple(sorted(edges, key=lambda e: e.keys))


def _owner(key: int) -> int:
    robot = robot_of_key(key)
    if robot is None:
        raise GraphError(f"key {describe_key(key)} belongs to no robot (not a robot Symbol)")
    return robot


@dataclass(frozen=True)
class LocalProblem:
    """What one robot knows: its vertices (initial estimates), its edges, its separators, maybe the anchor.

    ``anchor`` is one of the robot's own keys, held at its initial pose, when
    this robot fixes the team's gauge (robot 0's first pose by default).

    Vertices are kept by key and edges in a canonical order (by their keys,
    ties in the given order): the normal equations are sums over edges, and a
    robot that reads its own g2o file (:meth:`from_robot_file`, where its
    separators come in its file's order) must build bit for bit the system that
    a driver partitioning the team's graph (:meth:`from_graph`) builds.
    """

    robot: int
    poses: Mapping[int, Pose]
    edges: tuple[Edge, ...]
    separators: tuple[Edge, ...]
    anchor: int | None = None
    shared: Mapping[int, tuple[int, ...]] = field(init=False)
    neighbour_keys: Mapping[int, tuple[int, ...]] = field(init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "poses", MappingProxyType(dict(sorted(self.poses.items()))))
        object.__setattr__(self, "edges", _canonical(self.edges))
        object.__setattr__(self, "separators", _canonical(self.separators))
        for key in self.poses:
            if _owner(key) != self.robot:
                raise GraphError(
                    f"robot {self.robot} holds {describe_key(key)}, a key of robot {_owner(key)}"
                )
        for edge in self.edges:
            if any(k not in self.poses for k in edge.keys):
                raise GraphError(
                    f"edge {describe_key(edge.source)}-{describe_key(edge.target)} is not "
                    f"between two of robot {self.robot}'s keys"
                )
        shared: dict[int, set[int]] = {}
        neighbour: dict[int, set[int]] = {}
        for edge in self.separators:
            mine = [k for k in edge.keys if k in self.poses]
            if len(mine) != 1:
                raise GraphError(
                    f"separator {describe_key(edge.source)}-{describe_key(edge.target)} must join "
                    f"one of robot {self.robot}'s keys to another robot's"
                )
            other = edge.other(mine[0])
            robot = _owner(other)
            if robot == self.robot:
                raise GraphError(
                    f"{describe_key(other)} is robot {self.robot}'s own key but not one of its vertices"
                )
            shared.setdefault(robot, set()).add(mine[0])
            neighbour.setdefault(robot, set()).add(other)
        if self.anchor is not None and self.anchor not in self.poses:
            raise GraphError(f"anchor {describe_key(self.anchor)} is not one of robot {self.robot}'s keys")
        object.__setattr__(self, "shared", MappingProxyType({r: tuple(sorted(s)) for r, s in shared.items()}))
        object.__setattr__(
            self, "neighbour_keys", MappingProxyType({r: tuple(sorted(s)) for r, s in neighbour.items()})
        )

    @staticmethod
    def from_graph(graph: PoseGraph, robot: int, *, anchor: int | None = None) -> LocalProblem:
        """Robot ``robot``'s share of ``graph``; it holds ``anchor`` only if that key is its own."""
        keys = set(graph.robot_keys(robot))
        edges = tuple(e for e in graph.edges if e.source in keys and e.target in keys)
        separators = tuple(e for e in graph.edges if (e.source in keys) != (e.target in keys))
        return LocalProblem(
            robot, {k: graph.poses[k] for k in keys}, edges, separators, anchor if anchor in keys else None
        )

    @staticmethod
    def from_robot_file(path: str | Path, robot: int, *, anchor_robot: int = 0) -> LocalProblem:
        """Robot ``robot``'s problem from its own g2o file alone (:func:`~swarmrec.slam.g2o.read_robot_file`).

        The robot ``anchor_robot`` holds the anchor, its first pose (as
        :meth:`PoseGraph.anchor_key` picks it on the team's graph); the others none.
        """
        own = read_robot_file(path, robot)
        anchor = None
        if robot == anchor_robot:
            anchor = PoseGraph(own.poses, own.edges).anchor_key()
        return LocalProblem(robot, own.poses, own.edges, own.separators, anchor)

    @property
    def neighbours(self) -> tuple[int, ...]:
        return tuple(sorted(self.shared))

    @property
    def free_keys(self) -> tuple[int, ...]:
        """The keys this robot estimates (all its keys but the anchor)."""
        return tuple(sorted(k for k in self.poses if k != self.anchor))


class DgsAgent:
    """One robot running the distributed two-stage Gauss-Seidel on its :class:`LocalProblem`."""

    def __init__(self, problem: LocalProblem, *, gamma: float = 1.0) -> None:
        if not 0.0 < gamma < 2.0:
            raise ValueError(f"over-relaxation gamma must be in (0, 2), got {gamma}")
        self.problem = problem
        self.gamma = gamma
        self.robot = problem.robot
        self._stage: Stage = "rotation"
        self._linearisation = 0
        self._systems: dict[frozenset[int], BlockSystem] = {}
        self._solves_in_stage = 0
        # Stage 1: relaxed rotations (3x3) of own keys; latest 9-float rotations of neighbours' keys.
        self._relaxed = {k: p.rotation.copy() for k, p in problem.poses.items()}
        self._neighbour_rotations: dict[int, FloatArray] = {}
        # Pose stages: linearisation points and updates of own and neighbours' separator keys.
        self._linear: dict[int, Pose] = {}
        self._deltas: dict[int, FloatArray] = {}
        self._neighbour_deltas: dict[int, FloatArray] = {}
        # Neighbour robots that have sent an estimate in this stage, and their last iteration.
        self._heard: dict[int, int] = {}

    # ------------------------------------------------------------------ state
    @property
    def stage(self) -> Stage:
        return self._stage

    @property
    def linearisation(self) -> int:
        return self._linearisation

    @property
    def initialised(self) -> bool:
        """Whether this agent has solved at least once in the current stage."""
        return self._solves_in_stage > 0

    def expected_keys(self, sender: int) -> tuple[int, ...]:
        """The keys a message from ``sender`` must carry (its keys on separators with this robot)."""
        return self.problem.neighbour_keys.get(sender, ())

    # --------------------------------------------------------------- messages
    def receive(self, message: DgsMessage) -> bool:
        """Take a neighbour's estimates; False (ignored) when older than one already taken from it.

        Raises :class:`MessageError` for a message of another stage, for another
        robot, from a robot that is no neighbour, or with the wrong keys.
        """
        if message.receiver != self.robot:
            raise MessageError(f"robot {self.robot} got a message addressed to robot {message.receiver}")
        expected = self.expected_keys(message.sender)
        if not expected:
            raise MessageError(f"robot {message.sender} shares no separator with robot {self.robot}")
        if (message.stage, message.linearisation) != (self._stage, self._linearisation):
            raise MessageError(
                f"robot {self.robot} is in the {self._stage} stage (linearisation "
                f"{self._linearisation}); got a {message.stage} message (linearisation "
                f"{message.linearisation}) from robot {message.sender}"
            )
        if set(message.estimates) != set(expected):
            missing = sorted(set(expected) - set(message.estimates))
            extra = sorted(set(message.estimates) - set(expected))
            raise MessageError(
                f"message from robot {message.sender} has keys {len(message.estimates)}: missing "
                f"{[describe_key(k) for k in missing]}, unexpected {[describe_key(k) for k in extra]}"
            )
        if message.iteration < self._heard.get(message.sender, 0):
            return False
        self._heard[message.sender] = message.iteration
        for key, values in message.estimates.items():
            vector = np.array(values, dtype=np.float64)
            if self._stage == "rotation":
                self._neighbour_rotations[key] = vector
            else:
                self._neighbour_deltas[key] = vector
        return True

    def _outgoing(self, iteration: int) -> tuple[DgsMessage, ...]:
        messages = []
        for neighbour, keys in sorted(self.problem.shared.items()):
            if self._stage == "rotation":
                estimates = {k: tuple(rotation_vector(self._relaxed[k])) for k in keys}
            else:
                estimates = {k: tuple(self._deltas[k]) for k in keys}
            messages.append(
                DgsMessage(self.robot, neighbour, self._stage, self._linearisation, iteration, estimates)
            )
        return tuple(messages)

    # ------------------------------------------------------------------ solve
    def _active_neighbours(self) -> frozenset[int]:
        if self._stage == "pose" and self._linearisation > 1:
            return frozenset(self.problem.neighbours)
        return frozenset(self._heard)

    def _edges(self, active: frozenset[int]) -> list[Edge]:
        edges = list(self.problem.edges)
        for edge in self.problem.separators:
            other = edge.target if edge.source in self.problem.poses else edge.source
            if _owner(other) in active:
                edges.append(edge)
        return edges

    def _system(self, active: frozenset[int]) -> BlockSystem:
        system = self._systems.get(active)
        if system is None:
            edges = self._edges(active)
            if self._stage == "rotation":
                system = rotation_system(self.problem.free_keys, edges)
            else:
                system = pose_system(
                    self.problem.free_keys, edges, self._linear, frozen=self._linearisation == 1
                )
            self._systems[active] = system
        return system

    def step(self, iteration: int, inbox: Iterable[DgsMessage] = ()) -> StepReport:
        """Take ``inbox``, solve the local system with the neighbours' latest estimates, report and send.

        With nothing to solve against yet (flagged initialisation: no anchor,
        no neighbour heard from in this stage) the agent waits: no messages,
        infinite change.
        """
        for message in inbox:
            self.receive(message)
        active = self._active_neighbours()
        if self.problem.anchor is None and not active:
            return StepReport(
                self.robot, self._stage, self._linearisation, iteration, False, float("inf"), ()
            )
        change = 0.0  # a robot whose only key is the anchor has nothing to move
        if self.problem.free_keys:
            system = self._system(active)
            solve = self._rotation_solve if self._stage == "rotation" else self._pose_solve
            change = solve(system)
        self._solves_in_stage += 1
        return StepReport(
            self.robot, self._stage, self._linearisation, iteration, True, change, self._outgoing(iteration)
        )

    def _relax(self, old: FloatArray, new: FloatArray) -> FloatArray:
        if self._solves_in_stage == 0 or self.gamma == 1.0:
            return new
        return (1.0 - self.gamma) * old + self.gamma * new

    def _rotation_solve(self, system: BlockSystem) -> float:
        fixed = {
            k: self._neighbour_rotations[k].reshape(3, 3)
            for k in system.fixed_keys
            if k in self._neighbour_rotations
        }
        if self.problem.anchor is not None:
            fixed[self.problem.anchor] = self.problem.poses[self.problem.anchor].rotation
        solved = solve_rotations(system, fixed)
        squared = 0.0
        for key, rotation in solved.items():
            old = self._relaxed[key]
            squared += float(np.sum((rotation - old) ** 2))
            self._relaxed[key] = self._relax(old, rotation)
        return float(np.sqrt(squared))

    def _pose_solve(self, system: BlockSystem) -> float:
        fixed = {k: self._neighbour_deltas[k] for k in system.fixed_keys if k in self._neighbour_deltas}
        if self.problem.anchor is not None:
            fixed[self.problem.anchor] = self._deltas[self.problem.anchor]
        solved = solve_pose_updates(system, fixed)
        squared = 0.0
        for key, delta in solved.items():
            old = self._deltas[key]
            squared += float(np.sum((delta - old) ** 2))
            self._deltas[key] = self._relax(old, delta)
        return float(np.sqrt(squared))

    # ----------------------------------------------------------------- stages
    def begin_pose_stage(self) -> None:
        """Close the current stage and open the next pose stage (no communication needed).

        From the rotation stage: project the relaxed rotations (own, and the
        neighbours' last ones) to SO(3) and linearise at zero translation, the
        anchor's update fixed at its translation. From a pose stage: retract
        (own and neighbours' keys) and linearise again there, updates reset to zero.
        """
        if not self.initialised:
            raise GraphError(f"robot {self.robot} never solved in the {self._stage} stage")
        neighbour_keys = [k for keys in self.problem.neighbour_keys.values() for k in keys]
        anchor = self.problem.anchor
        if self._stage == "rotation":
            missing = [k for k in neighbour_keys if k not in self._neighbour_rotations]
            if missing:
                raise GraphError(
                    f"robot {self.robot} has no rotation estimate of {describe_key(missing[0])} "
                    "from its owner"
                )
            linear = {k: Pose(project_to_so3(r), np.zeros(3)) for k, r in self._relaxed.items()}
            for key in neighbour_keys:
                linear[key] = Pose(project_to_so3(self._neighbour_rotations[key].reshape(3, 3)), np.zeros(3))
            deltas = {k: np.zeros(6) for k in self.problem.poses}
            if anchor is not None:
                anchor_pose = self.problem.poses[anchor]
                linear[anchor] = Pose(anchor_pose.rotation.copy(), np.zeros(3))
                deltas[anchor] = np.concatenate([np.zeros(3), anchor_pose.translation])
        else:
            missing = [k for k in neighbour_keys if k not in self._neighbour_deltas]
            if missing:
                raise GraphError(
                    f"robot {self.robot} has no pose update of {describe_key(missing[0])} from its owner"
                )
            own = retract(self._linear, self._deltas)
            theirs = retract(self._linear, {k: self._neighbour_deltas[k] for k in neighbour_keys})
            linear = {**own, **theirs}
            deltas = {k: np.zeros(6) for k in self.problem.poses}
        # After a pose stage every neighbour's update restarts at zero, its last estimate, and is used
        # at once; after the rotation stage a neighbour's update is unknown until it sends one.
        relinearised = self._stage == "pose"
        self._linear = linear
        self._deltas = deltas
        self._neighbour_deltas = {k: np.zeros(6) for k in neighbour_keys} if relinearised else {}
        self._stage = "pose"
        self._linearisation += 1
        self._systems.clear()
        self._solves_in_stage = 0
        self._heard.clear()

    def estimate(self) -> dict[int, Pose]:
        """The robot's current estimates (rotation stage: projected rotations, zero translations)."""
        if self._stage == "rotation":
            return {k: Pose(project_to_so3(r), np.zeros(3)) for k, r in self._relaxed.items()}
        return retract(self._linear, {k: self._deltas[k] for k in self.problem.poses})
