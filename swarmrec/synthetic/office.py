"""The built-in synthetic office dataset: generate it, and write it in TUM's layout.

>>> ds = generate_office(OfficeConfig.preset("easy"))
>>> ds.sequence.name, len(ds.sequence) == len(ds.trajectory)
('synthetic-office', True)

The steps: :func:`~swarmrec.synthetic.world.build_world` places the objects,
:func:`~swarmrec.synthetic.camera.orbit_path` walks the camera around them,
:func:`~swarmrec.synthetic.detections.detect` simulates the detector. One
``numpy.random.Generator`` seeded with ``config.seed`` feeds all three, so
the same settings always give the same dataset.
"""

from __future__ import annotations

import dataclasses
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from swarmrec.core.types import Constellation, ConstellationSequence, Trajectory
from swarmrec.datasets.constellations import format_constellation, write_constellations
from swarmrec.datasets.tum import write_trajectory
from swarmrec.synthetic.camera import (
    TUM_FR3_CAMERA,
    PinholeCamera,
    matrices_to_quaternions,
    orbit_path,
    quaternions_to_matrices,
)
from swarmrec.synthetic.config import OfficeConfig
from swarmrec.synthetic.detections import Detections, camera_points, detect, visible_mask
from swarmrec.synthetic.world import OfficeWorld, build_world

__all__ = [
    "SEQUENCE_NAME",
    "SyntheticDataset",
    "covisibility",
    "frame_ids",
    "generate_office",
    "write_dataset",
]

IntArray = npt.NDArray[np.int64]
FloatArray = npt.NDArray[np.float64]

SEQUENCE_NAME = "synthetic-office"


@dataclass(frozen=True, eq=False)
class SyntheticDataset:
    """A generated office sequence with everything needed to check results against.

    ``sequence``: the noisy detections, one constellation per frame, in
    decreasing confidence order (what a real detector would give).
    ``noise_free``: the exact camera-frame positions of the objects visible in
    each frame (centre in the image, depth in range), no misses, noise,
    confusions, duplicates or false positives, ordered by world object index.
    ``sources[i][k]``: the world object behind ``sequence[i]``'s object ``k``
    (``-1`` for a false positive); ``visible[i]``: the world objects of
    ``noise_free[i]``, in its order.
    ``trajectory``: camera-to-world poses, same timestamps as the frames.
    """

    config: OfficeConfig
    sequence: ConstellationSequence
    noise_free: ConstellationSequence
    trajectory: Trajectory
    world: OfficeWorld
    sources: tuple[IntArray, ...]
    visible: tuple[IntArray, ...]
    camera: PinholeCamera = TUM_FR3_CAMERA


def frame_ids(config: OfficeConfig) -> tuple[tuple[str, ...], FloatArray]:
    """TUM-like frame ids (``"1000000000.033333"``) and their float timestamps.

    Built from integer microseconds so the ids are exact and unique.
    """
    micros = np.round(np.arange(config.n_frames) * (1e6 / config.rate_hz)).astype(np.int64)
    ids = tuple(f"{config.start_time_s + int(us) // 1_000_000}.{int(us) % 1_000_000:06d}" for us in micros)
    return ids, np.array([float(i) for i in ids])


def generate_office(config: OfficeConfig | None = None) -> SyntheticDataset:
    """Generate the synthetic office sequence described by ``config`` (default settings if None)."""
    config = OfficeConfig() if config is None else config
    rng = np.random.default_rng(config.seed)
    camera = TUM_FR3_CAMERA
    world = build_world(config, rng)
    cam_pos, cam_rot = orbit_path(config, rng)
    quats = matrices_to_quaternions(cam_rot)
    # Use the rotation of the stored quaternion, so that the detections agree
    # with the published poses to rounding error.
    cam_rot = quaternions_to_matrices(quats)
    ids, stamps = frame_ids(config)
    trajectory = Trajectory(timestamps=stamps, positions=cam_pos, quaternions=quats)

    p_cam = camera_points(world.positions, cam_pos, cam_rot)
    detections = detect(config, world, p_cam, cam_pos, cam_rot, camera, rng)
    sequence, sources = _split_frames(detections, ids, stamps, world.label_names)

    visible = visible_mask(p_cam, camera, config.depth_range_m)
    vis_frame, vis_obj = np.nonzero(visible)
    exact = Detections(
        frame=vis_frame.astype(np.int64),
        labels=world.labels[vis_obj],
        positions=p_cam[vis_frame, vis_obj],
        confidence=np.ones(vis_frame.size),
        source=vis_obj.astype(np.int64),
        true_labels=world.labels[vis_obj],
    )
    noise_free, vis_sources = _split_frames(exact, ids, stamps, world.label_names)
    return SyntheticDataset(
        config=config,
        sequence=sequence,
        noise_free=noise_free,
        trajectory=trajectory,
        world=world,
        sources=sources,
        visible=vis_sources,
        camera=camera,
    )


def covisibility(ds: SyntheticDataset) -> FloatArray:
    """Pairwise overlap of what the frames see (``n x n``, in [0, 1]).

    Entry ``(i, j)`` is the Jaccard index of the sets of world objects visible
    in frames ``i`` and ``j`` (``|A & B| / |A | B|``, 0 when both are empty).
    A ground truth for place recognition that needs no hand-made rules: two
    frames show the same place when they see mostly the same objects.
    """
    n = len(ds.visible)
    seen = np.zeros((n, len(ds.world)), dtype=np.float64)
    for i, objects in enumerate(ds.visible):
        seen[i, objects] = 1.0
    common = seen @ seen.T
    counts = seen.sum(axis=1)
    union = counts[:, None] + counts[None, :] - common
    return np.asarray(np.where(union > 0, common / np.maximum(union, 1.0), 0.0))


def _split_frames(
    det: Detections, ids: tuple[str, ...], stamps: FloatArray, label_names: tuple[str, ...]
) -> tuple[ConstellationSequence, tuple[IntArray, ...]]:
    """Per-frame constellations of flat detections sorted by frame."""
    bounds = np.searchsorted(det.frame, np.arange(len(ids) + 1))
    constellations = []
    sources = []
    for i in range(len(ids)):
        a, b = int(bounds[i]), int(bounds[i + 1])
        constellations.append(Constellation(det.labels[a:b], det.positions[a:b]))
        sources.append(det.source[a:b].copy())
    seq = ConstellationSequence(
        frame_ids=ids,
        timestamps=stamps,
        constellations=tuple(constellations),
        label_names=label_names,
        name=SEQUENCE_NAME,
    )
    return seq, tuple(sources)


def write_dataset(ds: SyntheticDataset, folder: Path, *, overwrite: bool = False) -> None:
    """Write ``ds`` in the TUM constellation layout under ``folder``.

    * ``constellations/<frame id>.txt``: one ``<label name> <x> <y> <z>`` line
      per detection (camera frame, metres; a label may contain spaces);
    * ``groundtruth.txt``: ``<timestamp> tx ty tz qx qy qz qw`` per frame,
      camera to world, under a ``# timestamp tx ty tz qx qy qz qw`` header;
    * ``coco.names``: the label names, one a line (line index = label index);
    * ``world.txt``: the world objects, ``<label name> <x> <y> <z>`` (world frame);
    * ``README.md``: what the folder is and the settings that made it.

    A folder that already holds files is refused unless ``overwrite`` is set;
    then the old ``constellations/`` folder is removed first so no stale
    frame survives.
    """
    folder = Path(folder)
    if folder.exists() and any(folder.iterdir()):
        if not overwrite:
            raise FileExistsError(f"{folder} is not empty; pass overwrite=True to replace it")
        shutil.rmtree(folder / "constellations", ignore_errors=True)
    write_constellations(ds.sequence, folder / "constellations")
    write_trajectory(ds.trajectory, folder / "groundtruth.txt")
    names = ds.sequence.label_names
    (folder / "coco.names").write_text("".join(f"{n}\n" for n in names), encoding="utf-8")
    world = Constellation(ds.world.labels, ds.world.positions)
    (folder / "world.txt").write_text(format_constellation(world, names), encoding="utf-8")
    (folder / "README.md").write_text(_readme(ds), encoding="utf-8")


def _readme(ds: SyntheticDataset) -> str:
    settings = "\n".join(
        f"| `{f.name}` | `{getattr(ds.config, f.name)!r}` |" for f in dataclasses.fields(ds.config)
    )
    n_objects = sum(len(c) for c in ds.sequence.constellations)
    return (
        f"# {SEQUENCE_NAME} (seed {ds.config.seed})\n\n"
        "Synthetic object-to-point detections generated by `swarmrec.synthetic` "
        "(docs/synthetic-world.md), in the layout of the TUM constellations:\n\n"
        "- `constellations/<timestamp>.txt`: `<label> <x> <y> <z>` per object, metres, "
        "camera frame (x right, y down, z forward), decreasing detector confidence.\n"
        "- `groundtruth.txt`: `timestamp tx ty tz qx qy qz qw`, camera to world "
        "(`p_world = R(q) p_cam + t`).\n"
        "- `coco.names`: label names; `world.txt`: the objects' world positions.\n\n"
        f"{len(ds.sequence)} frames, {n_objects} detections, "
        f"{len(ds.world)} world objects.\n\n"
        "| setting | value |\n|---|---|\n"
        f"{settings}\n"
    )
