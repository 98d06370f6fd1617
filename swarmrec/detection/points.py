"""Object to point: one 3D point per detected box, from the depth image.

As in the constellation paper, an object's point is the median of the 3D
points of the valid depth pixels inside its box, per axis, in the camera
frame (x right, y down, z forward, metres). The median, not the mean,
because a box also covers background and foreground: as long as most of its
pixels are on the object, the point stays on the object.

A pixel ``(u, v)`` (column, row) of depth ``z`` back-projects to
``((u - cx) z / fx, (v - cy) z / fy, z)``, the TUM RGB-D convention. A box
``x1 y1 x2 y2`` (continuous coordinates, pixel ``u`` covering ``[u, u + 1)``,
as the detector gives them) holds the pixels whose centre lies in
``[x1, x2) x [y1, y2)``, so two boxes that touch share no pixel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from swarmrec.datasets.tum import TUM_DEPTH_SCALE
from swarmrec.detection.errors import DetectionError
from swarmrec.errors import ConfigError

__all__ = ["CameraIntrinsics", "ObjectPoints", "object_points", "transform_points"]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics of the depth image and its units; defaults are TUM freiburg3's.

    ``depth_scale`` is depth units per metre (TUM's 16-bit PNGs:
    :data:`~swarmrec.datasets.tum.TUM_DEPTH_SCALE`, 5000; 1 for a float
    depth image already in metres).
    """

    fx: float = 535.4
    fy: float = 539.2
    cx: float = 320.1
    cy: float = 247.6
    depth_scale: float = TUM_DEPTH_SCALE

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "depth_scale"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"camera {name} must be a positive number, got {value}")
        if not (math.isfinite(self.cx) and math.isfinite(self.cy)):
            raise ConfigError(f"camera principal point must be finite, got ({self.cx}, {self.cy})")


@dataclass(frozen=True, eq=False)
class ObjectPoints:
    """The points of the boxes that had valid depth, and which boxes had none.

    ``points[i]`` belongs to box ``kept[i]``; ``dropped`` lists the boxes
    with no valid depth pixel (in box order), so a caller can keep labels
    aligned and count what the depth camera missed.
    """

    points: FloatArray
    kept: IntArray
    dropped: IntArray

    @property
    def n_dropped(self) -> int:
        return int(self.dropped.shape[0])


def object_points(
    depth: npt.ArrayLike,
    boxes: npt.ArrayLike,
    intrinsics: CameraIntrinsics | None = None,
    max_depth: float | None = None,
) -> ObjectPoints:
    """The median 3D point (camera frame, metres) of each box's valid depth pixels.

    ``depth`` is ``h x w`` in the intrinsics' units (a TUM uint16 PNG as
    read). A pixel is valid when its depth is finite, above zero (zero is
    the sensor's "no reading") and, with ``max_depth`` (metres) set, at most
    that far along the optical axis, where the sensor's noise grows. Boxes
    are clipped to the image; a box with no valid pixel, or a non-finite
    box, is dropped.
    """
    cam = intrinsics or CameraIntrinsics()
    if max_depth is not None and not max_depth > 0:
        raise ConfigError(f"max_depth must be positive (metres), got {max_depth}")
    d = np.asarray(depth)
    if d.ndim != 2:
        raise DetectionError(f"expected a depth image (h, w), got shape {d.shape}")
    b = np.asarray(boxes, dtype=np.float64)
    if b.size == 0:
        b = b.reshape(0, 4)
    if b.ndim != 2 or b.shape[1] != 4:
        raise DetectionError(f"expected boxes (n, 4) as x1 y1 x2 y2, got shape {b.shape}")
    h, w = d.shape
    # A non-finite box gets the empty range 0..0 and is dropped below like any box without depth.
    b = np.where(np.isfinite(b).all(axis=1, keepdims=True), b, 0.0)
    cols = np.clip(np.ceil(b[:, 0::2] - 0.5), 0, w).astype(np.int64)
    rows = np.clip(np.ceil(b[:, 1::2] - 0.5), 0, h).astype(np.int64)
    z = d.astype(np.float64) / cam.depth_scale
    valid: npt.NDArray[np.bool_] = np.isfinite(z) & (z > 0)
    if max_depth is not None:
        valid &= z <= max_depth
    points = np.zeros((b.shape[0], 3))
    has_point = np.zeros(b.shape[0], dtype=bool)
    # Pixel offsets from the principal point, once per column and row: a box only gathers them.
    du = np.arange(w) - cam.cx
    dv = (np.arange(h) - cam.cy)[:, None]
    # Boxes differ in size, so each is one slice; the per-pixel work inside is vectorised.
    for k, ((c0, c1), (r0, r1)) in enumerate(zip(cols.tolist(), rows.tolist(), strict=True)):
        mask = valid[r0:r1, c0:c1]
        zz = z[r0:r1, c0:c1][mask]
        if zz.size == 0:
            continue
        xx = np.broadcast_to(du[c0:c1], mask.shape)[mask] * zz / cam.fx
        yy = np.broadcast_to(dv[r0:r1], mask.shape)[mask] * zz / cam.fy
        points[k] = (np.median(xx), np.median(yy), np.median(zz))
        has_point[k] = True
    kept = np.flatnonzero(has_point).astype(np.int64)
    return ObjectPoints(points[kept], kept, np.flatnonzero(~has_point).astype(np.int64))


def transform_points(points: npt.ArrayLike, pose: npt.ArrayLike) -> FloatArray:
    """Points (``n x 3``) moved by a 4 x 4 rigid pose: ``R p + t`` for each point.

    With a TUM camera-to-world pose this turns camera-frame object points
    into world-frame ones.
    """
    p = np.asarray(points, dtype=np.float64)
    m = np.asarray(pose, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise DetectionError(f"expected points (n, 3), got shape {p.shape}")
    if m.shape != (4, 4):
        raise DetectionError(f"expected a 4 x 4 pose, got shape {m.shape}")
    result: FloatArray = p @ m[:3, :3].T + m[:3, 3]
    return result
