"""The main job from pixels: RGB-D frames for the detectors, and what they made of them.

``swarmrec run --dataset synthetic --from-pixels`` renders the synthetic
office as a TUM RGB-D folder in the run folder; ``swarmrec run --rgbd DIR``
takes any TUM-format folder (a real recording). Either way the detectors run
in ``rgbd`` mode on the folder (docs/detector.md) and write each
constellation they make under their data folder; after the replay the job
reads those back, in frame order, as the sequence the report scores (pair
scores, the offline check, ground truth from ``groundtruth.txt`` by time).
"""

from __future__ import annotations

import json
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from swarmrec.core.presets import get_preset
from swarmrec.core.types import Constellation, ConstellationSequence, Trajectory
from swarmrec.datasets.constellations import parse_constellation, read_constellations
from swarmrec.datasets.labels import LabelMap, label_names
from swarmrec.datasets.tum import read_trajectory
from swarmrec.datasets.tum_rgbd import RgbdFrame, frame_id_of, read_tum_rgbd
from swarmrec.detection import CameraIntrinsics, conf_threshold_for, load_detector
from swarmrec.errors import ConfigError, DatasetError
from swarmrec.experiments.places.settings import PixelSettings, PlacesSettings
from swarmrec.services.settings import RgbdSettings
from swarmrec.synthetic import OfficeConfig, generate_office
from swarmrec.synthetic.render import write_rgbd_sequence

__all__ = ["PixelSource", "detected_sequence", "prepare_pixels", "rgbd_settings"]


@dataclass(frozen=True, eq=False)
class PixelSource:
    """The RGB-D folder the detectors read and how they read it.

    ``exact`` is the folder's ``constellations/`` (a synthetic render's exact
    constellations), read only as the label-frequency prior of the
    ``balanced`` preset. ``render`` says what was rendered, when the job did.
    """

    folder: Path
    name: str
    frames: tuple[RgbdFrame, ...]
    frame_ids: tuple[str, ...]
    label_names: tuple[str, ...]
    labels_file: Path | None
    trajectory: Trajectory | None
    camera: CameraIntrinsics
    model: Path
    conf_threshold: float
    exact: ConstellationSequence | None
    render: dict[str, Any] | None

    def __len__(self) -> int:
        return len(self.frames)


#: What one rendered frame takes on disk (a 640x480 RGB PNG and its 16-bit depth PNG), measured.
RENDER_BYTES_PER_FRAME = 0.8e6


def _check_room(folder: Path, frames: int, say: bool) -> None:
    """Say how much the render will write, and refuse it when the disk has not that much free."""
    need = frames * RENDER_BYTES_PER_FRAME
    existing = folder
    while not existing.exists():
        existing = existing.parent
    free = shutil.disk_usage(existing).free
    if free < 1.1 * need:
        raise ConfigError(
            f"rendering {frames} frames into {folder} needs about {need / 1e9:.1f} GB and "
            f"{free / 1e9:.1f} GB are free: fewer --frames, or another --out"
        )
    if say:
        print(
            f"rendering {frames} RGB-D frames into {folder} (about {need / 1e9:.2f} GB, 0.8 MB a frame)",
            file=sys.stderr,
            flush=True,
        )


def _render(settings: PlacesSettings, folder: Path) -> dict[str, Any]:
    src = settings.source
    config = (
        OfficeConfig(seed=src.seed)
        if src.frames is None
        else OfficeConfig(seed=src.seed, n_frames=src.frames)
    )
    _check_room(folder, config.n_frames, settings.progress)
    summary = write_rgbd_sequence(generate_office(config), folder, overwrite=True, progress=settings.progress)
    return {
        "folder": str(summary.folder),
        "frames": summary.frames,
        "boxes": summary.boxes,
        "render_s": summary.render_s,
        "total_s": summary.total_s,
    }


def _camera_of(pixels: PixelSettings, folder: Path) -> CameraIntrinsics:
    """``--camera``, else the intrinsics a synthetic render wrote in ``boxes.json``, else TUM fr3."""
    default = CameraIntrinsics()
    scale = pixels.depth_scale
    if pixels.camera is not None:
        fx, fy, cx, cy = pixels.camera
        return CameraIntrinsics(fx, fy, cx, cy, scale if scale is not None else default.depth_scale)
    meta_path = folder / "boxes.json"
    if meta_path.is_file():
        try:
            cam = json.loads(meta_path.read_text(encoding="utf-8"))["camera"]
            found = CameraIntrinsics(
                float(cam["fx"]),
                float(cam["fy"]),
                float(cam["cx"]),
                float(cam["cy"]),
                scale if scale is not None else float(cam["depth_scale"]),
            )
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise DatasetError(meta_path, f"no usable camera intrinsics ({e}); pass --camera") from None
        return found
    if scale is not None:
        return CameraIntrinsics(default.fx, default.fy, default.cx, default.cy, scale)
    return default


def _subset(frames: tuple[RgbdFrame, ...], folder: Path, source: Path) -> Path:
    """A TUM folder listing only ``frames`` (absolute image paths), with ``source``'s ground truth."""
    folder.mkdir(parents=True, exist_ok=True)
    for name, paths in (("rgb", [f.rgb_path for f in frames]), ("depth", [f.depth_path for f in frames])):
        lines = [f"# the first {len(frames)} frames of {source}"]
        # Both lists carry the frame's (RGB) timestamp, so they pair exactly as they did in the source.
        lines += [f"{f.timestamp:.6f} {p.resolve()}" for f, p in zip(frames, paths, strict=True)]
        (folder / f"{name}.txt").write_text("\n".join(lines) + "\n", encoding="utf-8")
    gt = source / "groundtruth.txt"
    target = folder / "groundtruth.txt"
    target.unlink(missing_ok=True)
    if gt.is_file():
        target.write_bytes(gt.read_bytes())
    return folder


def prepare_pixels(settings: PlacesSettings) -> PixelSource:
    """Render (``--from-pixels``) or take (``--rgbd``) the RGB-D folder; the model is checked first."""
    px, src = settings.pixels, settings.source
    names = label_names(src.labels)
    # Fails here, before minutes of rendering, when the model is missing or does not fit the labels.
    model = Path(
        load_detector(
            px.model, n_classes=len(names), conf_threshold=px.conf_threshold, threads=px.detector_threads
        ).model
    ).resolve()
    render = None
    if px.rgbd is not None:
        folder, name = px.rgbd, px.rgbd.resolve().name
    else:
        folder = settings.out / "rgbd"
        render = _render(settings, folder)
        name = "synthetic-office-rgbd"
    seq = read_tum_rgbd(folder, max_dt=px.rgbd_max_dt)
    if not len(seq):
        raise DatasetError(folder, "no RGB image pairs with a depth image (rgb.txt, depth.txt)")
    source = folder
    frames = seq.frames
    if src.frames is not None and px.rgbd is not None and src.frames < len(frames):
        frames = frames[: src.frames]
        folder = _subset(frames, settings.out / "rgbd-subset", source)
    gt_path = src.groundtruth
    if gt_path is None and (folder / "groundtruth.txt").is_file():
        gt_path = folder / "groundtruth.txt"
    exact = None
    if get_preset(settings.preset).ranges == "balanced" and (source / "constellations").is_dir():
        exact = read_constellations(source / "constellations", names)
    return PixelSource(
        folder=folder,
        name=name,
        frames=tuple(frames),
        frame_ids=tuple(frame_id_of(f) for f in frames),
        label_names=names,
        labels_file=src.labels,
        trajectory=read_trajectory(gt_path) if gt_path else None,
        camera=_camera_of(px, source),
        model=model,
        conf_threshold=conf_threshold_for(px.model, px.conf_threshold),
        exact=exact,
        render=render,
    )


def rgbd_settings(src: PixelSource, pixels: PixelSettings) -> RgbdSettings:
    """The settings that make every detector read ``src`` in rgbd mode."""
    cam = src.camera
    return RgbdSettings(
        detector_model=str(src.model),
        conf_threshold=src.conf_threshold,
        detector_threads=pixels.detector_threads,
        camera_fx=cam.fx,
        camera_fy=cam.fy,
        camera_cx=cam.cx,
        camera_cy=cam.cy,
        depth_scale=cam.depth_scale,
        rgbd_max_dt=pixels.rgbd_max_dt,
    )


def detected_sequence(
    src: PixelSource, data_dir: Path, blocks: list[range]
) -> tuple[ConstellationSequence, list[int]]:
    """The constellations the detectors wrote, in frame order, and the frames they made none of.

    A frame a detector skipped (a bad image) or never reached is an empty
    constellation here, so frame indices stay those of the replay.
    """
    labels = LabelMap(src.label_names)
    out: list[Constellation] = []
    missing: list[int] = []
    for robot, block in enumerate(blocks):
        folder = data_dir / f"robot{robot}" / "detector" / "constellations"
        for g in block:
            path = folder / f"{src.frame_ids[g]}.txt"
            try:
                text = path.read_text(encoding="utf-8")
            except FileNotFoundError:
                missing.append(g)
                out.append(Constellation.empty())
                continue
            except OSError as e:
                raise DatasetError(path, f"cannot read: {e}") from e
            out.append(parse_constellation(text, labels, str(path)))
    if len(out) != len(src):
        raise ConfigError(f"the robots' blocks cover {len(out)} frames, the sequence has {len(src)}")
    stamps = np.array([f.timestamp for f in src.frames], dtype=np.float64)
    seq = ConstellationSequence(src.frame_ids, stamps, tuple(out), src.label_names, name=src.name)
    return seq, missing
