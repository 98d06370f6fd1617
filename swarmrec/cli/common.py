"""Flags more than one command shares."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeAlias

from swarmrec.core.presets import PRESETS
from swarmrec.evaluation.source import DatasetSource
from swarmrec.services.settings import IndexSettings

if TYPE_CHECKING:
    from swarmrec.deployments.local import LocalSettings
    from swarmrec.experiments.places.settings import PlacesSettings

__all__ = [
    "Subparsers",
    "add_dataset_flags",
    "add_index_flags",
    "add_local_swarm_flags",
    "dataset_source",
    "local_settings",
    "swarm_places_settings",
]

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


def add_local_swarm_flags(p: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """How a local swarm runs: --insecure, --hosting, --data-plane (`run` and `up`)."""
    p.add_argument(
        "--insecure",
        action="store_true",
        help="plaintext, unauthenticated zenoh links (debugging; logged by every process); "
        "default: mutual TLS with a PKI made for the run and the router's access control",
    )
    p.add_argument(
        "--hosting",
        default="service",
        metavar="service|robot|robots:K",
        help="how the local swarm puts services in processes: one per service (default), one per robot "
        "(its services share a session), or K robots per process (a simulation of many robots)",
    )
    p.add_argument(
        "--data-plane",
        choices=("compiled", "python"),
        default="compiled",
        help="which implementation serves the kinds that have a compiled one: compiled (default: the "
        "Rust host, built by `make dataplane`; docs/dataplane.md) or python (the reference)",
    )


def local_settings(args: argparse.Namespace) -> LocalSettings:
    """The local deployment's settings from ``add_local_swarm_flags`` (and `run`'s link flags)."""
    # (Imported here: `serve` shares this module and must not load the deployments.)
    from swarmrec.deployments.links import LinkSpec
    from swarmrec.deployments.local import LocalSettings

    return LocalSettings(
        hosting=args.hosting,
        security="insecure" if args.insecure else "mtls",
        link=LinkSpec(getattr(args, "link_rate", None), getattr(args, "link_latency", None)),
        schedule=getattr(args, "link_schedule", None),
        schedule_unit=getattr(args, "schedule_unit", "step"),
        topology=getattr(args, "topology", "star"),
        radio_range_m=getattr(args, "radio_range", None),
    )


def add_index_flags(p: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """The elastic index's replicas and rebalancing (`run` and `up`)."""
    p.add_argument(
        "--replicas",
        type=int,
        default=IndexSettings.replicas,
        help=f"index shards that hold each label group (default {IndexSettings.replicas}; 1 is the paper's "
        "one range a shard, no shard may then be lost)",
    )
    p.add_argument(
        "--rebalance-target",
        type=float,
        default=IndexSettings.rebalance_target,
        help="the coordinator adds and moves replicas while the busiest shard serves more than this "
        f"times the mean (default {IndexSettings.rebalance_target})",
    )


def swarm_places_settings(args: argparse.Namespace, out: Path, **changes: Any) -> PlacesSettings:
    """The places run a swarm left running is started for (`up`, `compose up`, `k8s up`): the
    dataset flags, --robots, --swarm, --timeout and --free, and ``changes``."""
    # (Imported here: `serve` shares this module and must not load the experiments.)
    from swarmrec.experiments.places.settings import PlacesSettings

    return PlacesSettings(
        source=dataset_source(args),
        robots=args.robots,
        preset=args.preset,
        pace="fast" if args.free else "lockstep",
        swarm=args.swarm,
        request_timeout_s=args.timeout,
        out=out,
        **changes,
    )
