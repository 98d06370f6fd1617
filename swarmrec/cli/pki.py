"""``swarmrec pki init``: the swarm's CA, one certificate per identity and the router's
access control (docs/security.md)."""

from __future__ import annotations

import argparse
from pathlib import Path

from swarmrec.cli.common import Subparsers
from swarmrec.runtime.hosting import host_ranges, robots_per_process
from swarmrec.security.pki import DEFAULT_ROUTER_NAMES, PkiSettings, main

__all__ = ["add", "run"]


def _names(text: str) -> tuple[str, ...]:
    return tuple(n.strip() for n in text.split(",") if n.strip())


def _hosts(hosting: str, robots: int) -> tuple[tuple[int, int], ...]:
    """The host certificates ``hosting`` needs: its processes' ranges and each robot alone
    (a robot restarted by itself)."""
    if hosting == "service":
        robots_per_process(hosting)
        return ()
    return tuple(sorted({*host_ranges(hosting, robots), *((r, r) for r in range(robots))}))


def add(sub: Subparsers) -> None:
    p = sub.add_parser(
        "pki",
        help="create the swarm's PKI: CA, a certificate per robot service, router, gateway, clients",
        description=(
            "init: create what is missing of the swarm's PKI in --out (ca.pem, ca.key, <cn>.pem/.key per "
            "identity, acl.json for the router); an existing file is kept, one that differs stops it "
            "unless --replace. Keep ca.key offline once the certificates are issued."
        ),
    )
    p.add_argument("action", choices=("init",))
    p.add_argument("--swarm", required=True, help="swarm name (in every common name)")
    p.add_argument("--robots", type=int, required=True, help="robots in the swarm")
    p.add_argument("--out", type=Path, required=True, help="the PKI folder (created 0700)")
    p.add_argument("--clients", default="cli", help="read-only client names, comma-separated (default cli)")
    p.add_argument("--operators", default="job", help="operator names (may drive replays; default job)")
    p.add_argument("--gateways", default="gateway", help="gRPC gateway identities (default gateway)")
    p.add_argument(
        "--router-names",
        default=",".join(DEFAULT_ROUTER_NAMES),
        help="names and IPs the router is dialled at (default localhost,127.0.0.1,::1; "
        "add 'router' for compose)",
    )
    p.add_argument(
        "--gateway-names",
        default=",".join((*DEFAULT_ROUTER_NAMES, "gateway")),
        help="names and IPs the gateway's gRPC port is dialled at",
    )
    p.add_argument(
        "--hosting",
        default="service",
        help="service (default), robot or robots:K: also issue the host certificates of processes "
        "that run every service of one robot (r<i>.host.<swarm>) or of K consecutive robots "
        "(r<first>-<last>.host.<swarm>)",
    )
    p.add_argument("--key-type", choices=("p256", "ed25519"), default="p256")
    p.add_argument("--days", type=int, default=365, help="validity of the end certificates (default 365)")
    p.add_argument(
        "--renew-days", type=int, default=0, help="treat certificates expiring within N days as expired"
    )
    p.add_argument("--replace", action="store_true", help="reissue what does not match instead of stopping")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    settings = PkiSettings(
        swarm=args.swarm,
        robots=args.robots,
        out=args.out,
        clients=_names(args.clients),
        operators=_names(args.operators),
        gateways=_names(args.gateways),
        router_names=_names(args.router_names),
        gateway_names=_names(args.gateway_names),
        hosts=_hosts(args.hosting, args.robots),
        key_type=args.key_type,
        cert_days=args.days,
        renew_days=args.renew_days,
        replace=args.replace,
    )
    return main(settings)
