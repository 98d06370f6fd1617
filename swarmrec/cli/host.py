"""``swarmrec host``: several services (of one robot, or of many) in one process over one session.

A robot as one process: ``swarmrec host --kinds index-shard,verifier,descriptor,detector
--robots 3``; a simulation: ``--robots 0-49``. Each service is configured as ``swarmrec
serve`` would configure it (the flags of every kind hosted; the robot id from
``--robots``), and with ``--data-dir ROOT`` each keeps its data in
``ROOT/robot<r>/<kind>``. Metrics: one endpoint for the process, each service at
``/metrics/<kind>/<robot>``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from swarmrec.cli.common import Subparsers
from swarmrec.errors import ConfigError
from swarmrec.runtime.runner import choose_zenoh_runtime, zenoh_log_from_env
from swarmrec.runtime.settings import Config, StorageSettings, add_flags, load_config
from swarmrec.services import registry

__all__ = ["add", "parse_robots", "run"]


def parse_robots(text: str) -> list[int]:
    """``"3"``, ``"0,2,5"`` or ``"0-49"`` (ranges inclusive) as robot ids, each once, in order."""
    out: list[int] = []
    for part in (p.strip() for p in text.split(",") if p.strip()):
        lo, dash, hi = part.partition("-")
        try:
            ids = range(int(lo), int(hi) + 1) if dash else [int(lo)]
        except ValueError:
            raise ConfigError(f"robots must be ids or ranges such as 0-9, got {part!r}") from None
        out += [r for r in ids if r not in out]
    if not out:
        raise ConfigError("give at least one robot (--robots)")
    return out


def add(sub: Subparsers) -> None:
    p = sub.add_parser(
        "host",
        help="run several services (of one robot, or many robots) in one process over one session",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--kinds", required=True, help=f"comma-separated kinds ({', '.join(registry.kinds('robot'))})"
    )
    p.add_argument("--robots", default="0", help="robot ids: 3, 0,2,5 or 0-49 (default 0)")
    components = registry.all_components()
    add_flags(p, components)
    p.set_defaults(handler=run)


def configs(args: argparse.Namespace) -> list[tuple[str, Config]]:
    """(kind, configuration) of every service the flags ask for."""
    kinds = [k.strip() for k in args.kinds.split(",") if k.strip()]
    for kind in kinds:
        if registry.spec(kind).scope != "robot":
            raise ConfigError(f"{kind} runs once per swarm: serve it with `swarmrec serve {kind}`")
    out = []
    for robot in parse_robots(args.robots):
        for kind in kinds:
            entry = registry.spec(kind)
            config = load_config(
                entry.all_components, args, known=registry.all_components(), overrides={"robot": robot}
            )
            if config.has(StorageSettings):
                storage = config.get(StorageSettings)
                if storage.data_dir is not None:
                    config = config.replace(
                        storage.with_(data_dir=Path(storage.data_dir) / f"robot{robot}" / kind)
                    )
            out.append((kind, config))
    return out


def run(args: argparse.Namespace) -> int:
    services = configs(args)
    choose_zenoh_runtime(services[0][1].bus)
    zenoh_log_from_env()
    return registry.serve_many(services)
