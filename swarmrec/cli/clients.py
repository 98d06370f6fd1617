"""``swarmrec query``, ``members`` and ``loop-closures`` (``--method dvpr``: the place
owner's): ask a running swarm, from any host that reaches its router (``--connect
tls/host:7447``) or its gRPC gateway (``--connect grpc://host:50051``), as the identity
``--identity`` of the PKI in ``--pki-dir``; or, on the machine that runs it, from the folder
of a swarm left running (``--run DIR``: its ``swarm.json`` names the router, the swarm and
the PKI; ``runs/up`` by default when a ``swarmrec up`` keeps a swarm there)."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

from swarmrec.cli.common import Subparsers
from swarmrec.client import GRPC_SCHEME, SwarmClient, connect
from swarmrec.core.presets import PRESETS
from swarmrec.datasets.constellations import parse_constellation
from swarmrec.datasets.labels import LabelMap, label_names
from swarmrec.deployments.base import read_attach_json
from swarmrec.deployments.local_up import require_keeper
from swarmrec.errors import ConfigError
from swarmrec.runtime.tls import TlsFiles

__all__ = ["DEFAULT_SWARM_DIR", "add", "add_connection_flags", "client_of", "swarm_dir_of"]

#: Where ``swarmrec up`` keeps its swarm by default, and where a client looks when told nothing.
DEFAULT_SWARM_DIR = Path("runs/up")
#: The router a client tries when told nothing and no swarm is kept in DEFAULT_SWARM_DIR
#: (a compose swarm's published port).
FALLBACK_CONNECT = "tls/127.0.0.1:7447"


def add_connection_flags(p: argparse.ArgumentParser, *, run_flag: bool = True) -> None:
    """How a command reaches a running swarm: --run (unless ``run_flag`` is False: the command
    has a --run of its own), --connect, --swarm, --pki-dir, --identity, --timeout and --json."""
    if run_flag:
        p.add_argument(
            "--run",
            dest="swarm_dir",
            type=Path,
            metavar="DIR",
            help="the folder of a swarm left running (its swarm.json, from swarmrec up, compose up or "
            f"k8s up): its router, name and PKI (default {DEFAULT_SWARM_DIR} when a swarm is kept there, "
            f"else --connect {FALLBACK_CONNECT})",
        )
    p.add_argument(
        "--connect",
        help="router endpoint(s), comma-separated, or the gRPC gateway as grpc://host:port; a tcp/ "
        "endpoint is the insecure mode (instead of --run)",
    )
    p.add_argument("--swarm", help="swarm name (default: the swarm file's, else local)")
    p.add_argument(
        "--pki-dir",
        type=Path,
        default=os.environ.get("SWARMREC_PKI_DIR") or None,
        help="the swarm's PKI folder (ca.pem and this client's pair; env SWARMREC_PKI_DIR)",
    )
    p.add_argument(
        "--identity",
        default=os.environ.get("SWARMREC_IDENTITY", ""),
        help="common name of this client's certificate (default client.cli.<swarm>; env SWARMREC_IDENTITY)",
    )
    p.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for answers (default 5)")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")


def add(sub: Subparsers) -> None:
    common = add_connection_flags

    p = sub.add_parser("query", help="ask a running swarm where a constellation was seen (nothing is stored)")
    p.add_argument(
        "constellation", type=Path, help="a constellation file (one 'label x y z' line per object)"
    )
    p.add_argument("--labels", type=Path, help="label list (default: COCO 80)")
    p.add_argument("--preset", choices=sorted(PRESETS), default="paper", help="(default paper)")
    p.add_argument("--top", type=int, default=10, help="matches to show (default 10)")
    common(p)
    p.set_defaults(handler=_query)
    p = sub.add_parser("members", help="list a running swarm's live services and shard label ranges")
    common(p)
    p.set_defaults(handler=_members)
    p = sub.add_parser("loop-closures", help="fetch the loop closures a robot has found")
    p.add_argument("robot", type=int, help="robot id")
    p.add_argument("--min-score", type=float, default=0.0, help="only closures at least this good")
    p.add_argument(
        "--method",
        choices=("constellations", "dvpr"),
        default="constellations",
        help="whose: the robot's descriptor (constellations, the default) or its place owner (dvpr)",
    )
    common(p)
    p.set_defaults(handler=_loop_closures)


def swarm_dir_of(args: argparse.Namespace) -> Path | None:
    """The folder of a swarm left running that the flags name, or the default one when they
    name nothing and a swarm is kept there; None: --connect (or its fallback) says where."""
    folder: Path | None = getattr(args, "swarm_dir", None)
    if folder is not None and args.connect is not None:
        raise ConfigError("--run names a swarm's folder, --connect its address: one of them")
    if folder is None and args.connect is None and (DEFAULT_SWARM_DIR / "swarm.json").is_file():
        folder = DEFAULT_SWARM_DIR
    return folder


def _swarm_file(folder: Path) -> dict[str, Any]:
    """What a client needs of ``folder/swarm.json`` (any deployment's), checked."""
    path = folder / "swarm.json"
    data = read_attach_json(folder)
    if not isinstance(data.get("router_endpoint"), str):
        raise ConfigError(f"{path} is not a swarm file: it names no router_endpoint")
    if data.get("deployment") == "local":
        require_keeper(folder, int(data.get("pid", 0)))
    return data


def client_of(args: argparse.Namespace, folder: Path | None = None) -> SwarmClient:
    """The client the flags of :func:`add_connection_flags` describe (``folder``: the swarm
    left running there, whatever the flags say)."""
    folder = folder or swarm_dir_of(args)
    address, swarm, pki_dir = args.connect or FALLBACK_CONNECT, args.swarm or "local", args.pki_dir
    if folder is not None:
        info = _swarm_file(folder)
        address, swarm = info["router_endpoint"], args.swarm or str(info.get("swarm", "local"))
        if pki_dir is None and info.get("security", "mtls") != "insecure" and info.get("pki_dir"):
            pki_dir = Path(info["pki_dir"])
    plaintext = address.startswith("tcp/") or (address.startswith(GRPC_SCHEME) and pki_dir is None)
    tls = None
    if pki_dir is not None:
        tls = TlsFiles.in_dir(Path(pki_dir), args.identity or f"client.cli.{swarm}")
    elif not plaintext:
        raise ConfigError(
            f"{address} is mutual TLS: give the swarm's PKI folder (--pki-dir or SWARMREC_PKI_DIR), "
            f"or the folder of a swarm left running (--run DIR)"
        )
    reason = "the swarm file says insecure" if folder is not None else "--connect tcp/..."
    return connect(address, swarm, timeout_s=args.timeout, tls=tls, insecure_reason=reason)


def _query(args: argparse.Namespace) -> int:
    names = label_names(args.labels)
    try:
        text = args.constellation.read_text(encoding="utf-8")
    except OSError as e:
        raise ConfigError(f"cannot read {args.constellation}: {e.strerror}") from None
    constellation = parse_constellation(text, LabelMap(names), str(args.constellation))
    with client_of(args) as swarm:
        result = swarm.query(constellation, preset=args.preset)
    matches = result.matches[: args.top]
    if args.json:
        print(
            json.dumps(
                {
                    "matches": [
                        {
                            "robot": m.match_robot_id,
                            "frame": m.match_frame_index,
                            "score": m.score,
                            "semantic_score": m.semantic_score,
                            "n_matched": m.n_matched,
                        }
                        for m in matches
                    ],
                    "candidates": result.n_candidates,
                    "verified_robots": result.verified_robots,
                    "failed_shards": result.failed_shards,
                    "failed_verifiers": result.failed_verifiers,
                    "duration_ms": result.duration_ms,
                }
            )
        )
    else:
        print(
            f"{len(result.matches)} matches from {result.n_candidates} candidates "
            f"(verified by robots {result.verified_robots}) in {result.duration_ms:.1f} ms"
        )
        print(f"{'rank':>4} {'robot':>5} {'frame':>6} {'score':>8} {'semantic':>8} {'objects':>7}")
        for rank, m in enumerate(matches, 1):
            print(
                f"{rank:>4} {m.match_robot_id:>5} {m.match_frame_index:>6} {m.score:>8.4f} "
                f"{m.semantic_score:>8.4f} {m.n_matched:>7}"
            )
    if not result.complete:
        print(
            f"warning: no answer from shards {result.failed_shards}, verifiers {result.failed_verifiers}",
            file=sys.stderr,
        )
        return 3
    return 0


def _members(args: argparse.Namespace) -> int:
    with client_of(args) as swarm:
        members = swarm.members()
    if args.json:
        print(json.dumps([m.__dict__ for m in members]))
        return 0 if members else 3
    if not members:
        print(f"no live member in swarm {swarm.swarm!r}", file=sys.stderr)
        return 3
    print(f"{'service':<12} {'robot':>5} {'labels':>10} {'stored':>7} {'version':>8}  metrics")
    for m in members:
        # A shard's label groups (two replicas each by default, so several a shard).
        rng = ",".join(f"{lo}-{hi}" for lo, hi in m.label_ranges)
        print(f"{m.kind:<12} {m.robot:>5} {rng:>10} {m.stored_items:>7} {m.version:>8}  {m.metrics_url}")
    return 0


def _loop_closures(args: argparse.Namespace) -> int:
    with client_of(args) as swarm:
        if args.method == "dvpr":
            closures = swarm.place_loop_closures(args.robot, args.min_score)
        else:
            closures = swarm.loop_closures(args.robot, args.min_score)
    if args.json:
        print(
            json.dumps(
                [
                    {
                        "query_frame": c.query_frame_index,
                        "match_robot": c.match_robot_id,
                        "match_frame": c.match_frame_index,
                        "score": c.score,
                        "n_matched": c.n_matched,
                    }
                    for c in closures
                ]
            )
        )
        return 0
    print(f"robot {args.robot}: {len(closures)} loop closures")
    print(f"{'frame':>6} {'robot':>5} {'frame':>6} {'score':>8} {'objects':>7}")
    for c in closures:
        print(
            f"{c.query_frame_index:>6} {c.match_robot_id:>5} {c.match_frame_index:>6} {c.score:>8.4f} "
            f"{c.n_matched:>7}"
        )
    return 0
