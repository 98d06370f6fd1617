"""What each object class looks like to the renderer, and the room around the objects.

Every class the office world uses gets its own silhouette, proportions,
colours and pattern (keys on a keyboard, a label band on a bottle, text lines
on a lit screen, fur dots on a teddy bear...), so that a small CNN trained on
the renders has something class-specific to learn. Colours vary per instance
within a class palette, drawn from the renderer's seed.

Shapes are given in the object's frame: x across, y towards the object's
*front*, z up, with the origin at the object's world position (its point in
the constellations). The world puts that point where the median depth of the
object's box lands (:mod:`swarmrec.synthetic.world`), so compact objects are
built around it, and deep objects with a flat front (a fridge, a microwave, a
book on a shelf) have their front a few centimetres before it rather than
their middle on it. Every shape holds its point (a test checks it); the parts
stand on the desk or floor beneath. The front is the world's ``facing`` where it has one (screens), the
user's side for objects on a desk, and the centre of the room for the rest:
chairs show their backrest, books on a shelf their spine, people their face
to whoever looks from the middle.

The room is built around the objects: floor, walls and ceiling a margin
beyond them (and beyond any camera positions given), with a door, a
whiteboard, windows, posters and ceiling lamps, plus the furniture that the
world's groups imply but do not list as objects (the side table, the counter
and the bookshelf under their objects). None of it has a label.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Literal

import numpy as np
import numpy.typing as npt

from swarmrec.errors import ConfigError
from swarmrec.synthetic.render_mesh import Lighting, Material, Part, Pattern, Scene, SceneBuilder
from swarmrec.synthetic.world import OfficeWorld

__all__ = ["CLASS_SHAPES", "build_scene"]

FloatArray = npt.NDArray[np.float64]
Shape = Callable[[np.random.Generator], tuple[Part, ...]]
# (shape, size, x, y, material) of a piece of a tilted object, see _tilted.
Piece = tuple[Literal["box", "ellipsoid"], tuple[float, float, float], float, float, Material]

# Floor to ceiling.
_ROOM_HEIGHT_M = 2.8
# Floor and walls stand this far beyond the outermost object or camera position.
_ROOM_MARGIN_M = 1.2
# Random turn (degrees, uniform +-) of each instance about the vertical, per class.
_YAW_JITTER_DEG: dict[str, float] = {
    "diningtable": 0.0,
    "tvmonitor": 4.0,
    "refrigerator": 3.0,
    "microwave": 5.0,
    "keyboard": 6.0,
    "laptop": 8.0,
    "book": 12.0,
    "person": 25.0,
}
_DEFAULT_YAW_JITTER_DEG = 35.0


def _pick(rng: np.random.Generator, options: Sequence[str]) -> str:
    return options[int(rng.integers(len(options)))]


def _solid(colour: str, emissive: bool = False) -> tuple[Material]:
    return (Material(colour, emissive=emissive),)


def _faces(
    sides: Material, *, front: Material | None = None, top: Material | None = None
) -> tuple[Material, ...]:
    """Six box materials (+x, -x, +y, -y, +z, -z): ``sides`` except a distinct front (+y) or top."""
    return (sides, sides, front or sides, sides, top or sides, sides)


def _tilted(parts: Sequence[Piece], tilt: float) -> tuple[Part, ...]:
    """Boxes and ellipsoids laid along y and tilted together by ``tilt`` degrees about x.

    Cutlery rests with one end raised (on a bowl's rim, a napkin), which
    also keeps the world's point, a centimetre or two above the desk, on it.
    Each entry is ``(shape, size, x, y, material)``.
    """
    c, s = np.cos(np.deg2rad(tilt)), np.sin(np.deg2rad(tilt))
    return tuple(
        Part(shape, size, (mat,), at=(x, y * c, y * s), tilt=tilt) for shape, size, x, y, mat in parts
    )


# --- desk objects --------------------------------------------------------------------------------


def _tvmonitor(rng: np.random.Generator) -> tuple[Part, ...]:
    body = Material(_pick(rng, ["#1c1c1c", "#2a2a2a", "#cfcfcf"]))
    screen = Material(
        _pick(rng, ["#3b6ea8", "#2d2d5a", "#e8e8e8", "#24506e"]),
        _pick(rng, ["#dfe8f2", "#9fb8d8", "#303030"]),
        Pattern.STRIPES_T,
        0.022,
        0.35,
        emissive=True,
    )
    return (
        Part("box", (0.56, 0.04, 0.35), (body,)),
        Part("box", (0.51, 0.004, 0.30), (screen,), at=(0.0, 0.021, 0.01)),
        Part("box", (0.05, 0.03, 0.14), (body,), at=(0.0, -0.03, -0.20)),
        Part("box", (0.24, 0.18, 0.015), (body,), at=(0.0, -0.03, -0.2625)),
    )


def _keyboard(rng: np.random.Generator) -> tuple[Part, ...]:
    body, keys, gaps = [("#202020", "#3c3c3c", "#141414"), ("#d8d8d8", "#f2f2f2", "#8a8a8a")][
        int(rng.integers(2))
    ]
    top = Material(keys, gaps, Pattern.GRID, 0.019, 0.2)
    return (Part("box", (0.44, 0.14, 0.024), _faces(Material(body), top=top), at=(0.0, 0.0, -0.008)),)


def _mouse(rng: np.random.Generator) -> tuple[Part, ...]:
    colour = _pick(rng, ["#1e1e1e", "#e0e0e0", "#8f8f8f"])
    return (
        Part("ellipsoid", (0.03, 0.055, 0.02), _solid(colour)),
        Part("box", (0.004, 0.03, 0.004), _solid("#555555"), at=(0.0, 0.03, 0.0175)),
    )


def _cup(rng: np.random.Generator) -> tuple[Part, ...]:
    colour = _pick(rng, ["#f5f5f5", "#c62828", "#1565c0", "#f9a825", "#2e7d32"])
    side = Material(colour, _pick(rng, ["#1a1a1a", "#ffffff", "#e53935"]), Pattern.BAND, 0.02, 0.008)
    top = Material(colour, "#3e2723", Pattern.DISC, 0.034)
    return (
        Part("frustum", (0.036, 0.042, 0.10), (side, top, side)),
        Part("box", (0.012, 0.03, 0.06), (Material(colour),), at=(0.05, 0.0, 0.005)),
    )


def _bottle(rng: np.random.Generator) -> tuple[Part, ...]:
    glass = _pick(rng, ["#2e7d32", "#6d4c2f", "#1e63a8", "#a8c8d8", "#c0ca33"])
    label = _pick(rng, ["#f2f2f2", "#d32f2f", "#fbc02d", "#1a237e"])
    cap = Material(_pick(rng, ["#f5f5f5", "#c62828", "#1565c0", "#212121"]))
    body = Material(glass, label, Pattern.BAND, 0.0, 0.04)
    return (
        Part("frustum", (0.033, 0.033, 0.17), (body,), at=(0.0, 0.0, -0.035)),
        Part("frustum", (0.033, 0.014, 0.04), (Material(glass),), at=(0.0, 0.0, 0.07)),
        Part("frustum", (0.014, 0.014, 0.03), (Material(glass),), at=(0.0, 0.0, 0.105)),
        Part("frustum", (0.016, 0.016, 0.016), (cap,), at=(0.0, 0.0, 0.128)),
    )


_COVERS = ("#b71c1c", "#0d47a1", "#1b5e20", "#f57f17", "#4a148c", "#263238", "#e65100", "#006064")
_PAGES = Material("#f3ecd8", "#cfc5ab", Pattern.STRIPES_T, 0.008, 0.3)


def _book(rng: np.random.Generator) -> tuple[Part, ...]:
    """A book lying flat, spine to the left (-x)."""
    colour = _pick(rng, _COVERS)
    cover = Material(colour, "#f0f0f0", Pattern.BAND, 0.05, 0.012)
    spine = Material(colour)
    size = (float(rng.uniform(0.15, 0.19)), float(rng.uniform(0.21, 0.25)), float(rng.uniform(0.035, 0.05)))
    return (Part("box", size, (_PAGES, spine, _PAGES, _PAGES, cover, cover)),)


def _standing_book(rng: np.random.Generator) -> tuple[Part, ...]:
    """A book upright on a shelf, spine to the front (+y)."""
    colour = _pick(rng, _COVERS)
    spine = Material(colour, "#f0f0f0", Pattern.BAND, 0.06, 0.01)
    size = (float(rng.uniform(0.03, 0.05)), 0.17, 0.24)
    look = (Material(colour), Material(colour), spine, _PAGES, _PAGES, _PAGES)
    return (Part("box", size, look, at=(0.0, -0.06, 0.0)),)


def _teddy_bear(rng: np.random.Generator) -> tuple[Part, ...]:
    fur_colour = _pick(rng, ["#8d5a2b", "#c49a6c", "#6b4423", "#e0c9a6"])
    fur = (Material(fur_colour, "#5a3a1c", Pattern.DOTS, 0.02, 0.18),)
    light = _solid("#ead7b8")
    dark = _solid("#111111")
    return (
        Part("ellipsoid", (0.085, 0.075, 0.10), fur, at=(0.0, 0.0, -0.03)),
        Part("ellipsoid", (0.065, 0.06, 0.062), fur, at=(0.0, 0.01, 0.115)),
        Part("ellipsoid", (0.024, 0.012, 0.024), fur, at=(-0.05, 0.0, 0.17)),
        Part("ellipsoid", (0.024, 0.012, 0.024), fur, at=(0.05, 0.0, 0.17)),
        Part("ellipsoid", (0.03, 0.022, 0.022), light, at=(0.0, 0.065, 0.105)),
        Part("ellipsoid", (0.009, 0.006, 0.009), dark, at=(-0.024, 0.064, 0.13)),
        Part("ellipsoid", (0.009, 0.006, 0.009), dark, at=(0.024, 0.064, 0.13)),
        Part("ellipsoid", (0.025, 0.025, 0.055), fur, at=(-0.085, 0.02, 0.0)),
        Part("ellipsoid", (0.025, 0.025, 0.055), fur, at=(0.085, 0.02, 0.0)),
        Part("ellipsoid", (0.03, 0.045, 0.025), light, at=(-0.045, 0.055, -0.105)),
        Part("ellipsoid", (0.03, 0.045, 0.025), light, at=(0.045, 0.055, -0.105)),
    )


def _bowl(rng: np.random.Generator) -> tuple[Part, ...]:
    colour = _pick(rng, ["#fafafa", "#4fc3f7", "#ff8a65", "#aed581"])
    inside = Material(colour, "#7b7b7b", Pattern.DISC, 0.07)
    return (
        Part(
            "frustum",
            (0.045, 0.08, 0.07),
            (Material(colour), inside, Material(colour)),
            at=(0.0, 0.0, -0.005),
        ),
    )


_STEEL = Material("#c4c4c4", "#8a8a8a", Pattern.STRIPES_S, 0.01, 0.3)


def _spoon(rng: np.random.Generator) -> tuple[Part, ...]:
    return _tilted(
        [
            ("box", (0.012, 0.12, 0.004), 0.0, -0.03, _STEEL),
            ("ellipsoid", (0.022, 0.032, 0.007), 0.0, 0.058, _STEEL),
        ],
        12.0,
    )


def _knife(rng: np.random.Generator) -> tuple[Part, ...]:
    handle = Material(_pick(rng, ["#3e2723", "#212121", "#c4c4c4"]))
    return _tilted(
        [
            ("box", (0.02, 0.11, 0.003), 0.0, 0.045, _STEEL),
            ("box", (0.018, 0.09, 0.012), 0.0, -0.055, handle),
        ],
        6.0,
    )


def _fork(rng: np.random.Generator) -> tuple[Part, ...]:
    parts: list[Piece] = [
        ("box", (0.012, 0.11, 0.004), 0.0, -0.035, _STEEL),
        ("box", (0.026, 0.03, 0.004), 0.0, 0.035, _STEEL),
    ]
    parts += [("box", (0.004, 0.035, 0.004), x, 0.0675, _STEEL) for x in (-0.0105, -0.0035, 0.0035, 0.0105)]
    return _tilted(parts, 6.5)


def _scissors(rng: np.random.Generator) -> tuple[Part, ...]:
    grip = _solid(_pick(rng, ["#e53935", "#1e88e5", "#fb8c00", "#212121"]))
    blade = (_STEEL,)
    return (
        Part("box", (0.014, 0.10, 0.004), blade, at=(-0.006, 0.045, 0.0), yaw=8.0),
        Part("box", (0.014, 0.10, 0.004), blade, at=(0.006, 0.045, 0.0), yaw=-8.0),
        Part("frustum", (0.022, 0.022, 0.008), grip, at=(-0.022, -0.035, 0.0)),
        Part("frustum", (0.022, 0.022, 0.008), grip, at=(0.022, -0.035, 0.0)),
    )


def _sports_ball(rng: np.random.Generator) -> tuple[Part, ...]:
    """A desk globe (YOLO calls it a sports ball): oceans with blotches of land on a stand."""
    globe = Material("#1565c0", _pick(rng, ["#43a047", "#8d6e63", "#c0ca33"]), Pattern.DOTS, 0.09, 0.36)
    stand = _solid(_pick(rng, ["#b08d57", "#424242"]))
    return (
        Part("ellipsoid", (0.14, 0.14, 0.14), (globe,)),
        Part("frustum", (0.012, 0.012, 0.05), stand, at=(0.0, 0.0, -0.165)),
        Part("frustum", (0.06, 0.05, 0.012), stand, at=(0.0, 0.0, -0.194)),
    )


def _laptop(rng: np.random.Generator) -> tuple[Part, ...]:
    shell = Material(_pick(rng, ["#9e9e9e", "#2b2b2b", "#c9c9c9"]))
    keys = Material("#333333", "#161616", Pattern.GRID, 0.017, 0.2)
    screen = Material(
        _pick(rng, ["#5a8fd0", "#f0f0f0", "#2e3b4e"]), "#d0dae6", Pattern.STRIPES_T, 0.02, 0.3, emissive=True
    )
    lean = 15.0  # the lid leans back by this much
    c, s = np.cos(np.deg2rad(lean)), np.sin(np.deg2rad(lean))
    lid_y, lid_z = -0.115 - 0.11 * s, -0.09 + 0.11 * c
    return (
        Part("box", (0.33, 0.23, 0.02), (shell,), at=(0.0, 0.0, -0.10)),
        Part("box", (0.28, 0.10, 0.002), (keys,), at=(0.0, 0.03, -0.089)),
        Part("box", (0.33, 0.012, 0.22), (shell,), at=(0.0, lid_y, lid_z), tilt=lean),
        Part(
            "box", (0.29, 0.003, 0.18), (screen,), at=(0.0, lid_y + 0.0075 * c, lid_z + 0.0075 * s), tilt=lean
        ),
    )


def _cell_phone(rng: np.random.Generator) -> tuple[Part, ...]:
    screen = Material("#24466e", "#8fb3d9", Pattern.STRIPES_T, 0.02, 0.25, emissive=True)
    return (
        Part("box", (0.072, 0.148, 0.009), _solid(_pick(rng, ["#111111", "#d9d9d9", "#b0bec5"]))),
        Part("box", (0.064, 0.13, 0.001), (screen,), at=(0.0, 0.0, 0.005)),
    )


def _vase(rng: np.random.Generator) -> tuple[Part, ...]:
    clay = Material(
        _pick(rng, ["#1e88e5", "#8e24aa", "#e57373", "#26a69a"]), "#fafafa", Pattern.STRIPES_T, 0.03, 0.3
    )
    stem = _solid("#33691e")
    bloom = _solid(_pick(rng, ["#ffeb3b", "#f06292", "#ff7043"]))
    return (
        Part("frustum", (0.045, 0.07, 0.09), (clay,), at=(0.0, 0.0, -0.105)),
        Part("frustum", (0.07, 0.035, 0.10), (clay,), at=(0.0, 0.0, -0.01)),
        Part("frustum", (0.035, 0.045, 0.05), (clay,), at=(0.0, 0.0, 0.065)),
        Part("frustum", (0.004, 0.004, 0.12), stem, at=(0.0, 0.0, 0.15)),
        Part("ellipsoid", (0.03, 0.03, 0.02), bloom, at=(-0.02, 0.0, 0.21)),
        Part("ellipsoid", (0.03, 0.03, 0.02), bloom, at=(0.025, 0.01, 0.2)),
    )


def _remote(rng: np.random.Generator) -> tuple[Part, ...]:
    top = Material("#1a1a1a", _pick(rng, ["#9e9e9e", "#e53935"]), Pattern.DOTS, 0.016, 0.28)
    return (Part("box", (0.05, 0.18, 0.02), _faces(Material("#1a1a1a"), top=top)),)


# --- room objects --------------------------------------------------------------------------------


def _refrigerator(rng: np.random.Generator) -> tuple[Part, ...]:
    colour = _pick(rng, ["#eeeeee", "#bdbdbd", "#cfd8dc"])
    door = Material(colour, "#3a3a3a", Pattern.BAND, 0.25, 0.008)
    handle = _solid("#616161")
    return (
        Part("box", (0.70, 0.66, 1.80), _faces(Material(colour), front=door), at=(0.0, -0.30, 0.0)),
        Part("box", (0.03, 0.04, 0.45), handle, at=(0.30, 0.05, 0.55)),
        Part("box", (0.03, 0.04, 0.45), handle, at=(0.30, 0.05, -0.15)),
    )


def _microwave(rng: np.random.Generator) -> tuple[Part, ...]:
    return (
        Part(
            "box",
            (0.50, 0.37, 0.30),
            _solid(_pick(rng, ["#e0e0e0", "#2b2b2b", "#b0b0b0"])),
            at=(0.0, -0.14, 0.0),
        ),
        Part("box", (0.31, 0.004, 0.21), _solid("#151515"), at=(-0.07, 0.047, 0.0)),
        Part(
            "box",
            (0.09, 0.004, 0.22),
            (Material("#cfcfcf", "#333333", Pattern.DOTS, 0.03, 0.25),),
            at=(0.18, 0.047, 0.0),
        ),
    )


def _cake(rng: np.random.Generator) -> tuple[Part, ...]:
    sponge = Material(_pick(rng, ["#f8e1c8", "#6d4c41", "#f8bbd0"]), "#8d4b2a", Pattern.STRIPES_T, 0.04, 0.2)
    icing = Material("#fff3e0", "#c62828", Pattern.DOTS, 0.04, 0.25)
    return (
        Part("frustum", (0.14, 0.14, 0.01), _solid("#fafafa"), at=(0.0, 0.0, -0.075)),
        Part("frustum", (0.11, 0.11, 0.12), (sponge, icing, sponge), at=(0.0, 0.0, -0.01)),
    )


def _donut(rng: np.random.Generator) -> tuple[Part, ...]:
    dough = Material("#d7a86e")
    icing = Material(_pick(rng, ["#f48fb1", "#5d4037", "#fff8e1"]), "#4e342e", Pattern.DISC, 0.018)
    return (
        Part("frustum", (0.09, 0.09, 0.01), _solid("#fafafa"), at=(0.0, 0.0, -0.055)),
        Part("frustum", (0.06, 0.05, 0.055), (dough, icing, dough), at=(0.0, 0.0, -0.0225)),
    )


def _handbag(rng: np.random.Generator) -> tuple[Part, ...]:
    leather = _pick(rng, ["#6d4c41", "#b71c1c", "#212121", "#c19a6b"])
    body = Material(leather, "#d7ccc8", Pattern.BAND, 0.06, 0.01)
    strap = _solid(leather)
    return (
        Part("box", (0.34, 0.14, 0.28), (body,), at=(0.0, 0.0, -0.16)),
        Part("box", (0.015, 0.015, 0.12), strap, at=(-0.1, 0.0, 0.04)),
        Part("box", (0.015, 0.015, 0.12), strap, at=(0.1, 0.0, 0.04)),
        Part("box", (0.215, 0.015, 0.015), strap, at=(0.0, 0.0, 0.0925)),
    )


def _backpack(rng: np.random.Generator) -> tuple[Part, ...]:
    cloth = _pick(rng, ["#1565c0", "#2e7d32", "#c62828", "#212121", "#ff8f00"])
    body = Material(cloth, "#9e9e9e", Pattern.BAND, 0.15, 0.008)
    return (
        Part("box", (0.30, 0.18, 0.44), (body,), at=(0.0, 0.0, -0.03)),
        Part(
            "box",
            (0.24, 0.06, 0.20),
            (Material(cloth, "#9e9e9e", Pattern.BAND, 0.06, 0.006),),
            at=(0.0, 0.115, -0.12),
        ),
        Part("box", (0.08, 0.02, 0.04), _solid("#212121"), at=(0.0, -0.03, 0.21)),
    )


def _person(rng: np.random.Generator) -> tuple[Part, ...]:
    shirt = Material(
        _pick(rng, ["#1e88e5", "#e53935", "#fdd835", "#43a047", "#f5f5f5"]),
        "#263238",
        _pick_pattern(rng),
        0.06,
        0.3,
    )
    trousers = _solid(_pick(rng, ["#283593", "#212121", "#5d4037", "#78909c"]))
    skin = _solid(_pick(rng, ["#f1c27d", "#c68642", "#8d5524", "#ffdbac"]))
    hair = _solid(_pick(rng, ["#2b1d0e", "#6b4226", "#d4b16a", "#9e9e9e"]))
    shoes = _solid("#1b1b1b")
    parts: list[Part] = []
    for side in (-1.0, 1.0):
        parts += [
            Part("box", (0.14, 0.16, 0.86), trousers, at=(side * 0.085, 0.0, -0.67)),
            Part("box", (0.12, 0.26, 0.06), shoes, at=(side * 0.085, 0.04, -1.07)),
            Part("box", (0.09, 0.11, 0.60), (shirt,), at=(side * 0.25, 0.0, 0.06)),
            Part("ellipsoid", (0.045, 0.045, 0.05), skin, at=(side * 0.25, 0.0, -0.27)),
            Part("ellipsoid", (0.012, 0.006, 0.008), shoes, at=(side * 0.035, 0.095, 0.57)),
        ]
    parts += [
        Part("box", (0.40, 0.22, 0.60), (shirt,), at=(0.0, 0.0, 0.07)),
        Part("frustum", (0.05, 0.05, 0.08), skin, at=(0.0, 0.0, 0.41)),
        Part("ellipsoid", (0.085, 0.1, 0.115), skin, at=(0.0, 0.0, 0.55)),
        Part("ellipsoid", (0.09, 0.105, 0.07), hair, at=(0.0, -0.015, 0.62)),
    ]
    return tuple(parts)


def _pick_pattern(rng: np.random.Generator) -> Pattern:
    """A shirt is plain, striped or checked."""
    return (Pattern.SOLID, Pattern.STRIPES_T, Pattern.CHECKER)[int(rng.integers(3))]


# --- furniture that is an object -----------------------------------------------------------------


def _chair(rng: np.random.Generator) -> tuple[Part, ...]:
    """An office chair, backrest to the front (+y)."""
    colour = _pick(rng, ["#212121", "#1a237e", "#424242", "#7f1d1d", "#1b5e20"])
    fabric = (Material(colour, "#5a5a5a", Pattern.CHECKER, 0.012),)
    frame = _solid(_pick(rng, ["#2b2b2b", "#9e9e9e"]))
    parts = [
        Part("box", (0.46, 0.44, 0.06), fabric, at=(0.0, 0.0, -0.31)),
        Part("box", (0.44, 0.05, 0.46), fabric, at=(0.0, 0.22, 0.0)),
        Part("box", (0.05, 0.03, 0.12), frame, at=(0.0, 0.2, -0.25)),
        Part("frustum", (0.025, 0.025, 0.37), frame, at=(0.0, 0.0, -0.525)),
        Part("box", (0.56, 0.045, 0.03), frame, at=(0.0, 0.0, -0.725), yaw=45.0),
        Part("box", (0.56, 0.045, 0.03), frame, at=(0.0, 0.0, -0.725), yaw=-45.0),
    ]
    for side in (-1.0, 1.0):
        parts += [
            Part("box", (0.05, 0.28, 0.03), frame, at=(side * 0.25, 0.0, -0.08)),
            Part("box", (0.03, 0.03, 0.2), frame, at=(side * 0.25, 0.0, -0.19)),
        ]
    return tuple(parts)


def _diningtable(rng: np.random.Generator) -> tuple[Part, ...]:
    """A desk (the world's point is the middle of its underside), modesty panel at the back (-y)."""
    wood, grain = [("#c8a165", "#b08850"), ("#e6e2da", "#d9d4ca"), ("#8d8d8d", "#7d7d7d")][
        int(rng.integers(3))
    ]
    top = Material(wood, grain, Pattern.STRIPES_S, 0.04, 0.25)
    metal = _solid("#555555")
    parts = [
        Part("box", (1.40, 0.80, 0.03), _faces(Material(grain), top=top), at=(0.0, 0.0, 0.015)),
        Part("box", (1.30, 0.02, 0.40), _solid(grain), at=(0.0, -0.37, -0.25)),
    ]
    parts += [
        Part("box", (0.05, 0.05, 0.72), metal, at=(x, y, -0.36)) for x in (-0.66, 0.66) for y in (-0.36, 0.36)
    ]
    return tuple(parts)


#: The shape of every class the office world uses (by YOLO name).
CLASS_SHAPES: dict[str, Shape] = {
    "tvmonitor": _tvmonitor,
    "keyboard": _keyboard,
    "mouse": _mouse,
    "cup": _cup,
    "bottle": _bottle,
    "book": _book,
    "chair": _chair,
    "diningtable": _diningtable,
    "teddy bear": _teddy_bear,
    "bowl": _bowl,
    "spoon": _spoon,
    "knife": _knife,
    "fork": _fork,
    "scissors": _scissors,
    "sports ball": _sports_ball,
    "laptop": _laptop,
    "cell phone": _cell_phone,
    "vase": _vase,
    "remote": _remote,
    "refrigerator": _refrigerator,
    "microwave": _microwave,
    "cake": _cake,
    "donut": _donut,
    "handbag": _handbag,
    "backpack": _backpack,
    "person": _person,
}
# Groups whose books stand upright.
_SHELF_GROUPS = frozenset({"bookshelf"})


def _shape_of(world: OfficeWorld, k: int, rng: np.random.Generator) -> tuple[Part, ...]:
    label = world.label_of(k)
    if label == "book" and world.groups[k] in _SHELF_GROUPS:
        return _standing_book(rng)
    try:
        shape = CLASS_SHAPES[label]
    except KeyError:
        raise ConfigError(
            f"the renderer has no shape for class {label!r} (object {k}, {world.groups[k]}); "
            f"known classes: {', '.join(sorted(CLASS_SHAPES))}"
        ) from None
    return shape(rng)


def _object_frames(world: OfficeWorld, rng: np.random.Generator) -> FloatArray:
    """Object-to-world rotations (``n x 3 x 3``, columns: across, front, up) of the world's objects.

    The front is ``facing`` where the world gives one, the user's side (away
    from the block's middle row line) for desk objects, and the centre of the
    room otherwise; each instance is then turned by a small random yaw.
    """
    rotations = np.empty((len(world), 3, 3))
    for k in range(len(world)):
        p = world.positions[k]
        if np.any(world.facing[k] != 0.0):
            front = world.facing[k, :2]
        elif world.groups[k].startswith("desk"):
            front = np.array([0.0, 1.0 if p[1] >= 0.0 else -1.0])
        elif np.hypot(p[0], p[1]) > 1e-9:
            front = -p[:2]
        else:
            front = np.array([0.0, 1.0])
        jitter = _YAW_JITTER_DEG.get(world.label_of(k), _DEFAULT_YAW_JITTER_DEG)
        angle = np.arctan2(front[1], front[0]) + np.deg2rad(rng.uniform(-jitter, jitter))
        f = np.array([np.cos(angle), np.sin(angle), 0.0])
        up = np.array([0.0, 0.0, 1.0])
        rotations[k] = np.stack([np.cross(f, up), f, up], axis=1)
    return rotations


def build_scene(
    world: OfficeWorld,
    rng: np.random.Generator,
    room_points: FloatArray | None = None,
    lighting: Lighting | None = None,
) -> Scene:
    """All triangles of ``world``'s objects (object index = world index), its furniture and room.

    The room encloses the objects and ``room_points`` (``n x 3``, for
    example the camera path) with a margin.
    """
    builder = SceneBuilder(lighting or Lighting())
    rotations = _object_frames(world, rng)
    members: dict[str, list[FloatArray]] = {}
    for k in range(len(world)):
        shape = _shape_of(world, k, rng)
        verts = [builder.add_part(part, rotations[k], world.positions[k], k) for part in shape]
        members.setdefault(world.groups[k], []).append(np.concatenate(verts).reshape(-1, 3))
    for group, objects in members.items():
        if group in _FURNITURE:
            for part in _FURNITURE[group](objects, rng):
                builder.add_part(part, np.eye(3), np.zeros(3), -1)
    points = world.positions if room_points is None else np.concatenate([world.positions, room_points])
    for part in _room(points, rng):
        builder.add_part(part, np.eye(3), np.zeros(3), -1)
    return builder.build(len(world))


# --- furniture implied by the world's groups -----------------------------------------------------


def _footprint(points: FloatArray, margin: float) -> tuple[FloatArray, FloatArray]:
    return points[:, :2].min(axis=0) - margin, points[:, :2].max(axis=0) + margin


def _side_table(objects: list[FloatArray], rng: np.random.Generator) -> list[Part]:
    points = np.concatenate(objects)
    lo, hi = _footprint(points, 0.12)
    top = float(points[:, 2].min())
    centre, size = (lo + hi) / 2, hi - lo
    wood = _solid(_pick(rng, ["#8d6e63", "#d7ccc8", "#5d4037"]))
    parts = [Part("box", (size[0], size[1], 0.03), wood, at=(centre[0], centre[1], top - 0.015))]
    for sx in (-1.0, 1.0):
        for sy in (-1.0, 1.0):
            at = (
                centre[0] + sx * (size[0] / 2 - 0.04),
                centre[1] + sy * (size[1] / 2 - 0.04),
                (top - 0.03) / 2,
            )
            parts.append(Part("box", (0.04, 0.04, top - 0.03), wood, at=at))
    return parts


def _counter(objects: list[FloatArray], rng: np.random.Generator) -> list[Part]:
    points = np.concatenate(objects)
    lo, hi = _footprint(points, 0.12)
    top = float(points[:, 2].min())
    centre, size = (lo + hi) / 2, hi - lo
    doors = Material(_pick(rng, ["#eceff1", "#8d6e63", "#546e7a"]), "#37474f", Pattern.STRIPES_S, 0.5, 0.02)
    stone = Material("#9e9e9e", "#8a8a8a", Pattern.CHECKER, 0.05)
    return [
        Part("box", (size[0], size[1], top), _faces(doors, top=stone), at=(centre[0], centre[1], top / 2))
    ]


def _bookshelf(objects: list[FloatArray], rng: np.random.Generator) -> list[Part]:
    """A board under each level of books, a top and a base, two sides and a back on the side away
    from the room's middle."""
    points = np.concatenate(objects)
    lo, hi = _footprint(points, 0.06)
    centre, size = (lo + hi) / 2, hi - lo
    wood = _solid(_pick(rng, ["#a1887f", "#6d4c41", "#eeeeee"]))
    # Books of one level share their bottom (to the centimetre).
    levels = np.unique(np.round([obj[:, 2].min() for obj in objects], 2))
    height = float(points[:, 2].max()) + 0.12
    boards = [*levels.tolist(), 0.08, height]
    parts = [Part("box", (size[0], size[1], 0.02), wood, at=(centre[0], centre[1], z - 0.01)) for z in boards]
    along = 0 if size[0] >= size[1] else 1  # the shelf's long axis
    across = 1 - along
    back_sign = 1.0 if centre[across] >= 0.0 else -1.0  # the back faces away from the room's middle
    for side in (-1.0, 1.0):
        at = centre.copy()
        at[along] += side * size[along] / 2
        side_size = [0.02, 0.02, height]
        side_size[across] = size[across]
        parts.append(Part("box", (side_size[0], side_size[1], height), wood, at=(at[0], at[1], height / 2)))
    back = centre.copy()
    back[across] += back_sign * size[across] / 2
    back_size = [0.02, 0.02, height]
    back_size[along] = size[along]
    parts.append(Part("box", (back_size[0], back_size[1], height), wood, at=(back[0], back[1], height / 2)))
    return parts


_FURNITURE: dict[str, Callable[[list[FloatArray], np.random.Generator], list[Part]]] = {
    "side table": _side_table,
    "counter": _counter,
    "bookshelf": _bookshelf,
}


def _room(points: FloatArray, rng: np.random.Generator) -> list[Part]:
    """Floor, ceiling and four walls around ``points``, with a door, a whiteboard, windows, posters, lamps."""
    lo, hi = _footprint(points, _ROOM_MARGIN_M)
    centre, size = (lo + hi) / 2, hi - lo
    h = _ROOM_HEIGHT_M
    carpet = Material(_pick(rng, ["#5f6b73", "#6d6258", "#4f5d4a"]), "#56616a", Pattern.CHECKER, 0.5)
    tiles = Material("#e8e8e4", "#b8b8b4", Pattern.GRID, 0.6, 0.03)
    parts = [
        Part("box", (size[0] + 0.2, size[1] + 0.2, 0.1), (carpet,), at=(centre[0], centre[1], -0.05)),
        Part("box", (size[0] + 0.2, size[1] + 0.2, 0.1), (tiles,), at=(centre[0], centre[1], h + 0.05)),
    ]
    paints = ["#dcd6c8", "#c9d6df", "#e6dccb", "#d5e0cf", "#e0d0d0", "#cfcfcf"]
    rng.shuffle(paints)
    # (outward axis, sign): the wall's inner face and the yaw that turns a decoration's +y into the room.
    walls = ((0, -1.0, -90.0), (0, 1.0, 90.0), (1, -1.0, 0.0), (1, 1.0, 180.0))
    decorations = (_door, _whiteboard, _windows, _posters)
    for (axis, sign, yaw), paint, decorate in zip(walls, paints, decorations, strict=False):
        wall = Material(paint, "#6b5e50", Pattern.BAND, -h / 2 + 0.05, 0.05)
        at = centre.copy()
        at[axis] += sign * (size[axis] / 2 + 0.05)
        wall_size = [size[0] + 0.2, size[1] + 0.2, h]
        wall_size[axis] = 0.1
        parts.append(Part("box", (wall_size[0], wall_size[1], h), (wall,), at=(at[0], at[1], h / 2)))
        length = size[1 - axis]
        face = at.copy()
        face[axis] -= sign * 0.05
        for offset, part in decorate(rng, length):
            pos = face.copy()
            pos[1 - axis] += offset
            pos[axis] -= sign * part.size[1] / 2
            parts.append(Part(part.shape, part.size, part.look, at=(pos[0], pos[1], part.at[2]), yaw=yaw))
    for x in np.arange(lo[0] + 1.2, hi[0] - 0.6, 2.4):
        for y in np.arange(lo[1] + 1.2, hi[1] - 0.6, 2.4):
            parts.append(Part("box", (0.6, 0.6, 0.02), _solid("#fffbe8", emissive=True), at=(x, y, h - 0.01)))
    return parts


def _along_wall(rng: np.random.Generator, length: float, width: float) -> float:
    """A random offset from the wall's middle that keeps a ``width`` decoration off the corners."""
    room = max(0.0, length / 2 - width / 2 - 0.8)
    return float(rng.uniform(-room, room))


def _door(rng: np.random.Generator, length: float) -> list[tuple[float, Part]]:
    wood = Material(_pick(rng, ["#6d4c41", "#a1887f", "#eeeeee"]), "#3e2723", Pattern.BAND, 0.05, 0.015)
    return [(_along_wall(rng, length, 0.95), Part("box", (0.95, 0.05, 2.05), (wood,), at=(0.0, 0.0, 1.025)))]


def _whiteboard(rng: np.random.Generator, length: float) -> list[tuple[float, Part]]:
    board = Material("#9e9e9e", "#fafafa", Pattern.FRAME, 0.77, 0.47)
    return [(_along_wall(rng, length, 1.6), Part("box", (1.6, 0.03, 1.0), (board,), at=(0.0, 0.0, 1.45)))]


def _windows(rng: np.random.Generator, length: float) -> list[tuple[float, Part]]:
    glass = Material("#cfe3f5", "#f4f4f4", Pattern.GRID, 0.7, 0.04, emissive=True)
    middle = _along_wall(rng, length, 3.2)
    return [(middle + dx, Part("box", (1.4, 0.03, 1.2), (glass,), at=(0.0, 0.0, 1.55))) for dx in (-0.8, 0.8)]


def _posters(rng: np.random.Generator, length: float) -> list[tuple[float, Part]]:
    out = []
    for _ in range(2):
        art = Material(
            _pick(rng, ["#ef5350", "#42a5f5", "#66bb6a", "#ffca28", "#ab47bc"]),
            _pick(rng, ["#263238", "#fafafa", "#ff7043"]),
            _pick_pattern(rng),
            float(rng.uniform(0.08, 0.2)),
            0.5,
        )
        out.append(
            (_along_wall(rng, length, 0.6), Part("box", (0.6, 0.02, 0.85), (art,), at=(0.0, 0.0, 1.5)))
        )
    return out
