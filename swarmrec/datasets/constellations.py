"""Reader and writer of the constellation text format.

One text file per frame, ``<frame id>.txt`` (the TUM RGB timestamp), one line
per object: ``<label> <x> <y> <z>`` in metres, camera frame. A label may
contain spaces ("teddy bear"): it is every token but the last three. Files are
ordered by their timestamp; the folder may also be a .zip archive holding the
files (at any depth, as the published ``constellations.zip`` does).

Empty files are legal (nothing was detected) and are counted in
``ConstellationSequence.skipped["empty_frames"]``. Everything else that does
not parse is an error naming the file and the line.
"""

from __future__ import annotations

import math
import zipfile
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from swarmrec.core.types import Constellation, ConstellationSequence
from swarmrec.datasets.labels import COCO_NAMES, LabelMap
from swarmrec.errors import DatasetError, MalformedLineError, UnknownLabelError

__all__ = ["parse_constellation", "read_constellations", "write_constellations"]


def parse_constellation(text: str, labels: LabelMap, source: str) -> Constellation:
    """Parse the text of one constellation file.

    Blank lines are skipped (some writers end files with one); a line with
    fewer than four tokens, a coordinate that is not a finite number, or a
    label not in ``labels`` raises an error pointing at ``source:line``.
    """
    label_idx: list[int] = []
    coords: list[tuple[float, float, float]] = []
    for number, raw in enumerate(text.splitlines(), start=1):
        tokens = raw.split()
        if not tokens:
            continue
        if len(tokens) < 4:
            raise MalformedLineError(
                source,
                f"expected '<label> <x> <y> <z>', got {len(tokens)} column(s): {raw.strip()!r}",
                line=number,
            )
        name = " ".join(tokens[:-3])
        try:
            xyz = (float(tokens[-3]), float(tokens[-2]), float(tokens[-1]))
        except ValueError:
            raise MalformedLineError(
                source, f"coordinates are not numbers: {' '.join(tokens[-3:])!r}", line=number
            ) from None
        if not all(math.isfinite(v) for v in xyz):
            raise MalformedLineError(source, f"non-finite coordinate in {raw.strip()!r}", line=number)
        index = labels.index(name)
        if index is None:
            raise UnknownLabelError(source, f"label {name!r} is not in the label list", line=number)
        label_idx.append(index)
        coords.append(xyz)
    if not label_idx:
        return Constellation.empty()
    return Constellation(np.array(label_idx, np.int64), np.array(coords, np.float64))


def _frame_key(name: str, source: str) -> tuple[float, str]:
    stem = Path(name).name[: -len(".txt")]
    try:
        return float(stem), stem
    except ValueError:
        raise DatasetError(
            source, f"constellation file name {Path(name).name!r} is not a timestamp"
        ) from None


def _iter_files(path: Path) -> Iterator[tuple[str, str, str]]:
    """Yield (frame file name, display source, text) for every .txt frame file."""
    if path.is_dir():
        for file in path.glob("*.txt"):
            try:
                text = file.read_text(encoding="utf-8")
            except (OSError, UnicodeDecodeError) as exc:
                raise DatasetError(file, f"cannot read: {exc}") from exc
            yield file.name, str(file), text
    elif path.is_file() and zipfile.is_zipfile(path):
        with zipfile.ZipFile(path) as archive:
            for info in archive.infolist():
                if info.is_dir() or not info.filename.endswith(".txt"):
                    continue
                source = f"{path}:{info.filename}"
                try:
                    text = archive.read(info).decode("utf-8")
                except (OSError, UnicodeDecodeError, zipfile.BadZipFile) as exc:
                    raise DatasetError(source, f"cannot read: {exc}") from exc
                yield info.filename, source, text
    elif path.exists():
        raise DatasetError(path, "expected a folder of <timestamp>.txt files or a .zip of them")
    else:
        raise DatasetError(path, "no such file or folder")


def read_constellations(
    path: str | Path,
    label_names: tuple[str, ...] = COCO_NAMES,
    name: str | None = None,
) -> ConstellationSequence:
    """Read every ``<timestamp>.txt`` of a folder or zip, in timestamp order.

    A folder that holds a ``constellations/`` subfolder (the layout of the
    synthetic world, ``swarmrec synth``) is read from that subfolder: its other
    .txt files (``groundtruth.txt``, ``world.txt``) are not frames.
    """
    path = Path(path)
    if path.is_dir() and (path / "constellations").is_dir():
        path = path / "constellations"
    labels = LabelMap(label_names)
    frames: list[tuple[tuple[float, str], Constellation]] = []
    for file_name, source, text in _iter_files(path):
        key = _frame_key(file_name, source)
        frames.append((key, parse_constellation(text, labels, source)))
    if not frames:
        raise DatasetError(path, "no <timestamp>.txt constellation files found")
    # Sorting by (value, text) gives the timestamp order and keeps the order
    # stable for equal values written differently.
    frames.sort(key=lambda item: item[0])
    empty = sum(1 for _, c in frames if len(c) == 0)
    return ConstellationSequence(
        frame_ids=tuple(key[1] for key, _ in frames),
        timestamps=np.array([key[0] for key, _ in frames]),
        constellations=tuple(c for _, c in frames),
        label_names=label_names,
        name=name or path.stem,
        skipped={"empty_frames": empty} if empty else {},
    )


def format_constellation(c: Constellation, label_names: tuple[str, ...]) -> str:
    """The text of one constellation file (repr of floats: exact round trip)."""
    return "".join(
        f"{label_names[int(label)]} {x!r} {y!r} {z!r}\n"
        for label, (x, y, z) in zip(c.labels, c.positions.tolist(), strict=True)
    )


def write_constellations(seq: ConstellationSequence, folder: str | Path) -> Path:
    """Write ``seq`` as ``folder/<frame id>.txt`` files; returns the folder."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for frame_id, c in zip(seq.frame_ids, seq.constellations, strict=True):
        (folder / f"{frame_id}.txt").write_text(format_constellation(c, seq.label_names), encoding="utf-8")
    return folder


def label_counts(seq: Iterable[Constellation], n_labels: int) -> np.ndarray:
    """How many objects of each label the frames hold in total."""
    counts = np.zeros(n_labels, np.int64)
    for c in seq:
        np.add.at(counts, c.labels, 1)
    return counts
