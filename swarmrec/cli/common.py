"""Flags more than one command shares."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TypeAlias

from swarmrec.core.presets import PRESETS
from swarmrec.datasets.source import DatasetSource

__all__ = ["Subparsers", "add_dataset_flags", "dataset_source"]

#: argparse's own type for what add_subparsers() returns.
Subparsers: TypeAlias = "argparse._SubParsersAction[argparse.ArgumentParser]"


def add_dataset_flags(p: argparse.ArgumentParser) -> None:
    """What a swarm replays: shared by `run` and `compose` (and the dataset part of `evaluate`)."""
    p.add_argument(
        "--dataset",
        default="synthetic",
        help="'synthetic' (built-in office world) or a folder/.zip of <timestamp>.txt constellation files "
        "(default: synthetic)",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the synthetic world (default 0)")
    p.add_argument("--frames", type=int, help="use only the first N frames (synthetic: generate N)")
    p.add_argument("--labels", type=Path, help="label list, one name a line (default: COCO 80)")
    p.add_argument(
        "--groundtruth",
        type=Path,
        help="TUM trajectory (groundtruth.txt) for precision-recall; default: groundtruth.txt beside the "
        "constellations, or the synthetic world's poses",
    )
    p.add_argument("--preset", choices=sorted(PRESETS), default="paper", help="(default paper)")


def dataset_source(args: argparse.Namespace) -> DatasetSource:
    """The dataset the flags of :func:`add_dataset_flags` name."""
    return DatasetSource(args.dataset, args.seed, args.frames, args.labels, args.groundtruth)
