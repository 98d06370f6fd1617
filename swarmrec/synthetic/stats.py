"""Statistics of a constellation sequence, and a side-by-side markdown comparison.

Run as a script to compare the synthetic office with the real TUM constellations::

    python -m swarmrec.synthetic.stats                      # seed 0, default settings
    python -m swarmrec.synthetic.stats --seed 3 --tum path/to/constellations.zip

The TUM zip is read with :func:`swarmrec.datasets.constellations.read_constellations`.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TypedDict

import numpy as np

from swarmrec.core.types import ConstellationSequence
from swarmrec.datasets.constellations import read_constellations
from swarmrec.synthetic.config import OfficeConfig
from swarmrec.synthetic.labels import coco_names
from swarmrec.synthetic.office import generate_office

__all__ = [
    "SequenceStats",
    "StatsSettings",
    "compare_markdown",
    "main",
    "sequence_stats",
    "stats_markdown",
]

#: Where the real TUM constellations lie in a checkout next to ``../shared``.
DEFAULT_TUM_ZIP = (
    Path(__file__).resolve().parents[2].parent
    / "shared"
    / "data"
    / "tum_fr3_long_office_household_constellations.zip"
)


class SequenceStats(TypedDict):
    """What :func:`sequence_stats` measures. Percentages are in [0, 100]."""

    name: str
    n_frames: int
    n_objects: int
    objects_per_frame_mean: float
    objects_per_frame_median: float
    objects_per_frame_max: int
    #: Number of objects in a frame -> number of frames with that many.
    objects_per_frame_histogram: dict[int, int]
    #: Frames with fewer than 3 objects (the paper ignores them), in per cent.
    frames_below_3_pct: float
    n_distinct_labels: int
    #: Every label seen, most frequent first: (name, per cent of all objects).
    label_frequency_pct: list[tuple[str, float]]
    #: Median, 5th and 95th percentile of the objects' z (depth along the camera axis).
    depth_median_m: float
    depth_p05_m: float
    depth_p95_m: float


def sequence_stats(seq: ConstellationSequence) -> SequenceStats:
    """Objects per frame, label frequencies and depths of ``seq``."""
    counts = np.array([len(c) for c in seq.constellations], dtype=np.int64)
    n_frames = len(seq)
    labels = np.concatenate([c.labels for c in seq.constellations]) if n_frames else np.zeros(0, np.int64)
    depths = np.concatenate([c.positions[:, 2] for c in seq.constellations]) if n_frames else np.zeros(0)
    n_objects = int(labels.size)
    per_label = np.bincount(labels, minlength=seq.n_labels) if n_objects else np.zeros(0, np.int64)
    order = sorted(np.flatnonzero(per_label), key=lambda i: (-int(per_label[i]), int(i)))
    hist = np.bincount(counts) if n_frames else np.zeros(0, np.int64)
    quant = np.percentile(depths, [5, 50, 95]) if n_objects else np.full(3, np.nan)
    return SequenceStats(
        name=seq.name,
        n_frames=n_frames,
        n_objects=n_objects,
        objects_per_frame_mean=float(counts.mean()) if n_frames else 0.0,
        objects_per_frame_median=float(np.median(counts)) if n_frames else 0.0,
        objects_per_frame_max=int(counts.max()) if n_frames else 0,
        objects_per_frame_histogram={k: int(v) for k, v in enumerate(hist) if v},
        frames_below_3_pct=100.0 * float((counts < 3).mean()) if n_frames else 0.0,
        n_distinct_labels=len(order),
        label_frequency_pct=[(seq.label_names[i], 100.0 * int(per_label[i]) / n_objects) for i in order],
        depth_median_m=float(quant[1]),
        depth_p05_m=float(quant[0]),
        depth_p95_m=float(quant[2]),
    )


def stats_markdown(stats: Sequence[SequenceStats], names: Sequence[str], top: int = 15) -> str:
    """Markdown tables with one column per statistics set: summary, histogram, labels."""
    if len(stats) != len(names):
        raise ValueError(f"{len(stats)} statistics sets but {len(names)} names")
    head = "| | " + " | ".join(names) + " |\n|---|" + "---:|" * len(names) + "\n"

    def row(title: str, cells: Sequence[str]) -> str:
        return f"| {title} | " + " | ".join(cells) + " |\n"

    out = ["**Summary**\n\n", head]
    out.append(row("frames", [str(s["n_frames"]) for s in stats]))
    out.append(row("objects", [str(s["n_objects"]) for s in stats]))
    out.append(row("objects per frame, mean", [f"{s['objects_per_frame_mean']:.2f}" for s in stats]))
    out.append(row("objects per frame, median", [f"{s['objects_per_frame_median']:.1f}" for s in stats]))
    out.append(row("objects per frame, max", [str(s["objects_per_frame_max"]) for s in stats]))
    out.append(row("frames with < 3 objects", [f"{s['frames_below_3_pct']:.1f} %" for s in stats]))
    out.append(row("distinct labels", [str(s["n_distinct_labels"]) for s in stats]))
    out.append(
        row(
            "depth z, median (5-95 %)",
            [f"{s['depth_median_m']:.2f} m ({s['depth_p05_m']:.2f}-{s['depth_p95_m']:.2f})" for s in stats],
        )
    )

    out += ["\n**Objects per frame** (per cent of frames)\n\n", head.replace("| |", "| objects |", 1)]
    largest = max((s["objects_per_frame_max"] for s in stats), default=0)
    for k in range(largest + 1):
        cells = [
            f"{100.0 * s['objects_per_frame_histogram'].get(k, 0) / max(s['n_frames'], 1):.1f}" for s in stats
        ]
        out.append(row(str(k), cells))

    out += [f"\n**Top {top} labels** (per cent of all objects)\n\n", head.replace("| |", "| rank |", 1)]
    for rank in range(top):
        cells = []
        for s in stats:
            freq = s["label_frequency_pct"]
            cells.append(f"{freq[rank][0]} {freq[rank][1]:.1f}" if rank < len(freq) else "")
        out.append(row(str(rank + 1), cells))
    return "".join(out)


def compare_markdown(
    a_stats: SequenceStats, b_stats: SequenceStats, names: Sequence[str], top: int = 15
) -> str:
    """Side-by-side markdown tables of two statistics sets, ``names`` = their two titles."""
    if len(names) != 2:
        raise ValueError(f"compare_markdown needs two names, got {len(names)}")
    return stats_markdown([a_stats, b_stats], names, top=top)


@dataclass(frozen=True)
class StatsSettings:
    """What ``python -m swarmrec.synthetic.stats`` compares."""

    tum_zip: Path = DEFAULT_TUM_ZIP
    seed: int = 0
    n_frames: int = 2500
    top: int = 15


def main(settings: StatsSettings) -> str:
    """The markdown comparison of the synthetic office (and TUM, if its zip exists)."""
    start = time.perf_counter()
    ds = generate_office(OfficeConfig(seed=settings.seed, n_frames=settings.n_frames))
    elapsed = time.perf_counter() - start
    print(f"generated {len(ds.sequence)} synthetic frames in {elapsed:.2f} s", file=sys.stderr)
    stats = [sequence_stats(ds.sequence)]
    names = [f"synthetic (seed {settings.seed})"]
    if settings.tum_zip.exists():
        stats.append(sequence_stats(read_constellations(settings.tum_zip, coco_names())))
        names.append("TUM fr3 long office household")
    else:
        print(f"{settings.tum_zip} not found: synthetic statistics only", file=sys.stderr)
    return stats_markdown(stats, names, top=settings.top)


def _parse_args(argv: Sequence[str] | None) -> StatsSettings:
    parser = argparse.ArgumentParser(
        prog="python -m swarmrec.synthetic.stats",
        description="Compare the synthetic office's statistics with the real TUM constellations.",
    )
    parser.add_argument("--tum", type=Path, default=DEFAULT_TUM_ZIP, help="TUM constellation zip")
    parser.add_argument("--seed", type=int, default=0, help="seed of the synthetic world")
    parser.add_argument("--frames", type=int, default=2500, help="synthetic frames")
    parser.add_argument("--top", type=int, default=15, help="labels listed")
    args = parser.parse_args(argv)
    return StatsSettings(tum_zip=args.tum, seed=args.seed, n_frames=args.frames, top=args.top)


if __name__ == "__main__":
    print(main(_parse_args(None)), end="")
