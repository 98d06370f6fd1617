"""RGB-D renders of the synthetic office: images for detector training, TUM RGB-D folders.

The synthetic office (:mod:`swarmrec.synthetic`) knows every object's label
and 3D position and the camera's path, but has no pixels. This module draws
them: each class as a few primitives with its own proportions, colours and
pattern (see :mod:`swarmrec.synthetic.render_shapes`), in a room with floor,
walls, windows and furniture, z-buffered in numba (one core, about 10 ms a
640x480 frame). A frame gives

* ``rgb``: BGR ``uint8``, with seeded lighting changes and sensor noise;
* ``depth``: ``uint16``, TUM's 5000 units per metre, 0 for no reading
  (outside the sensor's range); the depth of a pixel is the exact depth of
  the surface it shows (plus the Kinect's noise), so the median depth of a
  box lands on the object's visible surface, a few centimetres in front of
  its point;
* for every visible object (at least one pixel where it is the nearest
  surface): its exact box from those pixels, the visible fraction of the
  pixels it would cover without occluders (image border cuts are not
  counted as occlusion), and its exact camera-frame point.

>>> from swarmrec.synthetic import OfficeConfig, generate_office
>>> renderer = SequenceRenderer(generate_office(OfficeConfig.preset("easy", n_frames=10)))
>>> frame = renderer.render(0)
>>> frame.rgb.shape, frame.depth.dtype.name
((480, 640, 3), 'uint16')

:func:`write_rgbd_sequence` writes a sequence as a TUM RGB-D folder that
:func:`swarmrec.datasets.tum_rgbd.read_tum_rgbd` reads, with the boxes and
the exact constellations next to it; ``python -m swarmrec.synthetic.render``
does it from the command line.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
from tqdm import tqdm

from swarmrec.core.types import Constellation, ConstellationSequence
from swarmrec.datasets.constellations import format_constellation, write_constellations
from swarmrec.datasets.tum import TUM_DEPTH_SCALE, write_trajectory
from swarmrec.errors import ConfigError
from swarmrec.synthetic.camera import TUM_FR3_CAMERA, PinholeCamera, quaternions_to_matrices
from swarmrec.synthetic.config import OfficeConfig
from swarmrec.synthetic.office import SyntheticDataset, generate_office
from swarmrec.synthetic.render_mesh import Scene
from swarmrec.synthetic.render_raster import box_statistics, finish, rasterise
from swarmrec.synthetic.render_shapes import build_scene
from swarmrec.synthetic.world import OfficeWorld

__all__ = [
    "RenderCommand",
    "RenderSettings",
    "RenderSummary",
    "RenderedFrame",
    "SceneRenderer",
    "SequenceRenderer",
    "main",
    "write_rgbd_sequence",
]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]
ImageArray = npt.NDArray[np.uint8]
DepthArray = npt.NDArray[np.uint16]

# Triangles are clipped this far in front of the camera (metres).
_NEAR_CLIP_M = 0.01
# Separates the renderer's random stream from generate_office's, which uses the same seed.
_RENDER_STREAM = 0x52454E44


@dataclass(frozen=True)
class RenderSettings:
    """How frames are rendered; validated on construction.

    ``width`` x ``height``: image size; the camera's intrinsics are scaled
    to it (TUM's 640x480 by default). ``depth_range_m``: the depth sensor's
    near and far limits; depth outside reads 0, and objects whose point lies
    outside are left out of the exact constellations. ``rgb_noise``: standard
    deviation of the colour noise, in 8-bit levels. ``depth_noise``: factor
    on the Kinect depth-noise model (0 = exact depth). ``lighting_variation``:
    standard deviation of the slow brightness change along a sequence (0.1 = 10 %).
    """

    width: int = 640
    height: int = 480
    depth_range_m: tuple[float, float] = (0.4, 5.0)
    rgb_noise: float = 2.0
    depth_noise: float = 1.0
    lighting_variation: float = 0.1

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not 16 <= value <= 8192:
                raise ConfigError(f"{name} must be an integer in [16, 8192] pixels, got {value!r}")
        near, far = self.depth_range_m
        if not 0.0 < near < far <= 65535 / TUM_DEPTH_SCALE:
            raise ConfigError(
                f"depth_range_m must be (near, far) with 0 < near < far <= {65535 / TUM_DEPTH_SCALE:.3f} m "
                f"(the largest uint16 depth), got {self.depth_range_m}"
            )
        for name, high in (("rgb_noise", 64.0), ("depth_noise", 10.0), ("lighting_variation", 0.5)):
            value = getattr(self, name)
            if not 0.0 <= value <= high:
                raise ConfigError(f"{name} must be in [0, {high}], got {value}")


@dataclass(frozen=True, eq=False)
class RenderedFrame:
    """One rendered frame and what is visible in it.

    ``instances[v, u]`` is the world object seen at pixel ``(u, v)``, -1 for
    the room. The visible objects come in ascending world index:
    ``objects[i]`` has label ``labels[i]`` (COCO label index, the line of
    ``coco.names``), box ``boxes[i] = (x1, y1, x2, y2)`` (pixel ``u`` covers
    ``[u, u + 1)``, so ``x2`` and ``y2`` are one past the last pixel; the box
    lies inside the image), ``pixels[i]`` visible pixels, ``visible_fraction[i]``
    of the pixels it covers without occluders, and camera-frame point
    ``points[i]`` (x right, y down, z forward, metres); ``in_range[i]`` says
    whether that point's depth is inside the sensor's range.
    """

    rgb: ImageArray
    depth: DepthArray
    instances: npt.NDArray[np.int32]
    objects: IntArray
    labels: IntArray
    boxes: IntArray
    pixels: IntArray
    visible_fraction: FloatArray
    points: FloatArray
    in_range: BoolArray

    def constellation(self) -> Constellation:
        """The exact constellation: label and camera-frame point of every visible object in range."""
        return Constellation(self.labels[self.in_range], self.points[self.in_range])


def _scaled_camera(camera: PinholeCamera, width: int, height: int) -> PinholeCamera:
    """``camera`` for an image resized to ``width`` x ``height``.

    Pixel centres sit at integer coordinates, so the image spans
    ``[-0.5, width - 0.5]``: the principal point scales about -0.5.
    """
    sx, sy = width / camera.width, height / camera.height
    return PinholeCamera(
        fx=camera.fx * sx,
        fy=camera.fy * sy,
        cx=(camera.cx + 0.5) * sx - 0.5,
        cy=(camera.cy + 0.5) * sy - 0.5,
        width=width,
        height=height,
    )


class SceneRenderer:
    """Renders a world from any camera pose.

    The scene (every object's triangles, the furniture and the room around
    the objects and ``room_points``) is built once from ``seed``; each
    :meth:`render` only rasterises it.
    """

    def __init__(
        self,
        world: OfficeWorld,
        camera: PinholeCamera = TUM_FR3_CAMERA,
        settings: RenderSettings | None = None,
        *,
        seed: int = 0,
        room_points: FloatArray | None = None,
    ) -> None:
        self.world = world
        self.settings = settings or RenderSettings()
        self.camera = _scaled_camera(camera, self.settings.width, self.settings.height)
        self.scene: Scene = build_scene(world, np.random.default_rng([seed, _RENDER_STREAM]), room_points)
        self._intrinsics = np.array([self.camera.fx, self.camera.fy, self.camera.cx, self.camera.cy])

    def render(
        self, rotation: FloatArray, position: FloatArray, *, noise_seed: int = 0, gain: float = 1.0
    ) -> RenderedFrame:
        """The frame seen by the camera at ``position`` with camera-to-world ``rotation`` (TUM).

        ``noise_seed`` picks the sensor noise; ``gain`` scales the lighting.
        """
        s = self.settings
        h, w = s.height, s.width
        scene = self.scene
        zbuf = np.full((h, w), np.inf, np.float32)
        ids = np.full((h, w), -1, np.int32)
        stamp = np.full((h, w), -1, np.int32)
        rgb = np.zeros((h, w, 3), np.uint8)
        coverage = np.zeros(scene.n_objects, np.int64)
        rotation = np.ascontiguousarray(rotation, dtype=np.float64)
        position = np.ascontiguousarray(position, dtype=np.float64)
        rasterise(
            scene.vertices, scene.attributes, scene.materials, scene.objects, scene.palette,
            rotation, position, self._intrinsics, _NEAR_CLIP_M, float(gain),
            zbuf, ids, rgb, stamp, coverage,
        )  # fmt: skip
        depth = np.zeros((h, w), np.uint16)
        finish(
            zbuf, rgb, depth, np.asarray(s.depth_range_m, np.float64), TUM_DEPTH_SCALE,
            np.uint64(noise_seed % 2**64), s.rgb_noise, s.depth_noise,
        )  # fmt: skip
        count, box = box_statistics(ids, scene.n_objects)
        objects = np.flatnonzero(count > 0).astype(np.int64)
        points = (self.world.positions[objects] - position) @ rotation
        near, far = s.depth_range_m
        return RenderedFrame(
            rgb=rgb,
            depth=depth,
            instances=ids,
            objects=objects,
            labels=self.world.labels[objects],
            boxes=box[objects],
            pixels=count[objects],
            # A pixel seen is a pixel covered, so the ratio is at most 1.
            visible_fraction=count[objects] / coverage[objects],
            points=points,
            in_range=(points[:, 2] >= near) & (points[:, 2] <= far),
        )


class SequenceRenderer:
    """Renders the frames of a generated office sequence along its camera path.

    Frame ``i`` has the pose of ``ds.trajectory[i]``, sensor noise seeded by
    ``(seed, i)`` and a lighting gain from a smooth seeded curve, so it
    renders the same whatever else is rendered, in whatever order.
    """

    def __init__(self, ds: SyntheticDataset, settings: RenderSettings | None = None) -> None:
        self.dataset = ds
        self.scene_renderer = SceneRenderer(
            ds.world, ds.camera, settings, seed=ds.config.seed, room_points=ds.trajectory.positions
        )
        self._rotations = quaternions_to_matrices(ds.trajectory.quaternions)
        rng = np.random.default_rng([ds.config.seed, _RENDER_STREAM, 1])
        t = ds.trajectory.timestamps - ds.trajectory.timestamps[0]
        freqs = rng.uniform(0.02, 0.1, 3)
        phases = rng.uniform(0.0, 2 * np.pi, 3)
        wave = np.sin(2 * np.pi * freqs[None, :] * t[:, None] + phases[None, :]).mean(axis=1)
        self._gains = 1.0 + self.settings.lighting_variation * wave / np.sqrt(0.5 / 3)
        self._gains = np.clip(self._gains, 0.5, 1.5)

    @property
    def settings(self) -> RenderSettings:
        return self.scene_renderer.settings

    @property
    def camera(self) -> PinholeCamera:
        """The intrinsics of the rendered images (the dataset's, scaled to the image size)."""
        return self.scene_renderer.camera

    def __len__(self) -> int:
        return len(self.dataset.trajectory)

    def render(self, i: int) -> RenderedFrame:
        """Frame ``i`` of the sequence."""
        if not 0 <= i < len(self):
            raise IndexError(f"frame {i} is outside the sequence's {len(self)} frames")
        seed = int(np.random.SeedSequence([self.dataset.config.seed, i]).generate_state(1, np.uint64)[0])
        return self.scene_renderer.render(
            self._rotations[i],
            self.dataset.trajectory.positions[i],
            noise_seed=seed,
            gain=float(self._gains[i]),
        )


@dataclass(frozen=True)
class RenderSummary:
    """What :func:`write_rgbd_sequence` wrote and how long it took (render alone and in all)."""

    folder: Path
    frames: int
    boxes: int
    render_s: float
    total_s: float

    def line(self) -> str:
        per_frame = 1000 * self.render_s / max(self.frames, 1)
        return (
            f"{self.frames} frames, {self.boxes} boxes -> {self.folder} "
            f"(render {per_frame:.1f} ms/frame, total {self.total_s:.1f} s)"
        )


def write_rgbd_sequence(
    ds: SyntheticDataset,
    folder: str | Path,
    *,
    frames: Sequence[int] | None = None,
    settings: RenderSettings | None = None,
    overwrite: bool = False,
    progress: bool = False,
) -> RenderSummary:
    """Render ``frames`` of ``ds`` (all by default) into a TUM RGB-D folder, with labels.

    * ``rgb/<frame id>.png``, ``depth/<frame id>.png`` (16-bit, 5000 per
      metre), listed in ``rgb.txt`` and ``depth.txt`` with the same
      timestamps; ``groundtruth.txt`` holds every pose of the sequence;
    * ``boxes.json``: image size, intrinsics, label names, and per frame the
      visible objects (label, COCO label index, box, pixels, visible
      fraction, camera-frame point), for detector training and evaluation;
    * ``constellations/<frame id>.txt``: the exact constellations (visible
      objects in the depth range, camera frame), what a perfect detector
      with perfect depth would give; ``world_constellations/<frame id>.txt``:
      the same objects at their world-frame points;
    * ``coco.names``, ``world.txt`` (every object, world frame) and ``README.md``.

    A non-empty folder is refused unless ``overwrite``, which first removes
    the frame folders so no stale frame survives.
    """
    start = time.perf_counter()
    n = len(ds.trajectory)
    indices = list(range(n)) if frames is None else [int(i) for i in frames]
    if not indices or indices[0] < 0 or indices[-1] >= n or bool(np.any(np.diff(indices) <= 0)):
        # TUM file lists need increasing timestamps, one image each.
        raise ConfigError(
            f"frames must be increasing indices in [0, {n}), at least one; got {indices[:10]}..."
        )
    folder = Path(folder)
    if folder.exists() and any(folder.iterdir()):
        if not overwrite:
            raise FileExistsError(f"{folder} is not empty; pass overwrite=True (--overwrite) to replace it")
        for sub in ("rgb", "depth", "constellations", "world_constellations"):
            shutil.rmtree(folder / sub, ignore_errors=True)
    renderer = SequenceRenderer(ds, settings)
    for sub in ("rgb", "depth"):
        (folder / sub).mkdir(parents=True, exist_ok=True)
    ids = ds.sequence.frame_ids
    names = ds.sequence.label_names
    records: list[dict[str, Any]] = []
    exact: list[Constellation] = []
    world_exact: list[Constellation] = []
    render_s = 0.0
    for i in tqdm(indices, desc="rendering", unit="frame", disable=not progress, leave=False):
        t0 = time.perf_counter()
        frame = renderer.render(i)
        render_s += time.perf_counter() - t0
        _write_png(folder / "rgb" / f"{ids[i]}.png", frame.rgb)
        _write_png(folder / "depth" / f"{ids[i]}.png", frame.depth)
        records.append(_frame_record(i, ids[i], frame, names))
        exact.append(frame.constellation())
        world_exact.append(
            Constellation(frame.labels[frame.in_range], ds.world.positions[frame.objects[frame.in_range]])
        )
    chosen = tuple(ids[i] for i in indices)
    for name, what in (("rgb", "color images"), ("depth", "depth maps")):
        lines = [f"# {what}", f"# synthetic office, seed {ds.config.seed}", "# timestamp filename"]
        lines += [f"{frame_id} {name}/{frame_id}.png" for frame_id in chosen]
        (folder / f"{name}.txt").write_text("\n".join(lines) + "\n", encoding="utf-8")
    write_trajectory(ds.trajectory, folder / "groundtruth.txt")
    stamps = ds.sequence.timestamps[indices]
    for sub, constellations in (("constellations", exact), ("world_constellations", world_exact)):
        seq = ConstellationSequence(chosen, stamps, tuple(constellations), names, name=ds.sequence.name)
        write_constellations(seq, folder / sub)
    (folder / "coco.names").write_text("".join(f"{n}\n" for n in names), encoding="utf-8")
    world = Constellation(ds.world.labels, ds.world.positions)
    (folder / "world.txt").write_text(format_constellation(world, names), encoding="utf-8")
    camera = renderer.camera
    meta = {
        "sequence": ds.sequence.name,
        "seed": ds.config.seed,
        "width": camera.width,
        "height": camera.height,
        "camera": {
            "fx": camera.fx,
            "fy": camera.fy,
            "cx": camera.cx,
            "cy": camera.cy,
            "depth_scale": TUM_DEPTH_SCALE,
        },
        "box_format": "x1 y1 x2 y2 in pixels; pixel u covers [u, u+1), so x2 and y2 are exclusive",
        "label_names": list(names),
        "frames": records,
    }
    (folder / "boxes.json").write_text(json.dumps(meta, indent=1) + "\n", encoding="utf-8")
    (folder / "README.md").write_text(_readme(ds, renderer.settings, camera, len(indices)), encoding="utf-8")
    n_boxes = sum(len(r["objects"]) for r in records)
    return RenderSummary(folder, len(indices), n_boxes, render_s, time.perf_counter() - start)


def _write_png(path: Path, image: ImageArray | DepthArray) -> None:
    if not cv2.imwrite(str(path), image):
        raise OSError(f"cannot write {path}")


def _frame_record(i: int, frame_id: str, frame: RenderedFrame, names: tuple[str, ...]) -> dict[str, Any]:
    """One frame of ``boxes.json``."""
    objects = [
        {
            "object": int(k),
            "label": names[int(label)],
            "class_id": int(label),
            "box": [int(v) for v in box],
            "pixels": int(pixels),
            "visible_fraction": round(float(fraction), 4),
            "point": [round(float(v), 6) for v in point],
            "in_range": bool(in_range),
        }
        for k, label, box, pixels, fraction, point, in_range in zip(
            frame.objects,
            frame.labels,
            frame.boxes,
            frame.pixels,
            frame.visible_fraction,
            frame.points,
            frame.in_range,
            strict=True,
        )
    ]
    return {
        "frame": i,
        "id": frame_id,
        "rgb": f"rgb/{frame_id}.png",
        "depth": f"depth/{frame_id}.png",
        "objects": objects,
    }


def _readme(ds: SyntheticDataset, settings: RenderSettings, camera: PinholeCamera, n_frames: int) -> str:
    return (
        f"# {ds.sequence.name} RGB-D (seed {ds.config.seed})\n\n"
        "Rendered by `swarmrec.synthetic.render` from the synthetic office "
        "(docs/synthetic-world.md), in the layout of a TUM RGB-D sequence:\n\n"
        "- `rgb/`, `depth/`, `rgb.txt`, `depth.txt`, `groundtruth.txt`: as TUM "
        "(depth 16-bit PNG, 5000 units per metre, 0 = no reading; poses camera to world, "
        "`p_world = R(q) p_cam + t`).\n"
        "- `boxes.json`: per frame, every visible object's label, `class_id` (line of "
        "`coco.names`), box `x1 y1 x2 y2` (x2, y2 exclusive), visible pixels, visible fraction "
        "(occlusion only) and camera-frame point.\n"
        "- `constellations/`: exact constellations (visible objects whose point is in the depth "
        "range, camera frame: x right, y down, z forward); `world_constellations/`: the same "
        "objects at their world points.\n"
        "- `coco.names`, `world.txt`: label names and every object's world point.\n\n"
        f"{n_frames} frames, {camera.width}x{camera.height}, fx {camera.fx:.3f} fy {camera.fy:.3f} "
        f"cx {camera.cx:.3f} cy {camera.cy:.3f}; settings: {settings}.\n"
    )


@dataclass(frozen=True)
class RenderCommand:
    """What ``python -m swarmrec.synthetic.render`` renders."""

    out: Path
    frames: int = 2500
    seed: int = 0
    every: int = 1
    width: int = 640
    height: int = 480
    overwrite: bool = False
    progress: bool = True


def main(command: RenderCommand) -> RenderSummary:
    """Generate the office sequence of ``command.frames`` frames and render every ``every``-th."""
    if command.every < 1:
        raise ConfigError(f"every must be >= 1, got {command.every}")
    ds = generate_office(OfficeConfig(seed=command.seed, n_frames=command.frames))
    return write_rgbd_sequence(
        ds,
        command.out,
        frames=range(0, command.frames, command.every),
        settings=RenderSettings(width=command.width, height=command.height),
        overwrite=command.overwrite,
        progress=command.progress,
    )


def _size(text: str) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT such as 640x480, got {text!r}") from None
    return width, height


def _parse_args(argv: Sequence[str] | None) -> RenderCommand:
    parser = argparse.ArgumentParser(
        prog="python -m swarmrec.synthetic.render",
        description="Render the synthetic office as a TUM RGB-D folder with boxes and exact constellations.",
    )
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--frames", type=int, default=2500, help="frames of the camera path")
    parser.add_argument("--seed", type=int, default=0, help="seed of the world, path and renders")
    parser.add_argument("--every", type=int, default=1, help="render every K-th frame")
    parser.add_argument("--size", type=_size, default=(640, 480), help="image size WxH (default 640x480)")
    parser.add_argument("--overwrite", action="store_true", help="replace a non-empty output folder")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    return RenderCommand(
        out=args.out,
        frames=args.frames,
        seed=args.seed,
        every=args.every,
        width=args.size[0],
        height=args.size[1],
        overwrite=args.overwrite,
        progress=not args.quiet,
    )


if __name__ == "__main__":
    try:
        summary = main(_parse_args(None))
    except (ConfigError, FileExistsError) as exc:
        sys.exit(f"error: {exc}")
    print(summary.line(), file=sys.stderr)
