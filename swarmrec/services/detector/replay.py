"""The detector's replay mode: recorded constellations, a folder or zip of constellation files."""

from __future__ import annotations

import functools
import os
from pathlib import Path

from swarmrec.core.types import Constellation, ConstellationSequence
from swarmrec.datasets.constellations import read_constellations
from swarmrec.datasets.labels import label_names
from swarmrec.errors import ConfigError
from swarmrec.runtime import ServiceContext
from swarmrec.services.detector.frames import robot_block
from swarmrec.services.settings import DetectorSettings, PlaceSettings

__all__ = ["ReplaySource"]


class ReplaySource:
    """Its robot's block of a constellation dataset."""

    def __init__(self, ctx: ServiceContext) -> None:
        detector = ctx.settings(DetectorSettings)
        n_labels = ctx.settings(PlaceSettings).n_labels
        if not detector.dataset:
            raise ConfigError("the detector replays a dataset: set --dataset (a folder or .zip)")
        seq = _read_shared(detector.dataset, label_names(detector.labels_file, n_labels))
        block = robot_block(len(seq), ctx.bus, detector)
        self.frames: list[Constellation] = [seq.constellations[g] for g in block]
        self.frame_ids = [seq.frame_ids[g] for g in block]
        ctx.log.info(
            "dataset loaded", extra={"fields": {"dataset": detector.dataset, "frames": len(self.frames)}}
        )

    def constellation(self, t: int) -> Constellation:
        return self.frames[t]


def _read_shared(dataset: str, labels: tuple[str, ...]) -> ConstellationSequence:
    """The dataset read once per process: the detectors of many robots hosted together
    (``--hosting robots:K``) each take their block of the same file (reading TUM's 2585
    frames took each of them 0.2 s of the start)."""
    st = os.stat(dataset)
    return _read_cached(str(Path(dataset).resolve()), st.st_mtime_ns, st.st_size, labels)


@functools.lru_cache(maxsize=2)
def _read_cached(path: str, _mtime_ns: int, _size: int, labels: tuple[str, ...]) -> ConstellationSequence:
    # The file's time and size are in the key: a dataset rewritten in place is read again.
    return read_constellations(path, labels)
