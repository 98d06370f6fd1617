"""The ``swarmrec`` command line: one module per command.

Each command module has ``add(subparsers)`` (its flags) and ``run(args)``
(parse the flags into a settings object, call the ``main`` of the module that
does the work, print a summary), so tests call the same code without a shell.
A :class:`~swarmrec.errors.SwarmrecError` becomes one line on stderr and exit
code 2.

A command's module is imported only when that command runs (or for the full
``--help``): ``swarmrec serve`` starts every service of a swarm and must not
pay for loading the experiments, their plots and the association kernels.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Callable, Sequence

from swarmrec.errors import SwarmrecError

__all__ = ["COMMANDS", "build_parser", "main"]

#: Each command and the module that implements it, in the order ``--help`` lists them.
COMMANDS: dict[str, str] = {
    "evaluate": "swarmrec.cli.evaluate",
    "synth": "swarmrec.cli.synth",
    "run": "swarmrec.cli.run",
    "up": "swarmrec.cli.up",
    "down": "swarmrec.cli.up",
    "compose": "swarmrec.cli.compose",
    "landmarks": "swarmrec.cli.landmarks",
    "slam": "swarmrec.cli.slam",
    "serve": "swarmrec.cli.serve",
    "host": "swarmrec.cli.host",
    "query": "swarmrec.cli.clients",
    "members": "swarmrec.cli.clients",
    "loop-closures": "swarmrec.cli.clients",
    "place-query": "swarmrec.cli.method_clients",
    "clusters": "swarmrec.cli.method_clients",
    "slam-team": "swarmrec.cli.method_clients",
    "slam-estimate": "swarmrec.cli.method_clients",
    "slam-map": "swarmrec.cli.method_clients",
    "landmark-round": "swarmrec.cli.method_clients",
    "explain": "swarmrec.cli.explain",
    "pki": "swarmrec.cli.pki",
    "k8s": "swarmrec.cli.k8s",
    "vpr": "swarmrec.cli.vpr",
}


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The parser of every command (``only``: of that one command)."""
    parser = argparse.ArgumentParser(
        prog="swarmrec",
        description="Decentralized place and landmark recognition for robot swarms, over zenoh, "
        "with measured bytes.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    modules = [COMMANDS[only]] if only in COMMANDS else list(dict.fromkeys(COMMANDS.values()))
    for name in modules:
        importlib.import_module(name).add(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    command = argv[0] if argv else None
    args = build_parser(command).parse_args(argv)
    handler: Callable[[argparse.Namespace], int] = args.handler
    try:
        return handler(args)
    except SwarmrecError as exc:
        print(f"swarmrec {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        # The reader left (``| head``): what was printed is what it wanted. Point stdout at
        # /dev/null so the interpreter's final flush does not raise again.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


if __name__ == "__main__":
    sys.exit(main())
