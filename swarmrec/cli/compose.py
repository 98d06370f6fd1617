"""``swarmrec compose write|up|down``: a workload's swarm as containers on this host."""

from __future__ import annotations

import argparse
from pathlib import Path

from swarmrec.cli.common import Subparsers, add_dataset_flags, swarm_places_settings
from swarmrec.deployments import compose
from swarmrec.deployments.base import SwarmSpec
from swarmrec.experiments.landmarks.simulation import LandmarkSettings, swarm_spec
from swarmrec.experiments.places.keep import compose as compose_places
from swarmrec.experiments.places.settings import PixelSettings
from swarmrec.experiments.slam.keep import compose as compose_slam
from swarmrec.experiments.slam.settings import LiveSlamSettings
from swarmrec.experiments.vpr.keep import compose as compose_dvpr
from swarmrec.experiments.vpr.settings import DvprSettings, VprRunSettings
from swarmrec.services.registry import WORKLOADS
from swarmrec.slam.scenarios import WORLDS

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
            "places or dvpr swarm, `swarmrec landmarks --attach DIR` simulates the street through a "
            "landmarks one and `swarmrec slam run --attach DIR` solves through a slam team."
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
    _add_dvpr_flags(p)
    slam = p.add_argument_group("slam workload", "one slam service per robot (docs/slam.md)")
    slam.add_argument(
        "--slam-folder",
        type=Path,
        metavar="DIR",
        help="robot folder (0.g2o, 1.g2o, ...); default: a simulated world (--world, --robots, --seed)",
    )
    slam.add_argument("--world", choices=WORLDS, default="chairs", help="simulated world (default chairs)")
    slam.add_argument(
        "--peer-timeout-s", type=float, default=10.0, help="a robot silent this long is declared gone"
    )
    p.set_defaults(handler=run)


def _add_dvpr_flags(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("dvpr workload", 'full-image place recognition (docs/vpr.md, "The live swarm")')
    g.add_argument(
        "--from-pixels",
        action="store_true",
        help="render the synthetic world (--seed, --frames) as RGB-D frames into OUT/dataset",
    )
    g.add_argument("--rgbd", type=Path, metavar="DIR", help="a TUM-format RGB-D folder instead")
    d = DvprSettings()
    g.add_argument(
        "--clusters-per-robot", type=int, default=d.clusters_per_robot, help="clusters each robot owns"
    )
    g.add_argument(
        "--assignment-seed", type=int, default=d.assignment_seed, help="seed of the clusters' assignment"
    )
    g.add_argument(
        "--assignment", type=Path, metavar="JSON", help="an assignment table (swarmrec.vpr.assignment/1)"
    )
    g.add_argument(
        "--rebalance-every",
        type=int,
        default=d.rebalance_every,
        metavar="STEPS",
        help="`swarmrec run --attach` re-balances the cluster owners live after every STEPS lock-step "
        "steps (default 0: never)",
    )
    g.add_argument(
        "--centres",
        type=Path,
        metavar="NPZ",
        help="k-means centres (default: the shipped ones, or trained into OUT/centres.npz)",
    )
    g.add_argument(
        "--vpr-wire-code",
        choices=("int8", "float32"),
        default=d.wire_code,
        help="how a query carries its descriptor (default int8)",
    )


def write(args: argparse.Namespace, settings: compose.ComposeSettings) -> tuple[compose.SwarmFile, SwarmSpec]:
    """The compose files of the swarm the flags describe."""
    if args.workload == "landmarks":
        lm = LandmarkSettings(
            out=args.out / "report", robots=args.robots, swarm=args.swarm, request_timeout_s=args.timeout
        )
        record = {"swarm": lm.swarm, "robots": lm.robots, "request_timeout_s": lm.request_timeout_s}
        spec = swarm_spec(lm)
        return compose.write_compose(spec, settings, experiment=record), spec
    if args.workload == "slam":
        team = LiveSlamSettings(
            out=args.out,
            folder=args.slam_folder,
            world=args.world,
            robots=args.robots,
            seed=args.seed,
            swarm=args.swarm,
            request_timeout_s=args.timeout,
            peer_timeout_s=args.peer_timeout_s,
        )
        info = compose_slam(team, settings)
        return info, SwarmSpec(compose.bus_for(info.robots, info.swarm), WORKLOADS["slam"], workload="slam")
    if args.workload == "dvpr":
        pixels = PixelSettings(from_pixels=args.from_pixels, rgbd=args.rgbd)
        vpr = VprRunSettings(
            run=swarm_places_settings(args, args.out, pixels=pixels),
            dvpr=DvprSettings(
                clusters_per_robot=args.clusters_per_robot,
                assignment_seed=args.assignment_seed,
                wire_code=args.vpr_wire_code,
                centres=args.centres,
                assignment=args.assignment,
                rebalance_every=args.rebalance_every,
            ),
        )
        info = compose_dvpr(vpr, settings, say=print)
        return info, SwarmSpec(vpr.run.bus(), WORKLOADS["dvpr"], workload="dvpr")
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
        elif args.workload == "slam":
            print(f"solve through it: swarmrec slam run --attach {args.out}")
        else:
            print(f"replay through it: swarmrec run --attach {args.out}")
    return 0
