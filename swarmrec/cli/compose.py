"""``swarmrec compose write|up|down``: a workload's swarm as containers on this host."""

from __future__ import annotations

import argparse
from pathlib import Path

from swarmrec.cli.common import Subparsers, add_dataset_flags, swarm_places_settings
from swarmrec.deployments import compose
from swarmrec.deployments.base import SwarmSpec
from swarmrec.experiments.landmarks.simulation import LandmarkSettings, swarm_spec
from swarmrec.experiments.places.keep import compose as compose_places
from swarmrec.services.registry import WORKLOADS

__all__ = ["add", "run"]


def add(sub: Subparsers) -> None:
    p = sub.add_parser(
        "compose",
        help="the swarm as containers: write a compose file for N robots, bring it up or down",
        description=(
            "write: generate compose.yml (router, each robot's services of the workload, Prometheus), "
            "prometheus.yml, swarm.json and the dataset under --out. "
            "up: write, then start every container and wait until all are healthy. "
            "down: stop and remove the containers, the network and (unless --keep-volumes) the volumes. "
            "Build the images first (make images). Then `swarmrec run --attach DIR` replays through a "
            "places swarm and `swarmrec landmarks --attach DIR` simulates the street through a landmarks one."
        ),
    )
    p.add_argument("action", choices=("write", "up", "down"))
    p.add_argument("--robots", type=int, default=4, help=f"robots, 1 .. {compose.MAX_ROBOTS} (default 4)")
    p.add_argument(
        "--workload",
        choices=sorted(WORKLOADS),
        default="places",
        help="; ".join(f"{w}: {', '.join(k)} per robot" for w, k in WORKLOADS.items()) + " (default places)",
    )
    add_dataset_flags(p)
    p.add_argument("--swarm", default="compose", help="swarm name (default compose)")
    p.add_argument("--project", default="swarmrec", help="compose project name (default swarmrec)")
    p.add_argument("--router-port", type=int, default=7447, help="router port on 127.0.0.1 (default 7447)")
    p.add_argument(
        "--prometheus-port", type=int, default=9090, help="Prometheus port on 127.0.0.1 (default 9090)"
    )
    p.add_argument(
        "--gateway-port", type=int, default=50051, help="gRPC gateway port on 127.0.0.1 (default 50051)"
    )
    p.add_argument(
        "--insecure",
        action="store_true",
        help="plaintext zenoh links and gRPC port (debugging); default: mutual TLS, a PKI in OUT/pki",
    )
    p.add_argument(
        "--free", action="store_true", help="compose for free replay (--pace fast or a rate), not lock-step"
    )
    p.add_argument("--timeout", type=float, default=5.0, help="seconds a service waits for a peer")
    p.add_argument("--out", type=Path, default=Path("runs/compose"), help="folder (default runs/compose)")
    p.add_argument("--keep-volumes", action="store_true", help="down: keep the named volumes")
    p.set_defaults(handler=run)


def write(args: argparse.Namespace, settings: compose.ComposeSettings) -> tuple[compose.SwarmFile, SwarmSpec]:
    """The compose files of the swarm the flags describe."""
    if args.workload == "landmarks":
        lm = LandmarkSettings(
            out=args.out / "report", robots=args.robots, swarm=args.swarm, request_timeout_s=args.timeout
        )
        record = {"swarm": lm.swarm, "robots": lm.robots, "request_timeout_s": lm.request_timeout_s}
        spec = swarm_spec(lm)
        return compose.write_compose(spec, settings, experiment=record), spec
    run = swarm_places_settings(args, args.out)
    info = compose_places(run, settings)
    return info, SwarmSpec(run.bus(), WORKLOADS["places"], workload="places")


def run(args: argparse.Namespace) -> int:
    if args.action == "down":
        info = compose.read_swarm_file(args.out)
        compose.down(info, volumes=not args.keep_volumes)
        print(f"compose project {info.project}: containers and network removed", end="")
        print("" if args.keep_volumes else ", volumes removed")
        return 0
    settings = compose.ComposeSettings(
        project=args.project,
        out=args.out,
        router_port=args.router_port,
        prometheus_port=args.prometheus_port,
        gateway_port=args.gateway_port,
        security="insecure" if args.insecure else "mtls",
    )
    info, spec = write(args, settings)
    containers = len(spec.kinds) * spec.robots + 2 + len(spec.swarm_kinds)
    print(f"wrote {info.compose_file} ({spec.robots} robots, {args.workload}, {containers} containers)")
    if args.action == "up":
        print("starting containers; waiting until every one is healthy ...", flush=True)
        seconds = compose.up(info)
        print(
            f"swarm up in {seconds:.1f} s: gateway {info.gateway_address}, router {info.router_endpoint}, "
            f"Prometheus {info.prometheus_url}"
        )
        if args.workload == "landmarks":
            print(f"simulate the street through it: swarmrec landmarks --attach {args.out}")
        else:
            print(f"replay through it: swarmrec run --attach {args.out}")
    return 0
