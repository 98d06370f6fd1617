"""The detector's replay mode: recorded constellations, a folder or zip of constellation files."""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass
from pathlib import Path

from swarmrec.core.types import Constellation, ConstellationSequence
from swarmrec.datasets.constellations import read_constellations
from swarmrec.datasets.labels import label_names
from swarmrec.errors import ConfigError, WireError
from swarmrec.runtime import ServiceContext
from swarmrec.runtime.settings import BusSettings, Config
from swarmrec.services.detector.frames import robot_block
from swarmrec.services.settings import DetectorSettings, PlaceSettings, VprSettings
from swarmrec.wire.codec import constellation_to_proto

__all__ = ["Block", "ReplaySource", "read_block", "wire_frames"]


@dataclass(frozen=True)
class Block:
    """The frames one robot replays: its block of the dataset, in order."""

    frames: list[Constellation]
    frame_ids: list[str]


def read_block(bus: BusSettings, detector: DetectorSettings, n_labels: int) -> Block:
    """Robot ``bus.robot``'s block of ``detector.dataset``; ConfigError without a dataset."""
    if not detector.dataset:
        raise ConfigError("the detector replays a dataset: set --dataset (a folder or .zip)")
    seq = _read_shared(detector.dataset, label_names(detector.labels_file, n_labels))
    block = robot_block(len(seq), bus, detector)
    return Block([seq.constellations[g] for g in block], [seq.frame_ids[g] for g in block])


class ReplaySource:
    """Its robot's block of a constellation dataset."""

    def __init__(self, ctx: ServiceContext) -> None:
        detector = ctx.settings(DetectorSettings)
        block = read_block(ctx.bus, detector, ctx.settings(PlaceSettings).n_labels)
        self.frames, self.frame_ids = block.frames, block.frame_ids
        ctx.log.info(
            "dataset loaded", extra={"fields": {"dataset": detector.dataset, "frames": len(self.frames)}}
        )

    def constellation(self, t: int) -> Constellation:
        return self.frames[t]


def wire_frames(config: Config) -> tuple[list[str], list[bytes | str]]:
    """What a compiled replaying detector sends (swarmrec-dataplane's ``detector``): each
    frame of its robot's block as the Python detector puts it on the wire (the same
    ``Constellation`` bytes), or, for a frame it cannot put there, why (its step is
    refused with that). The dataset is read and converted here, by the one reader and
    codec, so the two implementations cannot send different frames."""
    bus = config.bus
    places = config.get(PlaceSettings)
    if config.has(VprSettings) and config.get(VprSettings).place_method == "dvpr":
        raise ConfigError(
            "place_method dvpr describes camera images: run the detector in rgbd mode "
            "(a replayed constellation has no image)"
        )
    block = read_block(bus, config.get(DetectorSettings), places.n_labels)
    out: list[bytes | str] = []
    for t, (c, frame_id) in enumerate(zip(block.frames, block.frame_ids, strict=True)):
        try:
            wire = constellation_to_proto(c, bus.robot, t, frame_id, exact=places.exact_positions)
        except WireError as e:
            out.append(str(e))
            continue
        out.append(wire.SerializeToString())
    return block.frame_ids, out


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
