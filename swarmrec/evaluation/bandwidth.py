"""What a decentralized query sends: the paper's byte model and the load on
each range holder.

The byte model is the paper's estimate (Table I, Fig. 1), not bytes measured
on a wire: per query, 1.5 B per non-zero label sent to a range holder, 3 B per
candidate returned, and 7 B per object (1 B label + 3 x 2 B position) of the
full constellation times ``n_fq`` robots, with at least 16 objects counted.
Averaged, as published, over every (robot, step) slot of the lock-step run,
the last robot's padding included.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from swarmrec.evaluation.scoring import DecentralizedRun

__all__ = ["ByteModel", "HolderLoad", "holder_load", "paper_byte_model"]

LABEL_BYTES = 1.5
CANDIDATE_BYTES = 3.0
OBJECT_BYTES = 7.0
MIN_OBJECTS_COUNTED = 16


@dataclass(frozen=True)
class ByteModel:
    """Mean bytes of one query, by part (the paper's estimate)."""

    partial_descriptors: float
    candidates: float
    constellations: float

    @property
    def total(self) -> float:
        return self.partial_descriptors + self.candidates + self.constellations

    def to_dict(self) -> dict[str, float]:
        return {**asdict(self), "total": self.total}


def paper_byte_model(run: DecentralizedRun, n_fq: int) -> ByteModel:
    """The published byte model for ``run``."""
    slots = run.n_robots * run.frames_per_robot
    labels = float(np.count_nonzero(run.descriptors))
    candidates = float(run.candidate_counts.sum())
    objects = np.maximum(run.descriptors.sum(axis=2), MIN_OBJECTS_COUNTED)
    return ByteModel(
        partial_descriptors=LABEL_BYTES * labels / slots,
        candidates=CANDIDATE_BYTES * candidates / slots,
        constellations=OBJECT_BYTES * n_fq * float(objects.sum()) / slots,
    )


@dataclass(frozen=True)
class HolderLoad:
    """Partial queries received by each range holder over the run."""

    bounds: list[int]
    partial_queries: list[int]
    labels: list[int]
    objects: list[int]

    @property
    def balance_ratio(self) -> float:
        """Busiest holder over the mean (1.0 is perfectly even)."""
        loads = np.asarray(self.partial_queries, dtype=np.float64)
        mean = loads.mean() if loads.size else 0.0
        return float(loads.max() / mean) if mean > 0 else 0.0

    def to_dict(self) -> dict[str, object]:
        return {**asdict(self), "balance_ratio": self.balance_ratio}


def holder_load(run: DecentralizedRun) -> HolderLoad:
    """Each holder's load: partial descriptors received (one per query frame
    with at least one object in the holder's range), non-zero labels and
    objects in them."""
    return HolderLoad(
        bounds=[int(b) for b in run.bounds],
        partial_queries=[int(v) for v in run.partial_descriptors_per_holder],
        labels=[int(v) for v in run.labels_per_holder],
        objects=[int(v) for v in run.objects_per_holder],
    )
