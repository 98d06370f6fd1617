"""``swarmrec place-query``, ``clusters``, ``slam-team``, ``slam-estimate``, ``slam-map`` and
``landmark-round``: ask a running swarm's full-image, SLAM and landmark services, over zenoh
or through its gRPC gateway, with the connection flags of ``swarmrec query``
(:mod:`swarmrec.cli.clients`). ``--json`` prints the answer's protobuf message as JSON (the
schema's field names), as grpcurl would."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

# protobuf ships no type stubs (see swarmrec/runtime/rpc.py for the two codes).
from google.protobuf import json_format  # type: ignore[import-untyped, unused-ignore]
from google.protobuf.message import Message  # type: ignore[import-untyped, unused-ignore]

from swarmrec.cli.clients import add_connection_flags, client_of
from swarmrec.cli.common import Subparsers
from swarmrec.errors import ConfigError
from swarmrec.wire import messages as pb

__all__ = ["add"]


def add(sub: Subparsers) -> None:
    p = sub.add_parser(
        "place-query", help="full-image: where a descriptor or an image was seen (nothing is stored)"
    )
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument(
        "--descriptor", type=Path, help="the unit descriptor: a .npy file, or whitespace-separated numbers"
    )
    what.add_argument("--image", type=Path, help="a PNG or JPEG, described with the swarm's descriptor model")
    p.add_argument("--exclude-robot", type=int, help="leave this robot's frames out of the answer")
    add_connection_flags(p)
    p.set_defaults(handler=_place_query)
    p = sub.add_parser("clusters", help="full-image: the place owners' cluster table and its version")
    add_connection_flags(p)
    p.set_defaults(handler=_clusters)
    p = sub.add_parser("slam-team", help="SLAM: every robot's solve (state, stage, iteration)")
    add_connection_flags(p)
    p.set_defaults(handler=_slam_team)
    p = sub.add_parser("slam-estimate", help="SLAM: one robot's estimate (--watch: each step until it ends)")
    p.add_argument("robot", type=int, help="robot id")
    p.add_argument("--watch", action="store_true", help="print each new estimate until the solve ends")
    add_connection_flags(p)
    p.set_defaults(handler=_slam_estimate)
    p = sub.add_parser("slam-map", help="SLAM: the merged map of the newest solve")
    add_connection_flags(p)
    p.set_defaults(handler=_slam_map)
    p = sub.add_parser("landmark-round", help="landmarks: every robot's fused posterior of one round")
    p.add_argument("round", type=int, nargs="?", help="the round (default: each robot's latest)")
    add_connection_flags(p)
    p.set_defaults(handler=_landmark_round)


def _as_json(msg: Message) -> str:
    return json.dumps(json_format.MessageToDict(msg, preserving_proto_field_name=True))


def _read_descriptor(path: Path) -> np.ndarray:
    try:
        if path.suffix == ".npy":
            return np.asarray(np.load(path, allow_pickle=False), np.float32).ravel()
        return np.asarray(path.read_text(encoding="utf-8").split(), np.float32)
    except (OSError, ValueError) as e:
        raise ConfigError(f"cannot read a descriptor from {path}: {e}") from None


def _place_query(args: argparse.Namespace) -> int:
    image: bytes | None = None
    descriptor = None
    if args.image is not None:
        try:
            image = args.image.read_bytes()
        except OSError as e:
            raise ConfigError(f"cannot read {args.image}: {e.strerror}") from None
    else:
        descriptor = _read_descriptor(args.descriptor)
    with client_of(args) as swarm:
        reply = swarm.place_query(descriptor, image=image, exclude_robot=args.exclude_robot)
    if args.json:
        print(_as_json(reply))
        return 0
    m = reply.match
    print(f"cluster {reply.cluster} (owner robot {reply.owner_robot_id}, table v{reply.assignment_version})")
    if not m.found:
        print("no stored frame answers")
        return 3
    print(f"nearest: robot {m.robot_id} frame {m.frame_index}, squared distance {m.distance:.4f}")
    return 0


def _clusters(args: argparse.Namespace) -> int:
    with client_of(args) as swarm:
        table = swarm.cluster_table()
    if args.json:
        print(_as_json(table))
        return 0
    agreed = "every owner agrees" if table.agreed else "THE OWNERS DISAGREE"
    print(f"cluster table v{table.version}, centres {table.centres_sha256[:12]}: {agreed}")
    print(f"{'robot':>5} {'version':>7}  clusters")
    for owner in table.owners:
        print(f"{owner.robot_id:>5} {owner.version:>7}  {' '.join(map(str, owner.owned_clusters))}")
    return 0 if table.agreed else 3


def _state(state: int) -> str:
    return str(pb.SlamState.Name(state)).removeprefix("SLAM_STATE_").lower()


def _slam_team(args: argparse.Namespace) -> int:
    with client_of(args) as swarm:
        team = swarm.slam_team()
    if args.json:
        print(json.dumps([json_format.MessageToDict(s, preserving_proto_field_name=True) for s in team]))
        return 0
    print(f"{'robot':>5} {'solve':>5} {'state':<10} {'lin':>3} {'iter':>5} {'converged':>9}")
    for s in team:
        print(
            f"{s.robot_id:>5} {s.solve_id:>5} {_state(s.state):<10} {s.linearisation:>3} {s.iteration:>5} "
            f"{s.converged!s:>9}"
        )
    return 0


def _slam_estimate(args: argparse.Namespace) -> int:
    with client_of(args) as swarm:
        estimates = (
            swarm.watch_slam_estimate(args.robot) if args.watch else iter([swarm.slam_estimate(args.robot)])
        )
        for e in estimates:
            if args.json:
                print(_as_json(e), flush=True)
            else:
                print(
                    f"robot {e.robot_id} solve {e.solve_id} {_state(e.state)} at linearisation "
                    f"{e.linearisation} iteration {e.iteration}: {len(e.keys)} vertices",
                    flush=True,
                )
    return 0


def _slam_map(args: argparse.Namespace) -> int:
    with client_of(args) as swarm:
        merged = swarm.slam_map()
    if args.json:
        print(_as_json(merged))
        return 0
    print(
        f"solve {merged.solve_id}: {len(merged.keys)} vertices from robots {list(merged.robot_ids)}"
        + (f", robots {list(merged.missing_robot_ids)} on another solve" if merged.missing_robot_ids else "")
        + ("" if merged.done else " (not every robot done)")
    )
    return 0 if merged.done else 3


def _landmark_round(args: argparse.Namespace) -> int:
    with client_of(args) as swarm:
        reply = swarm.landmark_round(args.round)
    if args.json:
        print(_as_json(reply))
        return 0
    print(f"{'robot':>5} {'round':>5} {'decision':>8} {'heard':>5} {'all':>5}")
    for p in reply.posteriors:
        print(f"{p.robot_id:>5} {p.round_id:>5} {p.decision:>8} {p.incorporated:>5} {p.heard_all!s:>5}")
    return 0 if reply.posteriors else 3
