"""Triangle meshes for the renderer: materials, convex primitives, and a scene as flat arrays.

Everything :mod:`swarmrec.synthetic.render` draws is a list of triangles in the
world frame, each with a material and the world object it belongs to (-1 for
the room), so the rasteriser (:mod:`swarmrec.synthetic.render_raster`) knows
nothing about shapes. Objects are built from a few convex primitives (box,
frustum, ellipsoid); each triangle is wound so that its normal points out of
its primitive, which lets the rasteriser drop the faces turned away from the
camera and halve its work.

Each vertex carries ``(s, t, shade)``: surface coordinates in metres (for the
material's pattern: stripes, keys, checks...) and a static Lambert shade from
two fixed lights. Lights do not move with the camera, so the shade is computed
once here and the rasteriser only interpolates it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum
from typing import Literal

import numpy as np
import numpy.typing as npt

__all__ = ["Lighting", "Material", "Part", "Pattern", "Scene", "SceneBuilder", "rotation_zx"]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

#: Number of floats per material row in :attr:`Scene.palette`.
MATERIAL_WIDTH = 10


class Pattern(IntEnum):
    """How a material mixes its two colours over the surface coordinates ``(s, t)`` (metres).

    ``a`` and ``b`` are the material's two parameters; where the test holds,
    the pixel takes the second colour.
    """

    SOLID = 0  #: never
    STRIPES_S = 1  #: ``frac(s / a) < b``: vertical stripes (wood grain, book pages)
    STRIPES_T = 2  #: ``frac(t / a) < b``: horizontal stripes (text lines, cake layers)
    CHECKER = 3  #: ``floor(s / a) + floor(t / a)`` odd: tiles, fabric
    GRID = 4  #: ``frac(s / a) < b or frac(t / a) < b``: keys of a keyboard, window bars
    BAND = 5  #: ``|t - a| < b``: a bottle's label, a skirting board
    DOTS = 6  #: distance to the nearest cell centre of an ``a`` grid ``< b * a``: buttons, fur
    DISC = 7  #: ``s^2 + t^2 < a^2``: a mug's coffee, a donut's hole
    FRAME = 8  #: ``|s| < a and |t| < b``: a screen inside its bezel


def _hex_bgr(colour: str) -> tuple[float, float, float]:
    """``"#rrggbb"`` as OpenCV's (blue, green, red) order."""
    value = int(colour.lstrip("#"), 16)
    return float(value & 0xFF), float((value >> 8) & 0xFF), float(value >> 16)


@dataclass(frozen=True)
class Material:
    """A surface look: two colours (``"#rrggbb"``) mixed by a :class:`Pattern`.

    An ``emissive`` surface (a lit screen, a window, a ceiling lamp) ignores
    the lights and keeps its colour.
    """

    colour: str
    colour2: str = "#000000"
    pattern: Pattern = Pattern.SOLID
    a: float = 0.0
    b: float = 0.0
    emissive: bool = False

    def row(self) -> list[float]:
        """The material as a row of :attr:`Scene.palette`."""
        return [
            *_hex_bgr(self.colour),
            *_hex_bgr(self.colour2),
            float(self.pattern),
            self.a,
            self.b,
            float(self.emissive),
        ]


@dataclass(frozen=True)
class Part:
    """One convex primitive of a shape, in its object's frame (x across, y front, z up).

    ``size`` is ``(sx, sy, sz)`` for a box, ``(r_bottom, r_top, height)`` for a
    frustum (a cylinder when both radii are equal, a cone when one is 0) and
    the three radii for an ellipsoid. ``look`` is one material for the whole
    part, or one per face: six for a box (+x, -x, +y, -y, +z, -z), three for
    a frustum (side, top, bottom). The part is centred at ``at``, turned by
    ``yaw`` degrees about z, after a ``tilt`` of degrees about its own x.
    """

    shape: Literal["box", "frustum", "ellipsoid"]
    size: tuple[float, float, float]
    look: tuple[Material, ...]
    at: tuple[float, float, float] = (0.0, 0.0, 0.0)
    yaw: float = 0.0
    tilt: float = 0.0


def rotation_zx(yaw_deg: float, tilt_deg: float = 0.0) -> FloatArray:
    """``Rz(yaw) @ Rx(tilt)``: a turn about the vertical after a tilt about x."""
    cy, sy = np.cos(np.deg2rad(yaw_deg)), np.sin(np.deg2rad(yaw_deg))
    ct, st = np.cos(np.deg2rad(tilt_deg)), np.sin(np.deg2rad(tilt_deg))
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, ct, -st], [0.0, st, ct]])
    result: FloatArray = rz @ rx
    return result


@dataclass(frozen=True)
class Lighting:
    """Two fixed directional lights (world frame, pointing *towards* the light) and ambient light.

    Shade ``= ambient + key * max(0, n . key_dir) + fill * max(0, n . fill_dir)``.
    """

    key_dir: tuple[float, float, float] = (0.35, 0.25, 1.0)
    fill_dir: tuple[float, float, float] = (-0.6, 0.8, 0.25)
    ambient: float = 0.38
    key: float = 0.55
    fill: float = 0.22

    def shade(self, normals: FloatArray) -> FloatArray:
        """Shade of unit normals (``... x 3``)."""
        k = np.asarray(self.key_dir) / np.linalg.norm(self.key_dir)
        f = np.asarray(self.fill_dir) / np.linalg.norm(self.fill_dir)
        result: FloatArray = (
            self.ambient + self.key * np.maximum(normals @ k, 0.0) + self.fill * np.maximum(normals @ f, 0.0)
        )
        return result


@dataclass(frozen=True, eq=False)
class Scene:
    """Triangles ready for the rasteriser.

    ``vertices[i]`` (3 x 3, world frame) is triangle i, wound outwards;
    ``attributes[i]`` holds ``(s, t, shade)`` per vertex; ``materials[i]``
    indexes a row of ``palette`` (see :meth:`Material.row`); ``objects[i]``
    is the world object (``-1``: room and furniture). Triangles of one
    object are contiguous, which the rasteriser's coverage count relies on.
    """

    vertices: FloatArray
    attributes: FloatArray
    materials: IntArray
    objects: IntArray
    palette: FloatArray
    n_objects: int

    def __len__(self) -> int:
        return int(self.vertices.shape[0])


@dataclass(frozen=True, eq=False)
class _Tessellation:
    """Triangles of a primitive in its own frame: vertices, ``(s, t)``, normals, face group."""

    vertices: FloatArray
    uv: FloatArray
    normals: FloatArray
    face: IntArray


# Box faces: (outward normal, s axis, t axis); s runs left to right seen from outside, t up.
_BOX_FACES = (
    ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
    ((-1.0, 0.0, 0.0), (0.0, -1.0, 0.0), (0.0, 0.0, 1.0)),
    ((0.0, 1.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    ((0.0, -1.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    ((0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0)),
    ((0.0, 0.0, -1.0), (1.0, 0.0, 0.0), (0.0, -1.0, 0.0)),
)
_QUAD_CORNERS = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
_QUAD_TRIANGLES = np.array([[0, 1, 2], [0, 2, 3]])


def _box(size: tuple[float, float, float]) -> _Tessellation:
    half = np.asarray(size) / 2
    verts, uvs, normals, faces = [], [], [], []
    for k, (n, s_axis, t_axis) in enumerate(_BOX_FACES):
        nv, sv, tv = np.asarray(n), np.asarray(s_axis), np.asarray(t_axis)
        hs, ht = float(np.abs(sv) @ half), float(np.abs(tv) @ half)
        uv = _QUAD_CORNERS * np.array([hs, ht])
        corners = nv * float(np.abs(nv) @ half) + uv[:, :1] * sv + uv[:, 1:] * tv
        verts.append(corners[_QUAD_TRIANGLES])
        uvs.append(uv[_QUAD_TRIANGLES])
        normals.append(np.broadcast_to(nv, (2, 3, 3)))
        faces.append([k, k])
    return _Tessellation(
        np.concatenate(verts), np.concatenate(uvs), np.concatenate(normals), np.array(faces).reshape(-1)
    )


def _segments(radius: float) -> int:
    """Sides of a round primitive: enough that its outline looks round at desk distances.

    A bottle or an eye gets 8, a teddy bear's body 16, a globe 20: small
    parts are many and cost the rasteriser per triangle, not per pixel.
    """
    return int(np.clip(round(4 + 120 * radius), 8, 20))


def _frustum(size: tuple[float, float, float]) -> _Tessellation:
    r_bot, r_top, height = size
    n = _segments(max(r_bot, r_top))
    angle = np.linspace(0.0, 2 * np.pi, n + 1)
    c, s = np.cos(angle), np.sin(angle)
    z0, z1 = -height / 2, height / 2
    bottom = np.stack([r_bot * c, r_bot * s, np.full(n + 1, z0)], axis=1)
    top = np.stack([r_top * c, r_top * s, np.full(n + 1, z1)], axis=1)
    slope = (r_bot - r_top) / max(height, 1e-9)
    side_n = np.stack([c, s, np.full(n + 1, slope)], axis=1)
    side_n /= np.linalg.norm(side_n, axis=1, keepdims=True)
    arc = angle * (r_bot + r_top) / 2
    j = np.arange(n)
    quads = np.stack([bottom[j], bottom[j + 1], top[j + 1], top[j]], axis=1)
    quad_n = np.stack([side_n[j], side_n[j + 1], side_n[j + 1], side_n[j]], axis=1)
    quad_uv = np.stack(
        [
            np.stack([arc[j], np.full(n, z0)], 1),
            np.stack([arc[j + 1], np.full(n, z0)], 1),
            np.stack([arc[j + 1], np.full(n, z1)], 1),
            np.stack([arc[j], np.full(n, z1)], 1),
        ],
        axis=1,
    )
    verts = [quads[:, _QUAD_TRIANGLES].reshape(-1, 3, 3)]
    uvs = [quad_uv[:, _QUAD_TRIANGLES].reshape(-1, 3, 2)]
    normals = [quad_n[:, _QUAD_TRIANGLES].reshape(-1, 3, 3)]
    faces = [np.zeros(2 * n, np.int64)]
    for group, ring, z, nz in ((1, top, z1, 1.0), (2, bottom, z0, -1.0)):
        if ring[0, 0] <= 0.0:
            continue  # a cone's tip has no cap
        centre = np.broadcast_to([0.0, 0.0, z], (n, 3))
        tri = np.stack([centre, ring[j], ring[j + 1]], axis=1)
        verts.append(tri)
        uvs.append(tri[..., :2])
        normals.append(np.broadcast_to([0.0, 0.0, nz], (n, 3, 3)))
        faces.append(np.full(n, group, np.int64))
    return _Tessellation(
        np.concatenate(verts), np.concatenate(uvs), np.concatenate(normals), np.concatenate(faces)
    )


def _ellipsoid(size: tuple[float, float, float]) -> _Tessellation:
    radii = np.asarray(size)
    n_lon = _segments(float(radii.max()))
    n_lat = max(4, n_lon // 2)
    lat = np.linspace(-np.pi / 2, np.pi / 2, n_lat + 1)
    lon = np.linspace(0.0, 2 * np.pi, n_lon + 1)
    la, lo = np.meshgrid(lat, lon, indexing="ij")
    unit = np.stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)], axis=-1)
    points = unit * radii
    normals = unit / radii
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    uv = np.stack([lo * (radii[0] + radii[1]) / 2, points[..., 2]], axis=-1)
    i, j = np.meshgrid(np.arange(n_lat), np.arange(n_lon), indexing="ij")
    corners = [(i, j), (i, j + 1), (i + 1, j + 1), (i + 1, j)]

    def quads(a: FloatArray) -> FloatArray:
        q = np.stack([a[ci, cj] for ci, cj in corners], axis=2).reshape(-1, 4, a.shape[-1])
        result: FloatArray = q[:, _QUAD_TRIANGLES].reshape(-1, 3, a.shape[-1])
        return result

    return _Tessellation(quads(points), quads(uv), quads(normals), np.zeros(2 * n_lat * n_lon, np.int64))


_TESSELLATORS = {"box": _box, "frustum": _frustum, "ellipsoid": _ellipsoid}
_FACE_GROUPS = {"box": 6, "frustum": 3, "ellipsoid": 1}


@dataclass
class SceneBuilder:
    """Collects parts into a :class:`Scene`; add each object's parts together, in object order."""

    lighting: Lighting = field(default_factory=Lighting)
    _vertices: list[FloatArray] = field(default_factory=list)
    _attributes: list[FloatArray] = field(default_factory=list)
    _materials: list[IntArray] = field(default_factory=list)
    _objects: list[IntArray] = field(default_factory=list)
    _palette: dict[Material, int] = field(default_factory=dict)

    def material_index(self, material: Material) -> int:
        """The palette row of ``material`` (equal materials share one)."""
        return self._palette.setdefault(material, len(self._palette))

    def add_part(self, part: Part, rotation: FloatArray, origin: FloatArray, obj: int) -> FloatArray:
        """Add ``part`` of the object at ``origin`` turned by ``rotation`` (object to world).

        Returns the part's world vertices (``n x 3 x 3``) so a caller can size
        what stands around it (a shelf under its books).
        """
        groups = _FACE_GROUPS[part.shape]
        if len(part.look) not in (1, groups):
            raise ValueError(f"a {part.shape} takes 1 or {groups} materials, got {len(part.look)}")
        tess = _TESSELLATORS[part.shape](part.size)
        turn = rotation @ rotation_zx(part.yaw, part.tilt)
        verts = (tess.vertices @ turn.T) + (rotation @ np.asarray(part.at) + origin)
        normals = tess.normals @ turn.T
        # Wind every triangle outwards (its geometric normal along the surface
        # normals), so that back faces can be culled by winding alone, and drop
        # the degenerate ones at the poles and tips.
        geo = np.cross(verts[:, 1] - verts[:, 0], verts[:, 2] - verts[:, 0])
        keep = np.linalg.norm(geo, axis=1) > 1e-12
        flip = np.einsum("ij,ij->i", geo, normals.sum(axis=1)) < 0
        order = np.where(flip[:, None], [0, 2, 1], [0, 1, 2])
        rows = np.arange(verts.shape[0])[:, None]
        verts = np.asarray(verts[rows, order][keep], dtype=np.float64)
        normals, uv = normals[rows, order][keep], tess.uv[rows, order][keep]
        face = tess.face[keep]
        look = face if len(part.look) > 1 else np.zeros_like(face)
        tri_mat = np.array([self.material_index(m) for m in part.look], np.int64)[look]
        emissive = np.array([m.emissive for m in part.look])[look]
        shade = np.where(emissive[:, None], 1.0, self.lighting.shade(normals))
        self._vertices.append(verts)
        self._attributes.append(np.concatenate([uv, shade[..., None]], axis=2))
        self._materials.append(tri_mat)
        self._objects.append(np.full(tri_mat.shape, obj, np.int64))
        return verts

    def build(self, n_objects: int) -> Scene:
        """The collected triangles as a :class:`Scene` of ``n_objects`` world objects."""
        palette = np.zeros((max(len(self._palette), 1), MATERIAL_WIDTH))
        for material, row in self._palette.items():
            palette[row] = material.row()
        if not self._vertices:
            empty = np.zeros((0, 3, 3))
            return Scene(
                empty, empty.copy(), np.zeros(0, np.int64), np.zeros(0, np.int64), palette, n_objects
            )
        return Scene(
            vertices=np.ascontiguousarray(np.concatenate(self._vertices)),
            attributes=np.ascontiguousarray(np.concatenate(self._attributes)),
            materials=np.concatenate(self._materials),
            objects=np.concatenate(self._objects),
            palette=palette,
            n_objects=n_objects,
        )
