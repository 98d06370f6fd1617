"""The static office: a block of desks with objects on them, and a room around it.

The block has ``n_desks`` desks in two back-to-back rows (like the two desks of
the TUM ``long_office_household`` scene). Desk layouts cycle through
``workstation, household, workstation, study``: with four or more desks the
workstation layout appears twice side by side, with the same kinds of objects
at nearly the same places (perceptual aliasing). Each desk has a chair in
front of it and counts itself as a ``diningtable`` (YOLO's name for a table).
Just outside the camera's orbit stand a fridge, a bookshelf, a counter, a side
table, a person, spare chairs and a few bags, seen mostly when the camera
glances away (where most rare labels come from).

The world frame has z up, the floor at z = 0, and the block centred on the
origin with its rows along x; tabletops are at 0.75 m.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from swarmrec.synthetic.config import DESK_DEPTH_M, DESK_WIDTH_M, OfficeConfig
from swarmrec.synthetic.labels import coco_names, label_index

__all__ = ["DESK_LAYOUTS", "OfficeWorld", "build_world"]

IntArray = npt.NDArray[np.int64]
FloatArray = npt.NDArray[np.float64]

# (label, offset along the desk's width from its middle, distance from the
# user's edge towards the back, height above the floor), in metres. Heights
# are of the object's centre, which is where the median of its box's depth
# pixels lands on average. Tabletop at 0.75 m.
Placement = tuple[str, float, float, float]

DESK_LAYOUTS: dict[str, tuple[Placement, ...]] = {
    "workstation": (
        ("tvmonitor", 0.00, 0.66, 1.02),
        ("keyboard", 0.00, 0.28, 0.77),
        ("mouse", 0.32, 0.28, 0.77),
        ("cup", -0.42, 0.30, 0.80),
        ("bottle", 0.50, 0.62, 0.87),
        ("bottle", 0.60, 0.50, 0.87),
        ("bottle", -0.25, 0.62, 0.87),
        ("book", -0.55, 0.62, 0.78),
        ("book", -0.55, 0.64, 0.83),
        ("chair", 0.05, -0.15, 0.75),
        ("chair", -0.60, -0.25, 0.75),
        ("diningtable", 0.00, 0.40, 0.72),
    ),
    "household": (
        ("teddy bear", -0.38, 0.55, 0.88),
        ("bottle", 0.22, 0.62, 0.87),
        ("bottle", 0.32, 0.70, 0.87),
        ("bottle", 0.40, 0.58, 0.87),
        ("bottle", 0.52, 0.68, 0.87),
        ("bottle", 0.60, 0.52, 0.87),
        ("bottle", -0.05, 0.70, 0.87),
        ("bowl", 0.00, 0.30, 0.79),
        ("spoon", 0.10, 0.28, 0.77),
        ("spoon", -0.10, 0.24, 0.77),
        ("knife", 0.18, 0.20, 0.76),
        ("fork", -0.18, 0.20, 0.76),
        ("cup", 0.45, 0.25, 0.80),
        ("book", -0.60, 0.30, 0.78),
        ("book", -0.60, 0.32, 0.82),
        ("scissors", -0.12, 0.58, 0.76),
        ("sports ball", -0.62, 0.68, 0.95),
        ("chair", -0.05, -0.15, 0.75),
        ("diningtable", 0.00, 0.40, 0.72),
    ),
    "study": (
        ("laptop", 0.00, 0.42, 0.86),
        ("mouse", 0.30, 0.35, 0.77),
        ("tvmonitor", -0.42, 0.68, 1.02),
        ("keyboard", -0.40, 0.28, 0.77),
        ("cell phone", 0.45, 0.20, 0.76),
        ("book", 0.55, 0.66, 0.78),
        ("book", 0.55, 0.66, 0.82),
        ("book", 0.56, 0.64, 0.86),
        ("bottle", 0.62, 0.35, 0.87),
        ("bottle", -0.62, 0.60, 0.87),
        ("cup", 0.24, 0.60, 0.80),
        ("vase", -0.15, 0.72, 0.90),
        ("chair", 0.00, -0.15, 0.75),
        ("diningtable", 0.00, 0.40, 0.72),
    ),
}

_LAYOUT_CYCLE = ("workstation", "household", "workstation", "study")

# Objects that hide what is behind them (radius in metres) and objects seen
# mostly from one side (their facing is the desk's user direction).
OCCLUDER_RADIUS_M: dict[str, float] = {
    "tvmonitor": 0.25,
    "chair": 0.25,
    "refrigerator": 0.35,
    "person": 0.22,
    "teddy bear": 0.10,
    "laptop": 0.15,
}
_FACING_LABELS = frozenset({"tvmonitor", "laptop", "refrigerator", "microwave"})


@dataclass(frozen=True, eq=False)
class OfficeWorld:
    """The static objects: ``labels[k]`` (COCO index) at ``positions[k]`` (world, m).

    ``groups[k]`` names the piece of furniture the object belongs to
    (``"desk 0 (workstation)"``, ``"bookshelf"``...). ``facing[k]`` is the unit
    direction an object's front looks to, zero for objects seen alike from
    all sides; ``occluder_radius[k]`` is how much an object hides behind it.
    """

    labels: IntArray
    positions: FloatArray
    groups: tuple[str, ...]
    facing: FloatArray
    occluder_radius: FloatArray
    label_names: tuple[str, ...]

    def __len__(self) -> int:
        return int(self.labels.shape[0])

    def label_of(self, k: int) -> str:
        return self.label_names[int(self.labels[k])]


def build_world(config: OfficeConfig, rng: np.random.Generator) -> OfficeWorld:
    """The office of ``config`` (object positions drawn from ``rng``)."""
    names: list[str] = []
    pos: list[FloatArray] = []
    groups: list[str] = []
    facing: list[FloatArray] = []

    # One random variation per layout, shared by all its copies: the copies
    # then differ only by alias_jitter_m (perceptual aliasing).
    variation = {name: rng.normal(0.0, 0.03, (len(layout), 2)) for name, layout in DESK_LAYOUTS.items()}
    n_cols = config.n_desks // 2
    for k in range(config.n_desks):
        col, row = k // 2, k % 2
        layout_name = _LAYOUT_CYCLE[k % len(_LAYOUT_CYCLE)]
        layout = DESK_LAYOUTS[layout_name]
        centre = np.array([(col - (n_cols - 1) / 2) * DESK_WIDTH_M, 0.0])
        # Row 0 faces +y (its user sits at y > 0), row 1 faces -y.
        out = np.array([0.0, 1.0]) if row == 0 else np.array([0.0, -1.0])
        centre = centre + out * DESK_DEPTH_M / 2
        # Along the desk's width (a horizontal unit vector perpendicular to out).
        across = np.array([out[1], -out[0]])
        offsets = variation[layout_name] + rng.normal(0.0, config.alias_jitter_m, (len(layout), 2))
        for (label, a, b, h), off in zip(layout, offsets, strict=True):
            if label in ("chair", "diningtable"):
                off = off * 0.0  # furniture stands where the layout puts it
            xy = centre + (a + off[0]) * across + (DESK_DEPTH_M / 2 - b + off[1]) * out
            names.append(label)
            pos.append(np.array([xy[0], xy[1], h]))
            groups.append(f"desk {k} ({layout_name})")
            facing.append(np.array([out[0], out[1], 0.0]) if label in _FACING_LABELS else np.zeros(3))

    # A chair at each end of the block, seen side-on from the long sides.
    hx = config.block_half_extent_m[0]
    for side in (-1.0, 1.0):
        names.append("chair")
        pos.append(np.array([side * (hx + 0.4), 0.35 * side, 0.7]))
        groups.append("block end")
        facing.append(np.zeros(3))

    for label, p, group, face in _room(config, rng):
        names.append(label)
        pos.append(p)
        groups.append(group)
        facing.append(face)

    label_names = coco_names()
    labels = np.array([label_index(n) for n in names], dtype=np.int64)
    return OfficeWorld(
        labels=labels,
        positions=np.array(pos, dtype=np.float64),
        groups=tuple(groups),
        facing=np.array(facing, dtype=np.float64),
        occluder_radius=np.array([OCCLUDER_RADIUS_M.get(n, 0.0) for n in names]),
        label_names=label_names,
    )


def _room(config: OfficeConfig, rng: np.random.Generator) -> list[tuple[str, FloatArray, str, FloatArray]]:
    """Furniture just outside the camera's orbit, all around it.

    The camera sees these over the desk block from afar (rarely detected) or
    up close when it glances away: that is where most rare labels come from.
    """
    ax, ay = config.orbit_semi_axes_m
    items: list[tuple[str, FloatArray, str, FloatArray]] = []

    def spot(angle_deg: float, out_m: float = 1.0) -> tuple[float, float]:
        """A point ``out_m`` outside the orbit ellipse, at polar angle ``angle_deg``."""
        a = np.deg2rad(angle_deg)
        x, y = ax * np.cos(a), ay * np.sin(a)
        normal = np.array([x / ax**2, y / ay**2])
        normal /= np.linalg.norm(normal)
        return float(x + out_m * normal[0]), float(y + out_m * normal[1])

    def put(label: str, at: tuple[float, float], dx: float, dy: float, h: float, group: str) -> None:
        p = np.array([at[0] + dx, at[1] + dy, h]) + np.append(rng.normal(0.0, 0.02, 2), 0.0)
        face = np.zeros(3)
        if label in _FACING_LABELS:
            face = -np.array([p[0], p[1], 0.0]) / np.hypot(p[0], p[1])  # facing the centre
        items.append((label, p, group, face))

    side = spot(0.0)
    put("remote", side, 0.0, -0.25, 0.76, "side table")
    put("cup", side, 0.0, 0.05, 0.80, "side table")
    put("book", side, 0.05, 0.3, 0.78, "side table")
    fridge = spot(50.0, 1.2)
    put("refrigerator", fridge, 0.0, 0.0, 0.9, "fridge")
    shelf = spot(90.0)
    for i in range(6):
        put("book", shelf, -0.6 + 0.24 * i, 0.0, 1.05 + 0.4 * (i % 2), "bookshelf")
    put("handbag", spot(125.0, 0.6), 0.0, 0.0, 0.3, "floor")
    counter = spot(180.0)
    put("microwave", counter, 0.0, -0.5, 1.05, "counter")
    put("bottle", counter, 0.0, -0.05, 1.02, "counter")
    put("bottle", counter, 0.05, 0.1, 1.02, "counter")
    put("cake", counter, 0.0, 0.35, 0.98, "counter")
    put("donut", counter, -0.05, 0.55, 0.96, "counter")
    put("chair", spot(215.0, 0.6), 0.0, 0.0, 0.7, "spare chairs")
    put("person", spot(250.0, 1.2), 0.0, 0.0, 1.1, "visitor")
    put("backpack", spot(300.0, 0.6), 0.0, 0.0, 0.25, "floor")
    put("chair", spot(330.0, 0.6), 0.0, 0.0, 0.7, "spare chairs")
    return items
