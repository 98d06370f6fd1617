"""A procedural renderer of the street's 19 landmark facades, as a robot's camera sees them.

The paper trains a 5-layer CNN on 7055 Gazebo images of its 19 buildings and tests it
on 3036 (84 % correct; 68 % in the swarm, whose views are more varied). The paper
gives no image size; we use 64 x 64 RGB, enough for window grids and roofs, small
enough for a robot's CNN. The same renderer makes the CNN's training set and the
simulator's views, so its difficulty is the knob that sets the single-robot rate.

A class is a :class:`FacadeDesign`: a combination of wall colour, wall texture, floor
and window-column counts, window shape, door layout, roof, building height and accent
colour. The 19 designs come from a palette shared by all classes and every two of them
differ in at least three attributes, so no single cue (colour alone, say) separates
them. A render draws the facade between two generic neighbouring buildings, with
per-render jitter of colours, lit windows and proportions, then warps it with the
pinhole projection of a camera at the given distance and viewing angle (the
conventions of :mod:`swarmrec.fusion.street`), and adds lighting, haze, occluders
(trees, poles, cars, people), blur and sensor noise. Hard views come for free: far
views leave the facade a few pixels wide, near views show only part of it, oblique
views compress it, and occluders hide up to about half of it. Everything is drawn
from the seed, so a (landmark, view, seed) triple always gives the same image.

Calibration (no CNN can be trained here): a stand-in, 1600 k-means filter features and
a linear read-out (Coates and Ng's single-layer network, which scores close to small
CNNs), trained on 7068 views of :func:`render_dataset` gets 84 % of 3040 held-out
views right, and 86 % of the 1180 robots of the 118 default street configurations.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import numpy.typing as npt

from swarmrec.errors import ConfigError
from swarmrec.fusion.wnbc import N_LANDMARKS

__all__ = [
    "FACADE_DESIGNS",
    "IMAGE_SIZE",
    "FacadeDesign",
    "RenderSettings",
    "View",
    "render_dataset",
    "render_view",
    "sample_view",
    "write_preview",
]

ImageArray = npt.NDArray[np.uint8]
#: An int, a sequence of ints (e.g. ``(configuration, robot)``) or a Generator to draw from.
Seed = int | Sequence[int] | np.random.Generator

#: Side of the square images, pixels.
IMAGE_SIZE = 64
#: Facade width in metres (the street's facades) and the canvas resolution it is drawn at.
_FACADE_M = 12.0
_PX_PER_M = 16.0
_TW = int(_FACADE_M * _PX_PER_M)  # facade width on the canvas, px
_SKY = 96  # sky band above the tallest roof, px
_GROUND = 48  # pavement band below the facade, px
#: Horizontal field of view of the robots' camera.
_FOV = math.radians(70.0)
#: Render at this multiple of the output size, then shrink: cheap antialiasing.
_SUPERSAMPLE = 2

# Wall and accent colours (RGB), shared by all classes.
_PALETTE: tuple[tuple[int, int, int], ...] = (
    (150, 70, 55),  # brick red
    (215, 200, 165),  # sand
    (140, 140, 135),  # concrete grey
    (120, 150, 170),  # slate blue
    (200, 160, 70),  # ochre
    (230, 228, 220),  # off-white
    (95, 75, 60),  # dark brown
    (110, 140, 95),  # sage green
)
Texture = Literal["plain", "brick", "siding", "panels"]
Window = Literal["rect", "arched", "tall", "square"]
Door = Literal["left", "centre", "right", "shop"]
Roof = Literal["flat", "cornice", "gable", "mansard"]
_TEXTURES: tuple[Texture, ...] = ("plain", "brick", "siding", "panels")
_WINDOWS: tuple[Window, ...] = ("rect", "arched", "tall", "square")
_DOORS: tuple[Door, ...] = ("left", "centre", "right", "shop")
_ROOFS: tuple[Roof, ...] = ("flat", "cornice", "gable", "mansard")
_HEIGHTS: tuple[float, ...] = (0.7, 0.85, 1.0)


@dataclass(frozen=True)
class FacadeDesign:
    """The fixed look of one landmark class."""

    wall: int
    texture: Texture
    floors: int
    columns: int
    window: Window
    door: Door
    roof: Roof
    height: float
    accent: int

    def attributes(self) -> tuple[object, ...]:
        return (
            self.wall,
            self.texture,
            self.floors,
            self.columns,
            self.window,
            self.door,
            self.roof,
            self.height,
            self.accent,
        )


def _make_designs(n: int, min_differences: int = 3, seed: int = 19) -> tuple[FacadeDesign, ...]:
    """``n`` designs drawn at random, each differing from every earlier one in at least
    ``min_differences`` attributes: distinct classes that still share most cues."""
    rng = np.random.default_rng(seed)
    designs: list[FacadeDesign] = []
    while len(designs) < n:
        wall, accent = (int(v) for v in rng.choice(len(_PALETTE), 2, replace=False))
        candidate = FacadeDesign(
            wall=wall,
            texture=_TEXTURES[int(rng.integers(len(_TEXTURES)))],
            floors=int(rng.integers(2, 6)),
            columns=int(rng.integers(2, 7)),
            window=_WINDOWS[int(rng.integers(len(_WINDOWS)))],
            door=_DOORS[int(rng.integers(len(_DOORS)))],
            roof=_ROOFS[int(rng.integers(len(_ROOFS)))],
            height=_HEIGHTS[int(rng.integers(len(_HEIGHTS)))],
            accent=accent,
        )
        if all(
            sum(a != b for a, b in zip(candidate.attributes(), d.attributes(), strict=True))
            >= min_differences
            for d in designs
        ):
            designs.append(candidate)
    return tuple(designs)


#: The look of landmark ``k`` is ``FACADE_DESIGNS[k]``.
FACADE_DESIGNS: tuple[FacadeDesign, ...] = _make_designs(N_LANDMARKS)


@dataclass(frozen=True)
class View:
    """Where the camera is, in the conventions of :class:`swarmrec.fusion.street.Sighting`:
    ``distance`` (m) along the optical axis to the facade, ``view_angle`` (rad, 0 =
    head-on, positive = turned towards the facade's right) and ``offset`` of the hit
    point along the facade (-0.5 left edge .. 0.5 right edge)."""

    distance: float
    view_angle: float
    offset: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.distance) and self.distance > 0):
            raise ConfigError(f"view distance must be > 0 m, got {self.distance}")
        if not abs(self.view_angle) < math.radians(89.0):
            raise ConfigError(f"view angle must be within +-89 degrees, got {math.degrees(self.view_angle)}")
        if not math.isfinite(self.offset):
            raise ConfigError(f"view offset must be finite, got {self.offset}")


@dataclass(frozen=True)
class RenderSettings:
    """The nuisances of a render; the defaults aim a small CNN at 80-90 % held-out accuracy."""

    size: int = IMAGE_SIZE
    #: Probability that a render has occluders in front of the facade.
    occlusion: float = 0.65
    #: Gain range of the global illumination (1 = as drawn).
    light: tuple[float, float] = (0.4, 1.45)
    #: Range of the standard deviation of the sensor noise (0-255 scale).
    noise: tuple[float, float] = (4.0, 18.0)
    #: Largest colour jitter of the walls, per channel (0-255 scale).
    colour_jitter: float = 30.0
    #: Largest vertical tilt of the camera: where on the facade's height the axis hits.
    tilt: float = 0.15
    #: Probability of a defocus or motion blur.
    blur: float = 0.4
    #: Whether distance adds haze (air between camera and facade).
    haze: bool = True

    def __post_init__(self) -> None:
        if self.size < 8:
            raise ConfigError(f"image size must be >= 8, got {self.size}")
        for name in ("occlusion", "blur"):
            if not 0 <= getattr(self, name) <= 1:
                raise ConfigError(f"{name} must be a probability, got {getattr(self, name)}")
        if not 0 < self.light[0] <= self.light[1]:
            raise ConfigError(f"light must be 0 < low <= high, got {self.light}")
        if not 0 <= self.noise[0] <= self.noise[1]:
            raise ConfigError(f"noise must be 0 <= low <= high, got {self.noise}")


def _rng(seed: Seed) -> np.random.Generator:
    return seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)


def _jitter(rng: np.random.Generator, colour: tuple[int, int, int], amount: float) -> tuple[int, int, int]:
    c = np.clip(np.asarray(colour, np.float64) + rng.uniform(-amount, amount, 3), 0, 255)
    return (int(c[0]), int(c[1]), int(c[2]))


def _shade(colour: tuple[int, int, int], factor: float) -> tuple[int, int, int]:
    c = np.clip(np.asarray(colour, np.float64) * factor, 0, 255)
    return (int(c[0]), int(c[1]), int(c[2]))


def _draw_texture(
    canvas: ImageArray, texture: Texture, x0: int, y0: int, x1: int, y1: int, wall: tuple[int, int, int]
) -> None:
    line = _shade(wall, 0.78)
    if texture == "brick":
        for row, y in enumerate(range(y0, y1, 6)):
            cv2.line(canvas, (x0, y), (x1, y), line, 1)
            for x in range(x0 + (row % 2) * 8, x1, 16):
                cv2.line(canvas, (x, y), (x, min(y + 6, y1)), line, 1)
    elif texture == "siding":
        for y in range(y0, y1, 10):
            cv2.line(canvas, (x0, y), (x1, y), line, 2)
    elif texture == "panels":
        for x in range(x0, x1, 48):
            cv2.line(canvas, (x, y0), (x, y1), line, 2)
        for y in range(y0, y1, 40):
            cv2.line(canvas, (x0, y), (x1, y), line, 2)


def _draw_window(
    canvas: ImageArray,
    shape: Window,
    cx: int,
    cy: int,
    w: int,
    h: int,
    glass: tuple[int, int, int],
    frame: tuple[int, int, int],
) -> None:
    if shape == "tall":
        w, h = max(4, int(w * 0.6)), int(h * 1.25)
    elif shape == "square":
        h = w
    x0, y0, x1, y1 = cx - w // 2, cy - h // 2, cx + w // 2, cy + h // 2
    cv2.rectangle(canvas, (x0 - 2, y0 - 2), (x1 + 2, y1 + 2), frame, -1)
    cv2.rectangle(canvas, (x0, y0), (x1, y1), glass, -1)
    if shape == "arched":
        cv2.ellipse(canvas, (cx, y0), (w // 2 + 2, w // 2 + 2), 0, 180, 360, frame, -1)
        cv2.ellipse(canvas, (cx, y0), (w // 2, w // 2), 0, 180, 360, glass, -1)
    cv2.line(canvas, (cx, y0), (cx, y1), frame, 1)
    if shape != "tall":
        cv2.line(canvas, (x0, cy), (x1, cy), frame, 1)


def _draw_building(
    rng: np.random.Generator,
    canvas: ImageArray,
    design: FacadeDesign,
    x0: int,
    ground_y: int,
    width: int,
    colour_jitter: float,
) -> None:
    """One facade, its bottom-left corner at ``(x0, ground_y)`` on the canvas."""
    height = int(design.height * _TW * rng.uniform(0.95, 1.05))
    top = ground_y - height
    wall = _jitter(rng, _PALETTE[design.wall], colour_jitter)
    accent = _jitter(rng, _PALETTE[design.accent], colour_jitter)
    x1 = x0 + width
    cv2.rectangle(canvas, (x0, top), (x1, ground_y), wall, -1)
    _draw_texture(canvas, design.texture, x0, top, x1, ground_y, wall)
    # Roof.
    if design.roof == "cornice":
        cv2.rectangle(canvas, (x0 - 6, top - 10), (x1 + 6, top + 4), accent, -1)
    elif design.roof == "gable":
        peak = (x0 + width // 2, top - int(0.3 * width))
        cv2.fillPoly(canvas, [np.array([(x0 - 6, top), peak, (x1 + 6, top)], np.int32)], accent)
    elif design.roof == "mansard":
        pts = [(x0 - 4, top), (x0 + 18, top - 34), (x1 - 18, top - 34), (x1 + 4, top)]
        cv2.fillPoly(canvas, [np.array(pts, np.int32)], _shade(accent, 0.7))
        for cx in np.linspace(x0 + 36, x1 - 36, max(design.columns - 1, 1)).astype(int).tolist():
            cv2.rectangle(canvas, (cx - 6, top - 26), (cx + 6, top - 8), (70, 80, 95), -1)
    else:  # flat: a thin parapet line
        cv2.rectangle(canvas, (x0, top), (x1, top + 3), _shade(wall, 0.6), -1)
    # Ground floor: door or shop front, in the accent colour.
    floor_h = height / (design.floors + 1)
    door_w, door_h = int(0.12 * width), int(0.8 * floor_h)
    shop = design.door == "shop"
    if shop:
        cv2.rectangle(canvas, (x0 + 8, ground_y - door_h), (x1 - 8, ground_y), accent, -1)
        cv2.rectangle(canvas, (x0 + 14, ground_y - door_h + 8), (x1 - 14, ground_y - 4), (60, 75, 90), -1)
        awning = _shade(accent, 0.8)
        cv2.rectangle(canvas, (x0 + 4, ground_y - door_h - 10), (x1 - 4, ground_y - door_h), awning, -1)
    else:
        where = {"left": 0.2, "centre": 0.5, "right": 0.8}[design.door]
        dcx = x0 + int(where * width)
        cv2.rectangle(
            canvas, (dcx - door_w // 2, ground_y - door_h), (dcx + door_w // 2, ground_y), accent, -1
        )
        cv2.line(canvas, (dcx, ground_y - door_h), (dcx, ground_y), _shade(accent, 0.6), 1)
    # Windows on the upper floors (and beside the door on the ground floor).
    frame = (235, 235, 230) if design.accent % 2 == 0 else (45, 45, 50)
    win_w = int(0.55 * width / (design.columns + 1))
    win_h = int(0.55 * floor_h)
    xs = np.linspace(x0, x1, design.columns + 2)[1:-1]
    for floor in range(1, design.floors + 1):
        cy = int(ground_y - (floor + 0.5) * floor_h)
        for cx in xs.tolist():
            lit = rng.random() < 0.25
            glass = _jitter(rng, (230, 210, 140) if lit else (70, 95, 120), 25)
            _draw_window(canvas, design.window, int(cx), cy, win_w, win_h, glass, frame)
    if not shop:
        cy = int(ground_y - 0.55 * floor_h)
        for cx in xs.tolist():
            if abs(cx - (x0 + {"left": 0.2, "centre": 0.5, "right": 0.8}[design.door] * width)) > door_w:
                _draw_window(canvas, "square", int(cx), cy, win_w, win_w, (70, 95, 120), frame)


def _draw_filler(rng: np.random.Generator, canvas: ImageArray, x0: int, x1: int, ground_y: int) -> None:
    """A generic neighbouring building: plain wall and a loose window grid, no class cue."""
    height = int(rng.uniform(0.5, 1.05) * _TW)
    wall = _jitter(rng, _PALETTE[int(rng.integers(len(_PALETTE)))], 30)
    cv2.rectangle(canvas, (x0, ground_y - height), (x1, ground_y), wall, -1)
    rows, step = int(rng.integers(2, 5)), int(rng.integers(24, 48))
    for r in range(rows):
        y = ground_y - int((r + 1.3) * height / (rows + 1))
        for x in range(x0 + step // 2, x1 - 8, step):
            cv2.rectangle(canvas, (x, y), (x + step // 3, y + 14), _shade(wall, 0.55), -1)


def _scene(rng: np.random.Generator, design: FacadeDesign, s: RenderSettings) -> tuple[ImageArray, int]:
    """The flat street wall: filler, the landmark, filler; sky above and pavement below.
    Returns the canvas and the row of the facade's base."""
    # Two filler buildings each side of the landmark, so oblique views see a street, not
    # the canvas edge smeared out.
    width = 5 * _TW
    height = _SKY + _TW + _GROUND
    canvas = np.zeros((height, width, 3), np.uint8)
    sky_top = np.array(_jitter(rng, (120, 160, 215), 30), np.float64)
    sky_bottom = np.array(_jitter(rng, (200, 215, 230), 20), np.float64)
    t = np.linspace(0.0, 1.0, _SKY + _TW)[:, None, None]
    canvas[: _SKY + _TW] = (sky_top * (1 - t) + sky_bottom * t).astype(np.uint8)
    ground_y = _SKY + _TW
    canvas[ground_y:] = _jitter(rng, (105, 105, 110), 20)
    gap = int(2.0 * _PX_PER_M / 2)  # half the 2 m gap between facades, on each side
    for k in (0, 1, 3, 4):
        _draw_filler(rng, canvas, k * _TW + gap, (k + 1) * _TW - gap, ground_y)
    _draw_building(rng, canvas, design, 2 * _TW, ground_y, _TW, s.colour_jitter)
    return canvas, ground_y


def _draw_occluders(rng: np.random.Generator, img: ImageArray) -> None:
    """Things between the camera and the facade: trees, poles, parked cars, people."""
    n = img.shape[0]
    for _ in range(int(rng.integers(1, 4))):
        kind = int(rng.integers(4))
        cx = int(rng.uniform(0.0, 1.0) * n)
        if kind == 0:  # tree: trunk and a ragged crown
            trunk = _jitter(rng, (90, 65, 45), 15)
            cv2.rectangle(img, (cx - n // 40, n // 2), (cx + n // 40, n), trunk, -1)
            leaf = _jitter(rng, (60, 110, 50), 25)
            for _ in range(6):
                c = (cx + int(rng.normal(0, n * 0.08)), int(n * rng.uniform(0.15, 0.5)))
                cv2.circle(img, c, int(n * rng.uniform(0.08, 0.18)), leaf, -1)
        elif kind == 1:  # pole or lamp post
            cv2.rectangle(
                img, (cx, int(n * rng.uniform(0, 0.3))), (cx + max(2, n // 30), n), (50, 50, 55), -1
            )
        elif kind == 2:  # parked car
            body = _jitter(rng, _PALETTE[int(rng.integers(len(_PALETTE)))], 40)
            w, h = int(n * rng.uniform(0.35, 0.7)), int(n * rng.uniform(0.18, 0.3))
            cv2.rectangle(img, (cx - w // 2, n - h), (cx + w // 2, n), body, -1)
            cv2.rectangle(img, (cx - w // 3, n - h - h // 2), (cx + w // 3, n - h), _shade(body, 0.6), -1)
        else:  # pedestrian
            coat = _jitter(rng, (80, 80, 90), 60)
            h = int(n * rng.uniform(0.3, 0.6))
            cv2.rectangle(img, (cx - n // 20, n - h), (cx + n // 20, n), coat, -1)
            cv2.circle(img, (cx, n - h - n // 25), max(2, n // 25), (200, 160, 130), -1)


def render_view(landmark: int, view: View, seed: Seed, settings: RenderSettings | None = None) -> ImageArray:
    """What a camera at ``view`` sees of ``landmark``: an RGB ``size x size x 3`` uint8 image.

    The same landmark, view and seed (ints, or a Generator in the same state) always
    give the same image.
    """
    if not 0 <= landmark < len(FACADE_DESIGNS):
        raise ConfigError(f"landmark must be in [0, {len(FACADE_DESIGNS)}), got {landmark}")
    s = settings or RenderSettings()
    rng = _rng(seed)
    canvas, ground_y = _scene(rng, FACADE_DESIGNS[landmark], s)

    out = s.size * _SUPERSAMPLE
    f = (out / 2) / math.tan(_FOV / 2)
    theta, d = view.view_angle, view.distance
    # Canvas pixel -> metres on the wall, relative to the hit point.
    hit_u = _TW * (2.5 + float(np.clip(view.offset, -0.5, 0.5)))
    hit_v = ground_y - _TW * float(np.clip(0.45 + rng.uniform(-s.tilt, s.tilt), 0.05, 0.95))
    # Keep only wall points in front of the camera: z = d + x sin(theta) > 5 % of d.
    x_lo, x_hi = -hit_u / _PX_PER_M, (canvas.shape[1] - hit_u) / _PX_PER_M
    if theta > 0:
        x_lo = max(x_lo, -0.95 * d / math.sin(theta))
    elif theta < 0:
        x_hi = min(x_hi, 0.95 * d / -math.sin(theta))
    c0, c1 = math.ceil(hit_u + x_lo * _PX_PER_M), math.floor(hit_u + x_hi * _PX_PER_M)
    crop = canvas[:, c0:c1]
    # Blur before shrinking so that far facades do not alias into moire.
    shrink = _PX_PER_M * d / f
    if shrink > 1.2:
        crop = np.asarray(cv2.GaussianBlur(crop, (0, 0), 0.45 * shrink), np.uint8)

    def project(u: float, v: float) -> tuple[float, float]:
        x, y = (u - hit_u) / _PX_PER_M, (v - hit_v) / _PX_PER_M
        z = d + x * math.sin(theta)
        return f * x * math.cos(theta) / z + out / 2, f * y / z + out / 2

    h = crop.shape[0]
    src = np.array([(0, 0), (c1 - c0, 0), (c1 - c0, h), (0, h)], np.float32)
    dst = np.array([project(c0, 0), project(c1, 0), project(c1, h), project(c0, h)], np.float32)
    homography = cv2.getPerspectiveTransform(src, dst)
    warped = cv2.warpPerspective(
        crop, homography, (out, out), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )
    img = np.asarray(cv2.resize(warped, (s.size, s.size), interpolation=cv2.INTER_AREA), np.uint8)
    if rng.random() < s.occlusion:
        _draw_occluders(rng, img)
    return _photometric(rng, img, d, s)


def _photometric(rng: np.random.Generator, img: ImageArray, distance: float, s: RenderSettings) -> ImageArray:
    """Light, haze, a soft shadow, blur and sensor noise."""
    n = img.shape[0]
    x = img.astype(np.float64) / 255.0
    haze = min(0.5, distance / 60.0) * rng.uniform(0.3, 1.0) if s.haze else 0.0
    x = x * (1 - haze) + haze * np.array([0.8, 0.83, 0.88])
    x = x * rng.uniform(*s.light) * rng.uniform(0.88, 1.12, 3)
    ramp = np.linspace(0.0, 1.0, n)
    direction = rng.uniform(0, 2 * math.pi)
    shadow = np.cos(direction) * ramp[None, :] + np.sin(direction) * ramp[:, None]
    shadow = 1.0 - rng.uniform(0.0, 0.45) * (shadow - shadow.min()) / (np.ptp(shadow) + 1e-9)
    x = np.clip(x * shadow[:, :, None], 0, 1) ** rng.uniform(0.8, 1.25)
    if rng.random() < s.blur:
        x = cv2.GaussianBlur(x, (0, 0), rng.uniform(0.5, 1.5))
    x = x * 255.0 + rng.normal(0.0, rng.uniform(*s.noise), x.shape)
    image: ImageArray = np.clip(np.rint(x), 0, 255).astype(np.uint8)
    return image


def sample_view(rng: np.random.Generator) -> View:
    """A random view as a robot in the street gets them: the camera stands 1-13 m in front
    of the facade's wall (the street is 14 m wide), anywhere from 7 m left of the facade
    to 7 m right of it, and aims at a point of the facade, as the robots of
    :mod:`swarmrec.fusion.street` do. Near, far and oblique views all occur; views
    beyond 25 m or more oblique than 80 degrees are drawn again."""
    while True:
        standoff = rng.uniform(1.0, 13.0)
        camera = rng.uniform(-0.5, 0.5) * _FACADE_M + rng.uniform(-7.0, 7.0)
        aim = rng.uniform(-0.45, 0.45) * _FACADE_M
        distance = math.hypot(standoff, aim - camera)
        angle = math.atan2(aim - camera, standoff)
        if distance <= 25.0 and abs(angle) <= math.radians(80.0):
            return View(distance, angle, aim / _FACADE_M)


def render_dataset(
    per_class: int, seed: int, settings: RenderSettings | None = None
) -> tuple[ImageArray, npt.NDArray[np.int64], tuple[View, ...]]:
    """``per_class`` random views of every landmark: images ``(N, size, size, 3)`` uint8,
    labels ``(N,)`` and the views, class-interleaved. Distinct seeds give disjoint draws
    (use one seed for training and another for testing)."""
    rng = np.random.default_rng(seed)
    images, labels, views = [], [], []
    for _, landmark in itertools.product(range(per_class), range(len(FACADE_DESIGNS))):
        view = sample_view(rng)
        images.append(render_view(landmark, view, rng, settings))
        labels.append(landmark)
        views.append(view)
    size = (settings or RenderSettings()).size
    stack = np.stack(images) if images else np.zeros((0, size, size, 3), np.uint8)
    return stack, np.array(labels, np.int64), tuple(views)


def write_preview(
    path: str | Path, seed: int = 0, views_per_class: int = 6, settings: RenderSettings | None = None
) -> Path:
    """A PNG grid, one row per landmark: a clean head-on view, then random views."""
    s = settings or RenderSettings()
    rng = np.random.default_rng(seed)
    clean = RenderSettings(
        size=s.size,
        occlusion=0.0,
        light=(1.0, 1.0),
        noise=(0.0, 0.0),
        colour_jitter=0.0,
        tilt=0.0,
        blur=0.0,
        haze=False,
    )
    rows = []
    for landmark in range(len(FACADE_DESIGNS)):
        tiles = [render_view(landmark, View(10.0, 0.0), rng, clean)]
        tiles += [render_view(landmark, sample_view(rng), rng, s) for _ in range(views_per_class)]
        rows.append(
            np.concatenate([np.pad(t, ((1, 1), (1, 1), (0, 0)), constant_values=255) for t in tiles], axis=1)
        )
    grid = np.concatenate(rows, axis=0)
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), cv2.cvtColor(grid, cv2.COLOR_RGB2BGR)):
        raise OSError(f"could not write {out}")
    return out
