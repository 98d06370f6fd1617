"""``swarmrec serve <kind>``: run one service of one robot (the registry's kinds)."""

from __future__ import annotations

import argparse

from swarmrec.cli.common import Subparsers
from swarmrec.runtime.runner import choose_zenoh_runtime, zenoh_log_from_env
from swarmrec.runtime.settings import add_flags, load_config
from swarmrec.services import registry

__all__ = ["add", "run"]


def add(sub: Subparsers) -> None:
    p = sub.add_parser(
        "serve",
        help=f"run one service of one robot ({', '.join(registry.kinds())})",
        description=(
            "Run one swarm service until SIGTERM/SIGINT. Settings come from defaults < --config "
            "TOML file < SWARMREC_* environment < flags; `swarmrec serve KIND --help` lists the "
            "settings KIND reads. Prints one JSON 'ready' line on stdout when serving; logs are "
            "JSON lines on stderr."
        ),
    )
    kinds = p.add_subparsers(dest="kind", required=True, metavar="KIND")
    for kind, entry in registry.REGISTRY.items():
        k = kinds.add_parser(kind, help=entry.summary, description=entry.summary)
        add_flags(k, entry.all_components)
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    entry = registry.spec(args.kind)
    overrides = {"mode": entry.zenoh_mode} if entry.zenoh_mode else {}
    config = load_config(entry.all_components, args, known=registry.all_components(), overrides=overrides)
    choose_zenoh_runtime(config.bus)
    zenoh_log_from_env()
    return registry.serve(args.kind, config)
