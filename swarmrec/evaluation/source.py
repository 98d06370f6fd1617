"""The one way a constellation dataset is loaded: the offline evaluation, the swarm's
place-recognition experiment and the compose generator all call :func:`load_dataset`.

A :class:`DatasetSource` names the data: ``"synthetic"`` (the built-in office world,
``seed`` and ``frames``), or a folder / ``.zip`` of constellation files with an
optional label list and ground truth (a ``groundtruth.txt`` beside the
constellations is used when none is given). ``frames`` keeps the first N frames.

The services read datasets from files: ``materialize`` writes the sequence as
constellation files there when it is not on disk as it will be replayed (the
synthetic world, or a subset of a user's dataset), so every detector reads the
same frames the report scores.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from swarmrec.core.types import ConstellationSequence, Trajectory
from swarmrec.datasets.constellations import read_constellations, write_constellations
from swarmrec.datasets.labels import label_names
from swarmrec.datasets.tum import read_trajectory
from swarmrec.errors import ConfigError
from swarmrec.synthetic import OfficeConfig, generate_office, write_dataset

__all__ = ["SYNTHETIC", "DatasetSource", "LoadedDataset", "load_dataset"]

SYNTHETIC = "synthetic"


@dataclass(frozen=True)
class DatasetSource:
    """Which constellations, and their labels and poses."""

    dataset: str = SYNTHETIC
    seed: int = 0
    frames: int | None = None
    labels: Path | None = None
    groundtruth: Path | None = None

    def __post_init__(self) -> None:
        if self.frames is not None and self.frames < 1:
            raise ConfigError(f"frames must be >= 1, got {self.frames}")

    @property
    def synthetic(self) -> bool:
        return self.dataset == SYNTHETIC


@dataclass(frozen=True, eq=False)
class LoadedDataset:
    """A dataset in memory, and where it is on disk when it is (``folder``: what a
    detector replays)."""

    sequence: ConstellationSequence
    trajectory: Trajectory | None
    labels_file: Path | None
    folder: Path | None


def load_dataset(source: DatasetSource, *, materialize: Path | None = None) -> LoadedDataset:
    """Read (or generate) ``source``; with ``materialize``, make sure it is on disk as
    constellation files (written there when it is not already a file or folder as is)."""
    if source.synthetic:
        config = (
            OfficeConfig(seed=source.seed)
            if source.frames is None
            else OfficeConfig(seed=source.seed, n_frames=source.frames)
        )
        world = generate_office(config)
        if materialize is None:
            return LoadedDataset(world.sequence, world.trajectory, None, None)
        # Read back what was written: the report scores exactly what the detectors replay.
        write_dataset(world, materialize, overwrite=True)
        seq = read_constellations(materialize, label_names())
        return LoadedDataset(seq, read_trajectory(materialize / "groundtruth.txt"), None, materialize)
    path = Path(source.dataset)
    seq = read_constellations(path, label_names(source.labels))
    folder: Path | None = path
    if source.frames is not None and source.frames < len(seq):
        seq = seq.subset(range(source.frames))
        if materialize is not None:
            write_constellations(seq, materialize)
        folder = materialize
    gt_path = source.groundtruth
    if gt_path is None and path.is_dir() and (path / "groundtruth.txt").is_file():
        gt_path = path / "groundtruth.txt"
    return LoadedDataset(seq, read_trajectory(gt_path) if gt_path else None, source.labels, folder)
