"""``swarmrec synth``: write the synthetic office world as constellation files."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from swarmrec.cli.common import Subparsers
from swarmrec.synthetic import OfficeConfig, generate_office, write_dataset

__all__ = ["add", "run"]


def add(sub: Subparsers) -> None:
    p = sub.add_parser(
        "synth", help="write the synthetic office world as constellation files + groundtruth.txt"
    )
    p.add_argument("--out", type=Path, required=True, help="folder to write")
    p.add_argument("--seed", type=int, default=0, help="the world's seed (default 0)")
    p.add_argument("--json", action="store_true", help="print what was written as JSON")
    p.add_argument("--frames", type=int, help="number of frames (default: the world's default)")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    config = (
        OfficeConfig(seed=args.seed)
        if args.frames is None
        else OfficeConfig(seed=args.seed, n_frames=args.frames)
    )
    ds = generate_office(config)
    write_dataset(ds, args.out)
    if args.json:
        print(json.dumps({"out": str(args.out), "frames": len(ds.sequence)}))
    else:
        print(
            f"wrote the synthetic office of seed {args.seed}, {len(ds.sequence)} frames, to {args.out} "
            "(constellations/ and groundtruth.txt): swarmrec evaluate --dataset "
            f"{args.out}, or swarmrec run --dataset {args.out}"
        )
    return 0
