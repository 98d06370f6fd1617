"""``swarmrec query``, ``members`` and ``loop-closures``: ask a running swarm, from any host
that reaches its router (``--connect tls/host:7447``) or its gRPC gateway
(``--connect grpc://host:50051``), as the identity ``--identity`` of the PKI in ``--pki-dir``."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from swarmrec.cli.common import Subparsers
from swarmrec.client import GRPC_SCHEME, SwarmClient, connect
from swarmrec.core.presets import PRESETS
from swarmrec.datasets.constellations import parse_constellation
from swarmrec.datasets.labels import LabelMap, label_names
from swarmrec.errors import ConfigError
from swarmrec.runtime.tls import TlsFiles

__all__ = ["add", "add_connection_flags", "client_of"]


def add_connection_flags(p: argparse.ArgumentParser, *, connect: str | None = "tls/127.0.0.1:7447") -> None:
    """How a command reaches a running swarm: --connect, --swarm, --pki-dir, --identity, --timeout,
    and --json (``connect``: the default router endpoint; None: no default)."""
    default = f" (default {connect})" if connect else ""
    p.add_argument(
        "--connect",
        default=connect,
        help=f"router endpoint(s), comma-separated{default}, or the gRPC "
        "gateway as grpc://host:port; a tcp/ endpoint is the insecure mode",
    )
    p.add_argument("--swarm", default="local", help="swarm name (default local)")
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
    common(p)
    p.set_defaults(handler=_loop_closures)


def client_of(args: argparse.Namespace) -> SwarmClient:
    """The client the flags of :func:`add_connection_flags` describe."""
    plaintext = args.connect.startswith("tcp/") or (
        args.connect.startswith(GRPC_SCHEME) and args.pki_dir is None
    )
    tls = None
    if args.pki_dir is not None:
        tls = TlsFiles.in_dir(Path(args.pki_dir), args.identity or f"client.cli.{args.swarm}")
    elif not plaintext:
        raise ConfigError(
            f"{args.connect} is mutual TLS: give the swarm's PKI folder (--pki-dir or SWARMREC_PKI_DIR)"
        )
    return connect(
        args.connect, args.swarm, timeout_s=args.timeout, tls=tls, insecure_reason="--connect tcp/..."
    )


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
        print(f"no live member in swarm {args.swarm!r}", file=sys.stderr)
        return 3
    print(f"{'service':<12} {'robot':>5} {'labels':>10} {'stored':>7} {'version':>8}  metrics")
    for m in members:
        # A shard's label groups (two replicas each by default, so several a shard).
        rng = ",".join(f"{lo}-{hi}" for lo, hi in m.label_ranges)
        print(f"{m.kind:<12} {m.robot:>5} {rng:>10} {m.stored_items:>7} {m.version:>8}  {m.metrics_url}")
    return 0


def _loop_closures(args: argparse.Namespace) -> int:
    with client_of(args) as swarm:
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
