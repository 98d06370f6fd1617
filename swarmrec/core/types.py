"""The small value types the pure core works on.

A *constellation* is what the detector makes of one frame: one label index and
one 3D point (metres, camera frame, z forward) per detected object. A
*sequence* is an ordered list of constellations with their frame ids, plus the
label names that give the label indices a meaning.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

__all__ = ["Constellation", "ConstellationSequence", "Trajectory"]

IntArray = npt.NDArray[np.int64]
FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class Constellation:
    """Objects seen in one frame: ``labels[k]`` is at ``positions[k]``.

    The object order is kept as the detector gave it: the paper's data
    association breaks ties by that order, so it is part of the data.
    """

    labels: IntArray
    positions: FloatArray

    def __post_init__(self) -> None:
        labels = np.ascontiguousarray(self.labels, dtype=np.int64).reshape(-1)
        positions = np.ascontiguousarray(self.positions, dtype=np.float64).reshape(-1, 3)
        if labels.shape[0] != positions.shape[0]:
            raise ValueError(f"constellation has {labels.shape[0]} labels but {positions.shape[0]} positions")
        object.__setattr__(self, "labels", labels)
        object.__setattr__(self, "positions", positions)

    def __len__(self) -> int:
        return int(self.labels.shape[0])

    @classmethod
    def empty(cls) -> Constellation:
        return cls(np.zeros(0, np.int64), np.zeros((0, 3), np.float64))


@dataclass(frozen=True, eq=False)
class ConstellationSequence:
    """An ordered dataset of constellations (frame order = list order)."""

    frame_ids: tuple[str, ...]
    timestamps: FloatArray
    constellations: tuple[Constellation, ...]
    label_names: tuple[str, ...]
    name: str = "sequence"
    # Counted, legal oddities met while reading (e.g. "empty_frames": 3).
    skipped: dict[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = len(self.constellations)
        if len(self.frame_ids) != n or len(self.timestamps) != n:
            raise ValueError("frame_ids, timestamps and constellations must have the same length")
        object.__setattr__(self, "timestamps", np.asarray(self.timestamps, dtype=np.float64))

    def __len__(self) -> int:
        return len(self.constellations)

    @property
    def n_labels(self) -> int:
        return len(self.label_names)

    def subset(self, indices: Sequence[int]) -> ConstellationSequence:
        """A new sequence with only the frames at ``indices`` (in that order)."""
        idx = list(indices)
        return ConstellationSequence(
            frame_ids=tuple(self.frame_ids[i] for i in idx),
            timestamps=self.timestamps[idx],
            constellations=tuple(self.constellations[i] for i in idx),
            label_names=self.label_names,
            name=self.name,
        )


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Camera poses in TUM format: ``timestamps[i]``, ``positions[i]`` (x y z),
    ``quaternions[i]`` (qx qy qz qw, camera to world)."""

    timestamps: FloatArray
    positions: FloatArray
    quaternions: FloatArray

    def __post_init__(self) -> None:
        t = np.asarray(self.timestamps, dtype=np.float64).reshape(-1)
        p = np.asarray(self.positions, dtype=np.float64).reshape(-1, 3)
        q = np.asarray(self.quaternions, dtype=np.float64).reshape(-1, 4)
        if not (t.shape[0] == p.shape[0] == q.shape[0]):
            raise ValueError("timestamps, positions and quaternions must have the same length")
        object.__setattr__(self, "timestamps", t)
        object.__setattr__(self, "positions", p)
        object.__setattr__(self, "quaternions", q)

    def __len__(self) -> int:
        return int(self.timestamps.shape[0])
