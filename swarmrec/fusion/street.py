"""The simulated street of the WNBC paper (Sec. 4) and swarm configurations in it.

The paper's Gazebo world is a street with nineteen unique buildings at known
positions; ten small robots, split into two or more clusters in line, double-line
or free formations, look at the facades, and the communication graph (from a radio
range) is always connected. Here the world is 2D, seen from above, metres and radians:

* the street runs along x, ``width`` wide; landmarks 0-9 are facades on the north
  side (``y = +width / 2``), landmarks 10-18 on the south side (``y = -width / 2``),
  staggered by half a facade so that clusters can sit in front of either side;
* a robot sees the landmark its optical axis hits: the ray from its position along
  its yaw (counter-clockwise from +x) to the first facade, within ``max_view`` metres.
  The landmark seen is therefore a function of position and yaw, as in the paper
  ("from the position and orientation of a robot it is possible to predict which
  landmark it would be facing"); a robot whose ray hits a gap or nothing is re-aimed.

For rendering, each robot gets its distance to the hit point, the viewing angle
(0 = head-on; positive when the camera is turned towards the facade's right, as seen
from the street) and where on the facade the ray hits (-0.5 = the facade's left edge,
+0.5 its right edge, again as seen from the street).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt

from swarmrec.errors import ConfigError
from swarmrec.fusion.wnbc import N_LANDMARKS, wrap_angle

__all__ = [
    "FORMATIONS",
    "Facade",
    "Sighting",
    "Street",
    "StreetSettings",
    "SwarmConfiguration",
    "communication_graph",
    "default_street",
    "generate_configuration",
    "generate_configurations",
    "is_connected",
]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

Formation = Literal["line", "double_line", "free"]
#: Cluster formations, as in the paper: "sometimes a line ..., sometimes a double line,
#: and sometimes more general formations".
FORMATIONS: tuple[Formation, ...] = ("line", "double_line", "free")


@dataclass(frozen=True)
class Facade:
    """Landmark ``landmark``: a facade from ``x0`` to ``x1`` on the north (``side = +1``)
    or south (``side = -1``) side of the street."""

    landmark: int
    side: int
    x0: float
    x1: float

    @property
    def width(self) -> float:
        return self.x1 - self.x0

    @property
    def centre(self) -> float:
        return 0.5 * (self.x0 + self.x1)


@dataclass(frozen=True)
class Sighting:
    """What a robot's optical axis hits: the landmark, the distance to the hit point, the
    viewing angle and the hit's offset along the facade (see the module docstring)."""

    landmark: int
    distance: float
    view_angle: float
    offset: float


@dataclass(frozen=True)
class Street:
    """A straight street of ``width`` metres with facades on both sides."""

    width: float
    facades: tuple[Facade, ...]

    def __post_init__(self) -> None:
        if sorted(f.landmark for f in self.facades) != list(range(len(self.facades))):
            raise ConfigError("facade landmarks must be 0 .. n-1, each once")
        if not self.width > 0:
            raise ConfigError(f"street width must be > 0, got {self.width}")

    def facade(self, landmark: int) -> Facade:
        return next(f for f in self.facades if f.landmark == landmark)

    def facade_y(self, side: int) -> float:
        return side * self.width / 2

    @property
    def x_range(self) -> tuple[float, float]:
        return min(f.x0 for f in self.facades), max(f.x1 for f in self.facades)

    def sight(self, x: float, y: float, yaw: float, max_view: float = math.inf) -> Sighting | None:
        """The landmark hit by the ray from ``(x, y)`` along ``yaw``, or ``None`` when the ray
        leaves the street through a gap, past the last facade or beyond ``max_view``."""
        dy = math.sin(yaw)
        if abs(dy) < 1e-9:
            return None  # looking straight along the street: no facade ahead
        side = 1 if dy > 0 else -1
        t = (self.facade_y(side) - y) / dy
        if t <= 0 or t > max_view:
            return None
        hit_x = x + t * math.cos(yaw)
        for f in self.facades:
            if f.side == side and f.x0 <= hit_x <= f.x1:
                head_on = side * math.pi / 2  # the yaw that faces this side squarely
                # The facade's own left-to-right, seen from the street, is +x on the
                # north side and -x on the south side.
                offset = side * (hit_x - f.centre) / f.width
                return Sighting(f.landmark, t, wrap_angle(head_on - yaw), offset)
        return None


def default_street(width: float = 14.0, facade_width: float = 12.0, gap: float = 2.0) -> Street:
    """The 19-landmark street: 10 facades on the north side, 9 on the south side shifted
    by half a pitch, so every facade has neighbours beside it and across the street."""
    pitch = facade_width + gap
    north = [Facade(k, 1, k * pitch, k * pitch + facade_width) for k in range(10)]
    south = [
        Facade(10 + k, -1, pitch / 2 + k * pitch, pitch / 2 + k * pitch + facade_width)
        for k in range(N_LANDMARKS - 10)
    ]
    return Street(width, tuple(north + south))


@dataclass(frozen=True)
class StreetSettings:
    """Knobs of :func:`generate_configurations` (metres, radians)."""

    n_robots: int = 10
    #: Robots talk when closer than this; a few metres makes multi-hop graphs.
    radio_range: float = 7.0
    min_clusters: int = 2
    max_clusters: int = 4
    #: Each cluster's robots stand this far apart, drawn per cluster.
    spacing: tuple[float, float] = (1.0, 3.0)
    #: A cluster's distance from the facade it looks at, drawn per cluster.
    standoff: tuple[float, float] = (2.5, 11.0)
    #: Standard deviation of a robot's yaw around the direction of its aim point.
    yaw_noise: float = 0.2
    #: Farthest a robot recognises a facade (its camera's useful range).
    max_view: float = 25.0
    #: Clusters are put at landmarks whose centres are at most this far apart, so that
    #: the graph has a chance to be connected.
    cluster_reach: float = 20.0
    #: Tries before giving up on a connected configuration.
    max_attempts: int = 2000

    def __post_init__(self) -> None:
        problems = []
        if self.n_robots < 2:
            problems.append(f"n_robots must be >= 2, got {self.n_robots}")
        if not 2 <= self.min_clusters <= self.max_clusters:
            problems.append(
                f"need 2 <= min_clusters <= max_clusters, got {self.min_clusters}, {self.max_clusters}"
            )
        if self.max_clusters > self.n_robots:
            problems.append(f"max_clusters {self.max_clusters} exceeds n_robots {self.n_robots}")
        if not self.radio_range > 0:
            problems.append(f"radio_range must be > 0, got {self.radio_range}")
        if not 0 < self.spacing[0] <= self.spacing[1]:
            problems.append(f"spacing must be 0 < low <= high, got {self.spacing}")
        if not 0 < self.standoff[0] <= self.standoff[1]:
            problems.append(f"standoff must be 0 < low <= high, got {self.standoff}")
        if self.yaw_noise < 0:
            problems.append(f"yaw_noise must be >= 0, got {self.yaw_noise}")
        if problems:
            raise ConfigError("street settings: " + "; ".join(problems))


@dataclass(frozen=True, eq=False)
class SwarmConfiguration:
    """One swarm configuration: per robot ``i``, ``positions[i]`` (x, y), ``yaws[i]``, the
    landmark it sees (the ground-truth class), the distance, viewing angle and facade
    offset of that sighting (for rendering) and its cluster; plus the communication
    graph ``adjacency`` (symmetric, no self-loops, connected)."""

    index: int
    positions: FloatArray
    yaws: FloatArray
    landmarks: IntArray
    distances: FloatArray
    view_angles: FloatArray
    offsets: FloatArray
    clusters: IntArray
    cluster_landmarks: tuple[int, ...]
    formations: tuple[Formation, ...]
    adjacency: BoolArray

    @property
    def n_robots(self) -> int:
        return int(self.positions.shape[0])


def communication_graph(positions: npt.ArrayLike, radio_range: float) -> BoolArray:
    """Undirected graph: robots closer than ``radio_range`` can talk (Sec. 2)."""
    p = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    d = np.linalg.norm(p[:, None, :] - p[None, :, :], axis=-1)
    adj: BoolArray = d <= radio_range
    np.fill_diagonal(adj, False)
    return adj


def is_connected(adjacency: npt.ArrayLike) -> bool:
    """Whether there is a path between any two robots (the paper's standing assumption)."""
    adj = np.asarray(adjacency, dtype=bool)
    n = int(adj.shape[0])
    if n == 0:
        return True
    seen = {0}
    queue = deque([0])
    while queue:
        for j in np.flatnonzero(adj[queue.popleft()]).tolist():
            if j not in seen:
                seen.add(j)
                queue.append(j)
    return len(seen) == n


def _cluster_sizes(rng: np.random.Generator, n_robots: int, n_clusters: int) -> list[int]:
    """At least two robots per cluster where possible, the rest spread at random."""
    base = min(2, n_robots // n_clusters)
    sizes = [base] * n_clusters
    for k in rng.integers(0, n_clusters, n_robots - base * n_clusters).tolist():
        sizes[k] += 1
    return sizes


def _cluster_landmarks(rng: np.random.Generator, street: Street, n: int, reach: float) -> list[int] | None:
    """A chain of distinct landmarks, each near one already chosen (beside or across the
    street), so that clusters in front of them can be within radio range."""
    chosen = [int(rng.integers(0, len(street.facades)))]
    while len(chosen) < n:
        near = sorted(
            {
                f.landmark
                for c in chosen
                for f in street.facades
                if f.landmark not in chosen and abs(f.centre - street.facade(c).centre) <= reach
            }
        )
        if not near:
            return None
        chosen.append(int(rng.choice(near)))
    return chosen


def _formation_offsets(
    rng: np.random.Generator, formation: Formation, size: int, spacing: float
) -> FloatArray:
    """Robot offsets from the cluster anchor: x along the facade, y away from it."""
    k = np.arange(size, dtype=np.float64)
    if formation == "line":
        offsets = np.stack([(k - (size - 1) / 2) * spacing, np.zeros(size)], axis=1)
    elif formation == "double_line":
        cols = np.ceil(size / 2)
        col, row = k // 2, k % 2
        offsets = np.stack([(col - (cols - 1) / 2 + row / 2) * spacing, row * spacing], axis=1)
    else:
        radius = spacing * math.sqrt(size) / 1.5
        angle = rng.uniform(0, 2 * math.pi, size)
        r = radius * np.sqrt(rng.uniform(0, 1, size))
        offsets = np.stack([r * np.cos(angle), r * np.sin(angle)], axis=1)
    return offsets + rng.normal(0.0, 0.1 * spacing, offsets.shape)


def _try_configuration(
    rng: np.random.Generator, street: Street, s: StreetSettings, index: int
) -> SwarmConfiguration | None:
    n_clusters = int(rng.integers(s.min_clusters, s.max_clusters + 1))
    landmarks = _cluster_landmarks(rng, street, n_clusters, s.cluster_reach)
    if landmarks is None:
        return None
    sizes = _cluster_sizes(rng, s.n_robots, n_clusters)
    x_lo, x_hi = street.x_range
    margin = 1.0  # robots keep a metre from the walls
    positions, yaws, clusters, sightings = [], [], [], []
    formations: list[Formation] = []
    for c, (landmark, size) in enumerate(zip(landmarks, sizes, strict=True)):
        f = street.facade(landmark)
        formation = FORMATIONS[int(rng.integers(0, len(FORMATIONS)))]
        formations.append(formation)
        spacing = rng.uniform(*s.spacing)
        standoff = min(rng.uniform(*s.standoff), street.width - 2 * margin)
        anchor = np.array(
            [f.centre + rng.uniform(-0.3, 0.3) * f.width, street.facade_y(f.side) - f.side * standoff]
        )
        offsets = _formation_offsets(rng, formation, size, spacing)
        offsets[:, 1] *= -f.side  # "away from the facade" is -y on the north side
        for p in anchor + offsets:
            x = float(np.clip(p[0], x_lo - 5.0, x_hi + 5.0))
            y = float(np.clip(p[1], -street.width / 2 + margin, street.width / 2 - margin))
            sighting = None
            for _ in range(20):
                aim = rng.uniform(f.x0 + 0.05 * f.width, f.x1 - 0.05 * f.width)
                yaw = math.atan2(street.facade_y(f.side) - y, aim - x) + rng.normal(0.0, s.yaw_noise)
                sighting = street.sight(x, y, yaw, s.max_view)
                if sighting is not None:
                    break
            if sighting is None:
                return None
            positions.append((x, y))
            yaws.append(wrap_angle(yaw))
            clusters.append(c)
            sightings.append(sighting)
    pos = np.array(positions, dtype=np.float64)
    adjacency = communication_graph(pos, s.radio_range)
    if not is_connected(adjacency):
        return None
    return SwarmConfiguration(
        index=index,
        positions=pos,
        yaws=np.array(yaws, dtype=np.float64),
        landmarks=np.array([g.landmark for g in sightings], dtype=np.int64),
        distances=np.array([g.distance for g in sightings], dtype=np.float64),
        view_angles=np.array([g.view_angle for g in sightings], dtype=np.float64),
        offsets=np.array([g.offset for g in sightings], dtype=np.float64),
        clusters=np.array(clusters, dtype=np.int64),
        cluster_landmarks=tuple(landmarks),
        formations=tuple(formations),
        adjacency=adjacency,
    )


def generate_configuration(
    index: int, seed: int = 0, settings: StreetSettings | None = None, street: Street | None = None
) -> SwarmConfiguration:
    """Configuration ``index`` of the family ``seed``: drawn from its own generator
    (seeded by ``(seed, index)``), so it does not depend on how many others are made.
    Draws are repeated until the communication graph is connected."""
    s = settings or StreetSettings()
    st = street or default_street()
    rng = np.random.default_rng([seed, index])
    for _ in range(s.max_attempts):
        config = _try_configuration(rng, st, s, index)
        if config is not None:
            return config
    raise ConfigError(
        f"no connected configuration in {s.max_attempts} draws; raise radio_range ({s.radio_range} m) "
        "or lower the spacing and standoff"
    )


def generate_configurations(
    count: int = 118, seed: int = 0, settings: StreetSettings | None = None, street: Street | None = None
) -> list[SwarmConfiguration]:
    """``count`` configurations (the paper collected 118 of 10 robots, 1180 data points)."""
    return [generate_configuration(i, seed, settings, street) for i in range(count)]
