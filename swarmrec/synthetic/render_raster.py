"""Numba kernels of the renderer: z-buffered triangle rasterisation, sensor noise, box statistics.

A pixel ``(col, row)`` samples the viewing ray through ``u = col, v = row``,
the convention :mod:`swarmrec.detection.points` back-projects with, so the
depth stored at a pixel back-projects exactly onto the surface it shows.
Depth is interpolated as ``1 / z``, which is linear in the image for a planar
triangle: the z-buffer holds the exact depth of each triangle's plane, not an
approximation. Surface coordinates and shade are interpolated perspective-
correctly the same way.

Besides the visible colour, depth and object id, :func:`rasterise` counts for
every object the pixels its triangles cover *ignoring* the others
(``coverage``): visible pixels over covered pixels is the object's visible
fraction. It needs the triangles of one object to be contiguous (a
``stamp`` image remembers which object last covered a pixel, so a pixel
covered by two triangles of the same object counts once).

Noise comes from a hash of ``(seed, pixel)`` rather than a random generator:
any frame renders the same whatever was rendered before it.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import numpy.typing as npt

__all__ = ["box_statistics", "finish", "rasterise"]

FloatArray = npt.NDArray[np.float64]
Float32Array = npt.NDArray[np.float32]
IntArray = npt.NDArray[np.int64]
Int32Array = npt.NDArray[np.int32]
ImageArray = npt.NDArray[np.uint8]
DepthArray = npt.NDArray[np.uint16]

# Slack (pixels) of the span test, so that no pixel on an edge shared by two
# triangles is lost to rounding; a pixel drawn twice is harmless.
_EDGE_EPS = 1e-7


@numba.njit(cache=True)
def _mixes(kind: int, a: float, b: float, s: float, t: float) -> bool:
    """Whether a material of pattern ``kind`` (:class:`~.render_mesh.Pattern`) shows its second
    colour at surface point ``(s, t)``."""
    if kind == 0:
        return False
    if kind == 1:
        return (s / a) - math.floor(s / a) < b
    if kind == 2:
        return (t / a) - math.floor(t / a) < b
    if kind == 3:
        return (math.floor(s / a) + math.floor(t / a)) % 2 == 1
    if kind == 4:
        return (s / a) - math.floor(s / a) < b or (t / a) - math.floor(t / a) < b
    if kind == 5:
        return abs(t - a) < b
    if kind == 6:
        ds = (s / a) - math.floor(s / a) - 0.5
        dt = (t / a) - math.floor(t / a) - 0.5
        return ds * ds + dt * dt < b * b
    if kind == 7:
        return s * s + t * t < a * a
    return abs(s) < a and abs(t) < b


@numba.njit(cache=True)
def _clip_near(src: FloatArray, near: float, out: FloatArray) -> int:
    """Clip triangle ``src`` (3 x 6: x y z s t shade) to ``z >= near`` into ``out``; vertex count."""
    n = 0
    for k in range(3):
        a = src[k]
        b = src[(k + 1) % 3]
        a_in = a[2] >= near
        b_in = b[2] >= near
        if a_in:
            out[n, :] = a
            n += 1
        if a_in != b_in:
            f = (near - a[2]) / (b[2] - a[2])
            for c in range(6):
                out[n, c] = a[c] + f * (b[c] - a[c])
            out[n, 2] = near
            n += 1
    return n


@numba.njit(cache=True)
def _triangle(
    poly: FloatArray,
    j: int,
    intrinsics: FloatArray,
    mat: int,
    obj: int,
    palette: FloatArray,
    gain: float,
    zbuf: Float32Array,
    ids: Int32Array,
    rgb: ImageArray,
    stamp: Int32Array,
    coverage: IntArray,
    lin: FloatArray,
) -> None:
    """Draw the camera-frame triangle ``poly[0], poly[j], poly[j + 1]`` (in front of the near plane).

    ``lin`` is scratch space (7 x 3), passed in so that no triangle allocates.
    """
    h, w = zbuf.shape
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    i1, i2 = j, j + 1
    w0 = 1.0 / poly[0, 2]
    w1 = 1.0 / poly[i1, 2]
    w2 = 1.0 / poly[i2, 2]
    u0 = fx * poly[0, 0] * w0 + cx
    v0 = fy * poly[0, 1] * w0 + cy
    u1 = fx * poly[i1, 0] * w1 + cx
    v1 = fy * poly[i1, 1] * w1 + cy
    u2 = fx * poly[i2, 0] * w2 + cx
    v2 = fy * poly[i2, 1] * w2 + cy
    area = (u1 - u0) * (v2 - v0) - (u2 - u0) * (v1 - v0)
    if abs(area) < 1e-12:
        return
    ymin = max(0, int(np.ceil(min(v0, v1, v2))))
    ymax = min(h - 1, int(np.floor(max(v0, v1, v2))))
    umin = max(0.0, min(u0, u1, u2))
    umax = min(w - 1.0, max(u0, u1, u2))
    if ymin > ymax or umin > umax:
        return
    # Barycentric weight k of pixel (u, v) is lin[k, 0] u + lin[k, 1] v + lin[k, 2].
    lin[0, 0], lin[0, 1], lin[0, 2] = (v1 - v2) / area, (u2 - u1) / area, (u1 * v2 - u2 * v1) / area
    lin[1, 0], lin[1, 1], lin[1, 2] = (v2 - v0) / area, (u0 - u2) / area, (u2 * v0 - u0 * v2) / area
    lin[2, 0], lin[2, 1], lin[2, 2] = (v0 - v1) / area, (u1 - u0) / area, (u0 * v1 - u1 * v0) / area
    # 1/z (row 3) and s/z, t/z, shade/z (rows 4-6) are linear in the image too.
    for q in range(4):
        a0 = w0 if q == 0 else poly[0, 2 + q] * w0
        a1 = w1 if q == 0 else poly[i1, 2 + q] * w1
        a2 = w2 if q == 0 else poly[i2, 2 + q] * w2
        for c in range(3):
            lin[3 + q, c] = lin[0, c] * a0 + lin[1, c] * a1 + lin[2, c] * a2
    kind, a, b = int(palette[mat, 6]), palette[mat, 7], palette[mat, 8]
    for y in range(ymin, ymax + 1):
        lo = umin
        hi = umax
        for k in range(3):
            c = lin[k, 1] * y + lin[k, 2]
            if lin[k, 0] > 0.0:
                lo = max(lo, -c / lin[k, 0] - _EDGE_EPS)
            elif lin[k, 0] < 0.0:
                hi = min(hi, -c / lin[k, 0] + _EDGE_EPS)
            elif c < -_EDGE_EPS:
                hi = -1.0
        for x in range(int(np.ceil(lo)), int(np.floor(hi)) + 1):
            inv_z = lin[3, 0] * x + lin[3, 1] * y + lin[3, 2]
            if inv_z <= 0.0:
                continue
            z = 1.0 / inv_z
            if obj >= 0 and stamp[y, x] != obj:
                stamp[y, x] = obj
                coverage[obj] += 1
            if z >= zbuf[y, x]:
                continue
            zbuf[y, x] = z
            ids[y, x] = obj
            s = (lin[4, 0] * x + lin[4, 1] * y + lin[4, 2]) * z
            t = (lin[5, 0] * x + lin[5, 1] * y + lin[5, 2]) * z
            light = (lin[6, 0] * x + lin[6, 1] * y + lin[6, 2]) * z * gain
            base = 3 if _mixes(kind, a, b, s, t) else 0
            for ch in range(3):
                rgb[y, x, ch] = np.uint8(min(255.0, max(0.0, palette[mat, base + ch] * light + 0.5)))


@numba.njit(cache=True)
def rasterise(
    vertices: FloatArray,
    attributes: FloatArray,
    materials: IntArray,
    objects: IntArray,
    palette: FloatArray,
    rotation: FloatArray,
    position: FloatArray,
    intrinsics: FloatArray,
    near: float,
    gain: float,
    zbuf: Float32Array,
    ids: Int32Array,
    rgb: ImageArray,
    stamp: Int32Array,
    coverage: IntArray,
) -> None:
    """Draw every triangle seen from the camera at ``position`` with camera-to-world ``rotation``.

    ``intrinsics`` is ``(fx, fy, cx, cy)``. ``zbuf`` (inf), ``ids`` (-1),
    ``stamp`` (-1), ``coverage`` (0) and ``rgb`` (background colour) must be
    initialised by the caller; triangles are clipped at ``near`` metres.
    """
    src = np.empty((3, 6))
    poly = np.empty((4, 6))
    lin = np.empty((7, 3))
    for i in range(vertices.shape[0]):
        for k in range(3):
            dx = vertices[i, k, 0] - position[0]
            dy = vertices[i, k, 1] - position[1]
            dz = vertices[i, k, 2] - position[2]
            # p_cam = R^T (p_world - t)
            for c in range(3):
                src[k, c] = rotation[0, c] * dx + rotation[1, c] * dy + rotation[2, c] * dz
            for c in range(3):
                src[k, 3 + c] = attributes[i, k, c]
        if src[0, 2] < near and src[1, 2] < near and src[2, 2] < near:
            continue
        # Back face: the outward normal points away from the camera (at the origin).
        ax, ay, az = src[1, 0] - src[0, 0], src[1, 1] - src[0, 1], src[1, 2] - src[0, 2]
        bx, by, bz = src[2, 0] - src[0, 0], src[2, 1] - src[0, 1], src[2, 2] - src[0, 2]
        nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
        if nx * src[0, 0] + ny * src[0, 1] + nz * src[0, 2] >= 0.0:
            continue
        n = _clip_near(src, near, poly)
        for j in range(1, n - 1):
            _triangle(
                poly,
                j,
                intrinsics,
                materials[i],
                objects[i],
                palette,
                gain,
                zbuf,
                ids,
                rgb,
                stamp,
                coverage,
                lin,
            )


@numba.njit(cache=True)
def _hash(seed: np.uint64, index: np.uint64) -> np.uint64:
    """SplitMix64 of ``seed`` and ``index``: 64 well-mixed bits per pixel."""
    x = seed ^ (index * np.uint64(0x9E3779B97F4A7C15))
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


@numba.njit(cache=True)
def finish(
    zbuf: Float32Array,
    rgb: ImageArray,
    depth: DepthArray,
    depth_range: FloatArray,
    depth_scale: float,
    seed: np.uint64,
    rgb_sigma: float,
    depth_noise: float,
) -> None:
    """Sensor noise on ``rgb`` (in place) and the ``uint16`` depth image (into ``depth``).

    Depth outside ``depth_range`` (metres) reads 0, the sensor's "no
    reading". Depth noise is the Kinect model of Nguyen et al. (2012),
    ``sigma = 0.0012 + 0.0019 (z - 0.4)^2`` metres, times ``depth_noise``.
    Both noises are triangular (the sum of two uniform bytes of one hash
    per pixel): the right spread at a fraction of a Gaussian draw's cost.
    """
    h, w = zbuf.shape
    # The sum of two uniforms on [0, 1], minus 1, has standard deviation 1/sqrt(6).
    spread = np.sqrt(6.0) / 255.0
    near, far = depth_range[0], depth_range[1]
    for y in range(h):
        for x in range(w):
            bits = _hash(seed, np.uint64(y * w + x))
            if rgb_sigma > 0.0:
                for ch in range(3):
                    b1 = float((bits >> np.uint64(16 * ch)) & np.uint64(0xFF))
                    b2 = float((bits >> np.uint64(16 * ch + 8)) & np.uint64(0xFF))
                    value = float(rgb[y, x, ch]) + rgb_sigma * spread * (b1 + b2 - 255.0)
                    rgb[y, x, ch] = np.uint8(min(255.0, max(0.0, value + 0.5)))
            z = float(zbuf[y, x])
            if depth_noise > 0.0 and z < far + 1.0:
                b1 = float((bits >> np.uint64(48)) & np.uint64(0xFF))
                b2 = float((bits >> np.uint64(56)) & np.uint64(0xFF))
                sigma = 0.0012 + 0.0019 * (z - 0.4) ** 2
                z += depth_noise * sigma * spread * (b1 + b2 - 255.0)
            # The range applies to what the sensor measures, noise included.
            if near <= z <= far:
                depth[y, x] = np.uint16(z * depth_scale + 0.5)
            else:
                depth[y, x] = 0


@numba.njit(cache=True)
def box_statistics(ids: Int32Array, n_objects: int) -> tuple[IntArray, IntArray]:
    """Visible pixels per object and boxes ``x1 y1 x2 y2`` (``x2``, ``y2`` one past the last pixel)."""
    h, w = ids.shape
    count = np.zeros(n_objects, np.int64)
    box = np.empty((n_objects, 4), np.int64)
    box[:, 0] = w
    box[:, 1] = h
    box[:, 2] = 0
    box[:, 3] = 0
    for y in range(h):
        for x in range(w):
            k = ids[y, x]
            if k < 0:
                continue
            count[k] += 1
            box[k, 0] = min(box[k, 0], x)
            box[k, 1] = min(box[k, 1], y)
            box[k, 2] = max(box[k, 2], x + 1)
            box[k, 3] = max(box[k, 3], y + 1)
    return count, box
