"""``swarmrec explain``: why a frame was (not) closed with another, from a finished run's
folder (``--run``, the default ``runs/swarm``) or a live swarm (``--connect``)."""

from __future__ import annotations

import argparse
from pathlib import Path

from swarmrec.cli.clients import add_connection_flags, client_of
from swarmrec.cli.common import Subparsers
from swarmrec.errors import ConfigError
from swarmrec.experiments.places.explain import Explanation, RunFolder, explain_live, explain_run

__all__ = ["add", "run"]

DEFAULT_RUN = Path("runs/swarm")


def add(sub: Subparsers) -> None:
    p = sub.add_parser(
        "explain",
        help="why a frame was not closed with another: where each candidate of its query stopped",
        description=(
            "The loop-closure funnel of robot ROBOT's frame FRAME: every candidate of its query and the "
            "stage it stopped at (shard, selection, verification, closure) with the reason. With --with, "
            "what happened to that one pair, both ways. From a finished run's folder (--run, default "
            f"{DEFAULT_RUN}), where a frame no shard returned is explained with the shards' scores "
            "recomputed from the run's data, or from a live swarm (--connect), whose descriptors keep "
            "their last explain_reports reports."
        ),
    )
    p.add_argument("robot", type=int, help="the querying robot")
    p.add_argument("frame", type=int, help="its robot-local frame index")
    p.add_argument(
        "--with",
        dest="other",
        type=int,
        nargs=2,
        metavar=("ROBOT2", "FRAME2"),
        help="the frame it should have been closed with",
    )
    p.add_argument(
        "--run",
        type=Path,
        help=f"a finished run's folder (default {DEFAULT_RUN}), or a swarm left running there "
        "(its swarm.json, from swarmrec up: asked live); not with --connect",
    )
    add_connection_flags(p, run_flag=False)
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    if args.robot < 0 or args.frame < 0 or (args.other and min(args.other) < 0):
        raise ConfigError("robot and frame numbers are >= 0")
    other = tuple(args.other) if args.other else None
    kept = args.run is not None and (args.run / "swarm.json").is_file()
    if args.connect is not None or kept:
        if args.connect is not None and args.run is not None:
            raise ConfigError("--run names a folder, --connect asks a live swarm: one of them")
        with client_of(args, folder=args.run if kept else None) as swarm:
            ex = explain_live(swarm, args.robot, args.frame, other)
    else:
        ex = explain_run(RunFolder(args.run or DEFAULT_RUN), args.robot, args.frame, other)
    show(ex, as_json=args.json)
    return 0 if ex.found else 3


def show(ex: Explanation, *, as_json: bool) -> None:
    print(ex.to_json() if as_json else "\n".join(ex.lines()))
