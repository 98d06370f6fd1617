"""Simulated multi-robot object-based SLAM scenarios: the paper's "25 chairs" and a "house".

A scenario is a world of objects with SE(3) poses and labels, a team of 2 to 6
robots driving loops that meet in the middle (rendezvous), and what the robots
build from it, exactly as the paper's pipeline (Sec. 2):

- each robot's object-based pose graph: odometry between consecutive poses and
  a relative-pose measurement ``z_ik ~ x_i^-1 o_k`` (the object-pose factor,
  Eq. 1 of the paper) each time it sees an object within its sensor's range and
  field of view; noise is Gaussian on the rotation (``sigma_rotation_deg``) and the
  translation (``sigma_translation``), and the information matrices are the
  matching ``diag(1/sigma_r^2, 1/sigma_t^2)`` (the paper's Table 2 levels:
  ``PAPER_NOISE_LEVELS``);
- object data association by label within a distance gate: a detection is the
  nearest mapped object with the same label within ``association_gate`` metres,
  or a new object. The paper runs this on the robot's own SLAM estimate; here
  it runs on the true pose plus the measurement's noise, i.e. we assume the
  single-robot front end keeps its local estimate within the gate;
- rendezvous: when two robots come within ``communication_range`` (after being
  apart), each sends only its objects' labels and poses in the common frame
  (the initial poses are known to all, the paper's assumption), as its front
  end placed them; the receiver pairs each object with its nearest unpaired
  object of the same label within the gate. Each pair (a shared object)
  becomes a separator: an object-object factor with a zero relative pose (Eq. 2
  of the paper) and information ``Lambda`` (``separator_sigma_*``). Like the
  single-robot association this assumes a locally accurate front end: with
  the paper's noise levels, dead reckoning alone drifts metres over a loop
  (several times the chairs' spacing), and the paper's simulations report no
  wrong association; wrong ones are studied separately (``outliers``).

``outliers`` injects that many wrong associations (two different objects of
the same label, or of any label when no such pair exists) between robots that
met, for the robust back end. Keys: robot ``r``'s poses ``Symbol('a' + r, i)``,
its objects ``Symbol('A' + r, k)``. Everything is drawn from one seeded
generator: the same settings give the same scenario.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from swarmrec.errors import ConfigError
from swarmrec.slam.errors import GraphError
from swarmrec.slam.graph import Edge, PoseGraph
from swarmrec.slam.keys import landmark_key, pose_key, robot_of_key
from swarmrec.slam.lie import FloatArray, Pose, so3_exp

__all__ = [
    "PAPER_NOISE_LEVELS",
    "WORLDS",
    "Scenario",
    "ScenarioSettings",
    "Separator",
    "World",
    "WorldObject",
    "generate_scenario",
    "make_world",
]

World = Literal["chairs", "house"]
WORLDS: tuple[World, ...] = ("chairs", "house")
# (sigma_R in degrees, sigma_t in metres), the rows of the paper's Table 2.
PAPER_NOISE_LEVELS: tuple[tuple[float, float], ...] = ((1.0, 0.1), (5.0, 0.1), (10.0, 0.2), (15.0, 0.3))

# The house: a living room, a kitchen and a bedroom, about 14 x 10 m (label, x, y, yaw in degrees).
_HOUSE_LAYOUT: tuple[tuple[str, float, float, float], ...] = (
    ("sofa", -4.5, 4.0, 180.0),
    ("armchair", -6.2, 1.8, 90.0),
    ("armchair", -2.6, 1.6, -90.0),
    ("table", -4.4, 1.9, 0.0),
    ("tv", -4.5, -0.6, 0.0),
    ("bookshelf", -6.6, -2.5, 90.0),
    ("plant", -1.4, 4.3, 0.0),
    ("lamp", -6.5, 4.3, 0.0),
    ("table", 3.0, 3.2, 0.0),
    ("chair", 2.0, 4.2, -90.0),
    ("chair", 4.0, 2.2, 90.0),
    ("fridge", 6.5, 4.3, 180.0),
    ("oven", 5.2, 4.4, 180.0),
    ("sink", 6.6, 2.0, 180.0),
    ("bed", 4.2, -3.0, 0.0),
    ("nightstand", 5.8, -4.2, 0.0),
    ("nightstand", 2.6, -4.2, 0.0),
    ("wardrobe", 6.6, -0.9, 180.0),
    ("desk", 0.8, -4.3, 90.0),
    ("chair", 0.8, -3.1, -90.0),
    ("plant", 0.2, 0.3, 0.0),
    ("lamp", 1.6, -1.8, 0.0),
    ("bookshelf", -2.2, -4.4, 90.0),
    ("plant", -3.8, -3.6, 0.0),
)
# Objects of one label are at least 2.5 m apart (tested), so the 1 m gate never confuses two of them.
_CHAIRS_GRID = 5
_CHAIRS_SPACING = 3.0
_OBJECT_HEIGHT = 0.5


@dataclass(frozen=True)
class WorldObject:
    label: str
    pose: Pose


@dataclass(frozen=True)
class ScenarioSettings:
    """How a scenario is generated (every field validated; see the module doc for the model).

    - ``world``: ``chairs`` (25 chairs on a 5 x 5 grid, 3 m apart, random yaw) or ``house``.
    - ``robots``: 2 to 6 robots, each driving ``laps`` of a circle of ``radius`` m whose
      centre is ``offset`` m from the world's centre, starting and ending near that centre.
    - ``step``: metres between consecutive poses.
    - ``sigma_rotation_deg``, ``sigma_translation``: measurement noise (odometry and objects).
    - ``sensor_range``, ``field_of_view_deg``: what a robot sees from a pose.
    - ``association_gate``: metres within which a detection is the same object (the paper's 2 sigma).
    - ``communication_range``: metres within which two robots meet.
    - ``separator_sigma_rotation_deg``, ``separator_sigma_translation``: ``Lambda`` of object-object factors.
    - ``outliers``: wrong inter-robot associations injected.
    """

    world: World = "chairs"
    robots: int = 6
    seed: int = 0
    sigma_rotation_deg: float = 5.0
    sigma_translation: float = 0.1
    step: float = 1.0
    radius: float = 4.0
    offset: float = 4.5
    laps: float = 1.1
    sensor_range: float = 4.0
    field_of_view_deg: float = 120.0
    association_gate: float = 1.0
    communication_range: float = 3.0
    separator_sigma_rotation_deg: float = 5.0
    separator_sigma_translation: float = 0.1
    outliers: int = 0

    def __post_init__(self) -> None:
        if self.world not in WORLDS:
            raise ConfigError(f"world must be one of {WORLDS}, got {self.world!r}")
        if not 2 <= self.robots <= 6:
            raise ConfigError(f"robots must be 2 to 6 (the paper's teams), got {self.robots}")
        positive = (
            "sigma_rotation_deg",
            "sigma_translation",
            "step",
            "radius",
            "laps",
            "sensor_range",
            "field_of_view_deg",
            "association_gate",
            "communication_range",
            "separator_sigma_rotation_deg",
            "separator_sigma_translation",
        )
        for name in positive:
            if not getattr(self, name) > 0.0:
                raise ConfigError(f"{name} must be positive, got {getattr(self, name)}")
        if self.offset < 0.0 or self.outliers < 0:
            raise ConfigError("offset and outliers must not be negative")


@dataclass(frozen=True)
class Separator:
    """An inter-robot object-object factor; ``correct`` when both objects are the same physical one."""

    edge: Edge
    correct: bool
    injected: bool


@dataclass(frozen=True)
class Scenario:
    """A generated scenario: the world, true trajectories, the team's pose graph and its ground truth.

    ``graph``'s vertices are the robots' initial estimates (dead reckoning from
    the known initial poses); ``truth`` has the true pose of every key (an
    object key: its object's pose); ``landmark_objects`` maps object keys to
    indices of ``objects``; ``meetings`` lists ``(robot a, robot b, step)``.
    """

    settings: ScenarioSettings
    objects: tuple[WorldObject, ...]
    trajectories: tuple[tuple[Pose, ...], ...]
    graph: PoseGraph
    truth: dict[int, Pose]
    landmark_objects: dict[int, int]
    separators: tuple[Separator, ...]
    meetings: tuple[tuple[int, int, int], ...]
    intra_association_errors: int

    @property
    def wrong_separators(self) -> int:
        return sum(not s.correct for s in self.separators)


def _yaw_pose(yaw: float, x: float, y: float, z: float = 0.0) -> Pose:
    return Pose(so3_exp([0.0, 0.0, yaw]), np.array([x, y, z]))


def make_world(world: World, rng: np.random.Generator) -> tuple[WorldObject, ...]:
    """The objects of a world (chairs: random yaw on a grid; house: the fixed layout, jittered)."""
    if world == "chairs":
        half = (_CHAIRS_GRID - 1) / 2.0
        return tuple(
            WorldObject(
                "chair",
                _yaw_pose(
                    float(rng.uniform(0.0, 2 * math.pi)),
                    (i - half) * _CHAIRS_SPACING,
                    (j - half) * _CHAIRS_SPACING,
                    _OBJECT_HEIGHT,
                ),
            )
            for i in range(_CHAIRS_GRID)
            for j in range(_CHAIRS_GRID)
        )
    return tuple(
        WorldObject(
            label,
            _yaw_pose(
                math.radians(yaw) + float(rng.normal(0.0, 0.1)),
                x + float(rng.normal(0, 0.1)),
                y + float(rng.normal(0, 0.1)),
                _OBJECT_HEIGHT,
            ),
        )
        for label, x, y, yaw in _HOUSE_LAYOUT
    )


def _trajectories(settings: ScenarioSettings) -> tuple[tuple[Pose, ...], ...]:
    """Loops that start and end next to the world's centre, each around its own part of the world.

    Robot ``r`` drives ``laps`` of a circle whose centre is ``offset`` metres from
    the world's centre in direction ``2 pi r / n``; it starts on the side nearest
    the world's centre, so the team starts together (and meets) there, spreads
    out, and meets again on the way back with its whole map.
    """
    n_steps = math.ceil(settings.laps * 2 * math.pi * settings.radius / settings.step)
    angle_step = settings.step / settings.radius
    out = []
    for robot in range(settings.robots):
        phase = 2 * math.pi * robot / settings.robots + 0.3  # off the grid's axes
        centre = settings.offset * np.array([math.cos(phase), math.sin(phase)])
        poses = []
        for i in range(n_steps + 1):
            theta = phase + math.pi + i * angle_step
            x, y = centre + settings.radius * np.array([math.cos(theta), math.sin(theta)])
            poses.append(_yaw_pose(theta + math.pi / 2, float(x), float(y)))
        out.append(tuple(poses))
    return tuple(out)


def _information(sigma_rotation_deg: float, sigma_translation: float) -> FloatArray:
    return np.diag([math.radians(sigma_rotation_deg) ** -2] * 3 + [sigma_translation**-2] * 3)


def _noisy(z: Pose, rng: np.random.Generator, sigma_r: float, sigma_t: float) -> Pose:
    return Pose(
        z.rotation @ so3_exp(rng.normal(0.0, sigma_r, 3)), z.translation + rng.normal(0.0, sigma_t, 3)
    )


def _visible(pose: Pose, obj: WorldObject, settings: ScenarioSettings) -> bool:
    local = pose.rotation.T @ (obj.pose.translation - pose.translation)
    distance = math.hypot(local[0], local[1])
    bearing = math.degrees(math.atan2(local[1], local[0]))
    return distance <= settings.sensor_range and abs(bearing) <= settings.field_of_view_deg / 2


@dataclass
class _RobotMap:
    """One robot's front end while it drives: its graph so far and its objects."""

    robot: int
    poses: dict[int, Pose]
    edges: list[Edge]
    labels: dict[int, str]
    first_seen: dict[int, int]
    positions: dict[int, FloatArray]  # where each object was predicted at its first sighting (association)
    objects: dict[int, int]  # object key -> true object index

    def subgraph(self, step: int) -> PoseGraph:
        keys = {pose_key(self.robot, i) for i in range(step + 1)}
        keys |= {k for k, s in self.first_seen.items() if s <= step}
        return PoseGraph(
            {k: self.poses[k] for k in keys},
            tuple(e for e in self.edges if e.source in keys and e.target in keys),
        )


def _drive(
    robot: int,
    trajectory: Sequence[Pose],
    objects: Sequence[WorldObject],
    settings: ScenarioSettings,
    rng: np.random.Generator,
) -> tuple[_RobotMap, int]:
    sigma_r = math.radians(settings.sigma_rotation_deg)
    sigma_t = settings.sigma_translation
    info = _information(settings.sigma_rotation_deg, sigma_t)
    m = _RobotMap(robot, {pose_key(robot, 0): trajectory[0]}, [], {}, {}, {}, {})
    wrong = 0
    for i, true_pose in enumerate(trajectory):
        key = pose_key(robot, i)
        if i > 0:
            z = _noisy(trajectory[i - 1].between(true_pose), rng, sigma_r, sigma_t)
            m.edges.append(Edge(pose_key(robot, i - 1), key, z, info))
            m.poses[key] = m.poses[pose_key(robot, i - 1)].compose(z)
        for index, obj in enumerate(objects):
            if not _visible(true_pose, obj, settings):
                continue
            z = _noisy(true_pose.between(obj.pose), rng, sigma_r, sigma_t)
            predicted = true_pose.compose(z).translation
            candidates = [
                (float(np.linalg.norm(p - predicted)), k)
                for k, p in m.positions.items()
                if m.labels[k] == obj.label
                and float(np.linalg.norm(p - predicted)) <= settings.association_gate
            ]
            if candidates:
                object_key = min(candidates)[1]
                wrong += m.objects[object_key] != index
            else:
                object_key = landmark_key(robot, len(m.labels))
                m.labels[object_key] = obj.label
                m.first_seen[object_key] = i
                m.positions[object_key] = predicted
                m.objects[object_key] = index
                m.poses[object_key] = m.poses[key].compose(z)
            m.edges.append(Edge(key, object_key, z, info))
    return m, wrong


def _associate(a: _RobotMap, b: _RobotMap, step: int, gate: float) -> list[tuple[int, int]]:
    """Shared objects: b pairs each of a's objects with its nearest unpaired same-label one in the gate.

    Both sides use their front end's object positions in the common frame
    (see the module doc: locally accurate, initial poses known).
    """
    mine = {k: p for k, p in a.positions.items() if a.first_seen[k] <= step}
    theirs = {k: p for k, p in b.positions.items() if b.first_seen[k] <= step}
    pairs = sorted(
        (float(np.linalg.norm(pa - pb)), ka, kb)
        for ka, pa in mine.items()
        for kb, pb in theirs.items()
        if a.labels[ka] == b.labels[kb] and float(np.linalg.norm(pa - pb)) <= gate
    )
    used_a: set[int] = set()
    used_b: set[int] = set()
    shared = []
    for _, ka, kb in pairs:
        if ka not in used_a and kb not in used_b:
            used_a.add(ka)
            used_b.add(kb)
            shared.append((ka, kb))
    return shared


def _meetings(
    trajectories: Sequence[Sequence[Pose]], communication_range: float
) -> list[tuple[int, int, int]]:
    events = []
    for a in range(len(trajectories)):
        for b in range(a + 1, len(trajectories)):
            together = False
            for step, (pa, pb) in enumerate(zip(trajectories[a], trajectories[b], strict=True)):
                close = float(np.linalg.norm(pa.translation - pb.translation)) <= communication_range
                if close and not together:
                    events.append((a, b, step))
                together = close
    return sorted(events, key=lambda e: (e[2], e[0], e[1]))


def _outlier_pairs(
    maps: Sequence[_RobotMap],
    met: set[tuple[int, int]],
    count: int,
    existing: set[tuple[int, int]],
    rng: np.random.Generator,
) -> list[tuple[int, int]]:
    pairs = sorted(met)
    out: list[tuple[int, int]] = []
    attempts = 0
    while len(out) < count and attempts < 1000 * max(count, 1):
        attempts += 1
        a, b = pairs[int(rng.integers(len(pairs)))]
        ka = sorted(maps[a].labels)[int(rng.integers(len(maps[a].labels)))]
        same_label = [
            k
            for k in sorted(maps[b].labels)
            if maps[b].labels[k] == maps[a].labels[ka] and maps[b].objects[k] != maps[a].objects[ka]
        ]
        others = same_label or [
            k for k in sorted(maps[b].labels) if maps[b].objects[k] != maps[a].objects[ka]
        ]
        if not others:
            continue
        kb = others[int(rng.integers(len(others)))]
        if (ka, kb) not in existing:
            existing.add((ka, kb))
            out.append((ka, kb))
    return out


def generate_scenario(settings: ScenarioSettings | None = None) -> Scenario:
    """Generate a scenario (deterministic for given settings; see the module doc)."""
    settings = settings or ScenarioSettings()
    rng = np.random.default_rng(settings.seed)
    objects = make_world(settings.world, rng)
    trajectories = _trajectories(settings)
    maps = []
    wrong_intra = 0
    for robot, trajectory in enumerate(trajectories):
        m, wrong = _drive(robot, trajectory, objects, settings, rng)
        maps.append(m)
        wrong_intra += wrong
    lam = _information(settings.separator_sigma_rotation_deg, settings.separator_sigma_translation)
    meetings = _meetings(trajectories, settings.communication_range)
    shared: dict[tuple[int, int], None] = {}
    for a, b, step in meetings:
        for pair in _associate(maps[a], maps[b], step, settings.association_gate):
            shared.setdefault(pair, None)
    met = {(a, b) for a, b, _ in meetings}
    injected = _outlier_pairs(maps, met, settings.outliers, set(shared), rng) if met else []
    separators = []
    for (ka, kb), is_injected in [*((p, False) for p in shared), *((p, True) for p in injected)]:
        ra, rb = _robot_of_landmark(ka), _robot_of_landmark(kb)
        correct = maps[ra].objects[ka] == maps[rb].objects[kb]
        separators.append(Separator(Edge(ka, kb, Pose.identity(), lam), correct, is_injected))
    poses = {k: p for m in maps for k, p in m.poses.items()}
    edges = [e for m in maps for e in m.edges] + [s.edge for s in separators]
    graph = PoseGraph(poses, tuple(edges))
    if not graph.is_connected():
        alone = sorted(set(range(settings.robots)) - {r for pair in graph.separator_counts() for r in pair})
        raise GraphError(
            f"the team's graph is not connected (robots without a shared object: {alone}); "
            "widen communication_range or association_gate"
        )
    truth = {pose_key(r, i): p for r, t in enumerate(trajectories) for i, p in enumerate(t)}
    landmark_objects = {k: i for m in maps for k, i in m.objects.items()}
    truth.update({k: objects[i].pose for k, i in landmark_objects.items()})
    return Scenario(
        settings,
        objects,
        trajectories,
        graph,
        truth,
        landmark_objects,
        tuple(separators),
        tuple(meetings),
        wrong_intra,
    )


def _robot_of_landmark(key: int) -> int:
    robot = robot_of_key(key)
    if robot is None:  # every key here is made by landmark_key
        raise GraphError(f"{key} is not an object key")
    return robot
