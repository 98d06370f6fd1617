"""The detector's replay mode: recorded constellations, a folder or zip of constellation files."""

from __future__ import annotations

from swarmrec.core.types import Constellation
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
        seq = read_constellations(detector.dataset, label_names(detector.labels_file, n_labels))
        block = robot_block(len(seq), ctx.bus, detector)
        self.frames: list[Constellation] = [seq.constellations[g] for g in block]
        self.frame_ids = [seq.frame_ids[g] for g in block]
        ctx.log.info(
            "dataset loaded", extra={"fields": {"dataset": detector.dataset, "frames": len(self.frames)}}
        )

    def constellation(self, t: int) -> Constellation:
        return self.frames[t]
