"""A full-image run's swarm left running for later runs to attach to (``swarmrec compose up
--workload dvpr``; ``swarmrec run --attach DIR`` replays through it).

:func:`compose` prepares what the swarm reads as the pipeline does (the descriptor model
checked, the centres resolved, the RGB-D frames rendered or taken) and writes the compose
files of its spec. The frames are laid out in ``DIR/dataset`` as a folder of their own
(images linked, not copied, where the file system lets it), the folder the detectors
mount, so the run that attaches later reads exactly the frames the containers read.
:func:`from_record` is that later run: the settings the swarm was composed for, read
back from ``swarm.json``.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

from swarmrec.deployments.compose import ComposeSettings, SwarmFile, write_compose
from swarmrec.errors import ConfigError
from swarmrec.experiments.places.pixels import PixelSource, prepare_pixels
from swarmrec.experiments.places.settings import PixelSettings, PlacesSettings
from swarmrec.experiments.vpr.pipeline import resolve_centres, spec_for
from swarmrec.experiments.vpr.settings import DvprSettings, VprRunSettings
from swarmrec.vpr.model import DescriptorModel

__all__ = ["compose", "from_record"]

#: The record's format: a later version reads the records it knows only.
RECORD = "swarmrec.dvpr-record/1"


def _link_or_copy(source: str | Path, target: str | Path) -> None:
    try:
        os.link(source, target)
    except OSError:  # another file system, or one without hard links
        shutil.copy2(source, target)


def self_contained(px: PixelSource, target: Path) -> Path:
    """``px``'s frames as a TUM folder of their own in ``target`` (relative image paths, so a
    container that mounts it finds them): ``rgb/``, ``depth/``, both lists with each frame's
    RGB timestamp (the frames pair as they did), its ground truth, and a render's
    ``boxes.json`` and exact ``constellations/`` when there are."""
    shutil.rmtree(target, ignore_errors=True)
    for sub in ("rgb", "depth"):
        (target / sub).mkdir(parents=True)
    lists: dict[str, list[str]] = {"rgb": [], "depth": []}
    for frame in px.frames:
        for sub, path in (("rgb", frame.rgb_path), ("depth", frame.depth_path)):
            # Named by the frame's id: unique, and the pairing does not depend on the source's names.
            name = f"{frame.timestamp:.6f}{path.suffix}"
            _link_or_copy(path, target / sub / name)
            lists[sub].append(f"{frame.timestamp:.6f} {sub}/{name}")
    for sub, lines in lists.items():
        (target / f"{sub}.txt").write_text("\n".join(lines) + "\n", encoding="utf-8")
    for extra in ("groundtruth.txt", "boxes.json"):
        if (px.folder / extra).is_file():
            shutil.copy2(px.folder / extra, target / extra)
    if (px.folder / "constellations").is_dir():
        shutil.copytree(px.folder / "constellations", target / "constellations", copy_function=_link_or_copy)
    return target


def _pixels_record(px: PixelSource, pixels: PixelSettings, folder: Path) -> dict[str, Any]:
    """The pixel settings that read ``folder`` as the detectors read it (every choice fixed,
    none left to a default a later version might change)."""
    cam = px.camera
    return {
        "rgbd": str(folder),
        "model": str(px.model),
        "conf_threshold": px.conf_threshold,
        "detector_threads": pixels.detector_threads,
        "camera": [cam.fx, cam.fy, cam.cx, cam.cy],
        "depth_scale": cam.depth_scale,
        "rgbd_max_dt": pixels.rgbd_max_dt,
    }


def _dvpr_record(dvpr: DvprSettings) -> dict[str, Any]:
    return {k: str(v) if isinstance(v, Path) else v for k, v in asdict(dvpr).items()}


def compose(
    settings: VprRunSettings, compose_settings: ComposeSettings, say: Callable[[str], None] = lambda _t: None
) -> SwarmFile:
    """Write the compose files of this full-image run's swarm under ``compose_settings.out``
    (frames rendered there first when ``--from-pixels``; centres trained there when the
    shipped ones lack this k); a later ``swarmrec run --attach`` reads the run back."""
    if settings.method != "dvpr":
        raise ConfigError("a compose swarm runs one method: --method both starts a swarm per method")
    out = compose_settings.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    settings = settings.with_(run=settings.run.with_(out=out))
    DescriptorModel(settings.dvpr.descriptor_model or None)  # a bad model stops here, before rendering
    centres = resolve_centres(settings, say)
    rendered = prepare_pixels(settings.run)
    folder = self_contained(rendered, out / "dataset")
    if rendered.render is not None:
        shutil.rmtree(rendered.folder, ignore_errors=True)  # linked into the dataset folder
    record = settings.run.record() | {
        "format": RECORD,
        "frames": None,
        "groundtruth": None,
        "pixels": _pixels_record(rendered, settings.run.pixels, folder),
        "dvpr": _dvpr_record(replace(settings.dvpr, centres=centres)),
    }
    attached = from_record(record, out=out / "report", progress=False)
    px = prepare_pixels(attached.run)  # the frames as the attached run will read them
    spec = spec_for(attached, px, centres)
    return write_compose(spec, compose_settings, experiment=record)


def from_record(record: dict[str, Any], **changes: Any) -> VprRunSettings:
    """The full-image run a compose swarm was composed for (``changes``: out, pace, plots ...)."""
    if record.get("format") != RECORD:
        raise ConfigError(f"the swarm file's experiment record is not a full-image run ({RECORD})")
    try:
        px = dict(record["pixels"])
        camera = px.pop("camera")
        px |= {"rgbd": Path(px["rgbd"]), "camera": tuple(camera) if camera else None}
        pixels = PixelSettings(**px)
        dvpr = dict(record["dvpr"])
        for name in ("centres", "assignment"):
            dvpr[name] = Path(dvpr[name]) if dvpr.get(name) else None
        run = PlacesSettings.from_record(record, pixels=pixels, **changes)
        return VprRunSettings(run=run, dvpr=DvprSettings(**dvpr), method="dvpr")
    except (KeyError, TypeError, ValueError) as e:
        raise ConfigError(f"the swarm file's experiment record is not a full-image run: {e}") from None
