"""``swarmrec run``: the main job, place recognition through a swarm: local processes,
a namespace of a Kubernetes cluster (``--deployment k8s``), or a swarm left running by
``swarmrec compose up`` or ``swarmrec k8s up`` (``--attach``)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from swarmrec.cli.common import (
    Subparsers,
    add_dataset_flags,
    add_index_flags,
    add_local_swarm_flags,
    dataset_source,
    local_settings,
)
from swarmrec.cli.k8s import add_cluster_flags, kubectl_of
from swarmrec.cli.vpr import add_method_flags, print_dvpr, run_method
from swarmrec.deployments.attach import attach
from swarmrec.deployments.base import AttachFile, Deployment
from swarmrec.deployments.kubernetes import DEFAULT_OVERLAY, KubernetesDeployment, KubernetesSettings
from swarmrec.deployments.local import LocalDeployment
from swarmrec.deployments.mesh import MeshReport
from swarmrec.errors import ConfigError
from swarmrec.experiments.places import PixelSettings, PlacesSettings, PlacesSummary, main
from swarmrec.experiments.places.report import DetectorFigures, FunnelStats, IndexSummary
from swarmrec.experiments.vpr import DvprSummary
from swarmrec.experiments.vpr import main as vpr_main
from swarmrec.experiments.vpr.keep import from_record as vpr_from_record
from swarmrec.services.settings import IndexSettings

__all__ = ["add", "print_summary", "run"]

DEFAULT_OUT = Path("runs/swarm")


def add(sub: Subparsers) -> None:
    p = sub.add_parser(
        "run",
        help="the main job: a local swarm of N robots (real processes over a real zenoh router) "
        "replays a dataset and reports",
        description=(
            "Start a zenoh router and every robot's detector, descriptor, index-shard and verifier as "
            "separate processes on this machine, replay the dataset split into N sub-trajectories, "
            "and write the report: loop closures, precision-recall against ground truth, bytes per "
            "query and shard load scraped from the services' Prometheus metrics, query latency."
        ),
    )
    add_dataset_flags(p)
    p.add_argument("--robots", type=int, default=10, help="robots in the swarm (default 10)")
    p.add_argument(
        "--pace",
        default="lockstep",
        help="lockstep (default; identical to the offline evaluation), fast, or frames per second",
    )
    p.add_argument("--swarm", default="local", help="swarm name (the key expressions' swarm segment)")
    p.add_argument(
        "--timeout", type=float, default=5.0, help="seconds a service waits for a peer (default 5)"
    )
    p.add_argument("--out", type=Path, default=DEFAULT_OUT, help="output folder")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
    p.add_argument(
        "--no-offline-check",
        action="store_true",
        help="skip comparing the pair scores with the offline evaluation",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    add_local_swarm_flags(p)
    links = p.add_argument_group(
        "topology and emulated links",
        "star: every robot reaches one router through a Toxiproxy proxy of its own (docs/links.md); "
        "mesh: a router per robot, linked to the robots it hears by a proxy per link (docs/mesh.md); "
        "local runs only",
    )
    links.add_argument(
        "--topology",
        choices=("star", "mesh"),
        default="star",
        help="star: one router for the swarm (default); mesh: a router per robot, each robot's services "
        "on their own, routers linked only to the robots they hear, traffic relayed over several hops",
    )
    links.add_argument(
        "--radio-range",
        type=float,
        metavar="M",
        help="mesh: robots hear each other within M metres of their own positions at each step "
        "(default: every robot hears every other)",
    )
    links.add_argument("--link-rate", type=float, metavar="KBPS", help="each link's bandwidth, kilobytes/s")
    links.add_argument("--link-latency", type=float, metavar="MS", help="each link's latency, each way, ms")
    links.add_argument(
        "--link-schedule",
        type=Path,
        metavar="CSV",
        help="when robots are out of range: start,end,robot rows (mesh: also start,end,robot_a,robot_b rows)",
    )
    links.add_argument(
        "--schedule-unit",
        choices=("step", "s"),
        default="step",
        help="the schedule's times: lock-step steps or seconds",
    )
    p.add_argument(
        "--wire-positions",
        choices=("mm", "exact"),
        default="mm",
        help="object positions on the wire: mm (about 2 bytes a coordinate, default) or exact doubles "
        "(8 bytes; the swarm's pair scores are then the published scripts' to the last bit)",
    )
    index = p.add_argument_group("elastic index", "label groups on index shards (docs/elastic-index.md)")
    add_index_flags(index)
    pixels = p.add_argument_group(
        "from pixels",
        "detectors find objects in RGB-D frames with an ONNX model instead of replaying constellations "
        "(docs/detector.md)",
    )
    pixels.add_argument(
        "--from-pixels",
        action="store_true",
        help="render the synthetic world (--seed, --frames) as RGB-D frames into OUT/rgbd and detect in them",
    )
    pixels.add_argument(
        "--rgbd",
        type=Path,
        metavar="DIR",
        help="a TUM-format RGB-D folder (rgb.txt, depth.txt, images; groundtruth.txt for precision-recall)",
    )
    pixels.add_argument(
        "--model",
        default="",
        metavar="ONNX",
        help="a YOLO-style ONNX export (v5 or v8 output, one class per label; default: the project's model)",
    )
    pixels.add_argument(
        "--conf-threshold",
        type=float,
        help="keep boxes at least this confident (default: the project's model's recommended one, else 0.25)",
    )
    pixels.add_argument(
        "--detector-threads", type=int, default=1, help="onnxruntime threads per detector (default 1)"
    )
    pixels.add_argument(
        "--camera",
        type=_camera,
        metavar="FX,FY,CX,CY",
        help="depth camera intrinsics in pixels (default: a render's own, else TUM freiburg3's)",
    )
    pixels.add_argument("--depth-scale", type=float, help="depth units per metre (default 5000, TUM's)")
    add_method_flags(p)
    p.add_argument(
        "--attach",
        type=Path,
        metavar="DIR",
        help="start nothing: replay through the running swarm that `swarmrec compose up --out DIR` or "
        "`swarmrec k8s up --out DIR` started (its dataset, robots and preset; --pace, --out, --no-plots "
        "still apply; a swarm composed with --workload dvpr runs --method dvpr)",
    )
    p.add_argument(
        "--deployment",
        choices=("local", "k8s"),
        default="local",
        help="where the swarm runs: local processes (default), or k8s: the k8s/ manifests in a new "
        "namespace of a Kubernetes cluster, with mutual TLS from Secrets made for the run "
        "(docs/kubernetes.md); removed after the run unless --keep",
    )
    k8s = p.add_argument_group("kubernetes", "with --deployment k8s")
    k8s.add_argument("--namespace", default="swarmrec-run", help="the run's namespace (default swarmrec-run)")
    k8s.add_argument(
        "--keep", action="store_true", help="leave the swarm running; OUT/k8s/swarm.json attaches to it"
    )
    add_cluster_flags(k8s)
    p.set_defaults(handler=run)


def _run_attached_dvpr(
    method: str, deployment: Deployment, info: AttachFile, out: Path, common: dict[str, Any]
) -> int:
    """``--attach`` a swarm composed for the full-image method: its run, through it."""
    if method == "both":
        raise ConfigError("--method both runs each method on a swarm of its own: attach one at a time")
    if info.workload != "dvpr":
        raise ConfigError(
            f"--method {method} needs a dvpr swarm (swarmrec compose up --workload dvpr); "
            f"the swarm in {deployment.description} runs {info.workload}"
        )
    settings = vpr_from_record(info.experiment, out=out, **common)
    summary = vpr_main(settings, lambda _folder: deployment, say=print)
    assert isinstance(summary, DvprSummary)  # one method: dvpr
    print_dvpr(summary, settings.out)
    return 0


def _local_links(args: argparse.Namespace) -> bool:
    """Whether the flags ask for emulated links or the mesh: only a local run starts them."""
    return bool(
        args.link_rate
        or args.link_latency
        or args.link_schedule
        or args.topology != "star"
        or args.radio_range
    )


def _kubernetes(args: argparse.Namespace, out: Path) -> KubernetesDeployment:
    """``--deployment k8s``: the run's namespace, its overlay, PKI and report under ``out/k8s``."""
    if _local_links(args):
        raise ConfigError(
            "emulated links and the mesh topology are set up by the local deployment (not --deployment k8s)"
        )
    if args.insecure or args.hosting != "service":
        raise ConfigError(
            "a Kubernetes swarm runs one service per pod under mutual TLS: drop --insecure and --hosting"
        )
    if args.data_plane != "compiled":
        raise ConfigError(
            "a Kubernetes swarm runs what its images and overlay say: --data-plane applies to "
            "local processes (set SWARMREC_DATA_PLANE in the overlay instead)"
        )
    return KubernetesDeployment(
        KubernetesSettings(
            namespace=args.namespace,
            out=out / "k8s",
            overlay=args.overlay or DEFAULT_OVERLAY,
            kubectl=kubectl_of(args),
            max_robots=args.max_robots,
            keep=args.keep,
        )
    )


def _camera(text: str) -> tuple[float, float, float, float]:
    try:
        fx, fy, cx, cy = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected FX,FY,CX,CY such as 535.4,539.2,320.1,247.6, got {text!r}"
        ) from None
    return fx, fy, cx, cy


def run(args: argparse.Namespace) -> int:
    common = {
        "pace": args.pace,
        "plots": not args.no_plots,
        "progress": not args.quiet,
        "check_offline": not args.no_offline_check,
    }
    if args.attach is not None:
        if _local_links(args):
            raise ConfigError(
                "emulated links and the mesh topology are set up by a local deployment the run starts itself"
            )
        attached, info = attach(args.attach)
        out = args.out if args.out != DEFAULT_OUT else args.attach / "report"
        if info.workload == "dvpr" or args.method != "constellations":
            return _run_attached_dvpr(args.method, attached, info, out, common)
        settings = PlacesSettings.from_record(info.experiment, out=out, **common)
        summary = main(settings, attached)
        print_summary(summary, settings.out)
        return 0
    settings = PlacesSettings(
        source=dataset_source(args),
        robots=args.robots,
        preset=args.preset,
        swarm=args.swarm,
        request_timeout_s=args.timeout,
        out=args.out,
        wire_positions=args.wire_positions,
        data_plane=args.data_plane,
        index=IndexSettings(replicas=args.replicas, rebalance_target=args.rebalance_target),
        pixels=PixelSettings(
            from_pixels=args.from_pixels,
            rgbd=args.rgbd,
            model=args.model,
            conf_threshold=args.conf_threshold,
            detector_threads=args.detector_threads,
            camera=args.camera,
            depth_scale=args.depth_scale,
        ),
        **common,
    )
    if args.method != "constellations":
        if args.deployment != "k8s":
            return run_method(args, settings, local_settings(args), print_summary)
        if args.keep:
            raise ConfigError("--keep leaves a places swarm running; --method dvpr and both remove theirs")
        # Each method's swarm in the run's namespace, one after the other.
        return run_method(
            args, settings, local_settings(args), print_summary, lambda folder: _kubernetes(args, folder)
        )
    deployment: Deployment
    k8s: KubernetesDeployment | None = None
    if args.deployment == "k8s":
        k8s = _kubernetes(args, args.out)
        deployment = k8s
    else:
        # (Links, hosting and security are the local deployment's; a bad schedule is refused here.)
        deployment = LocalDeployment.for_run(settings.out, local_settings(args))
    summary = main(settings, deployment)
    print_summary(summary, settings.out)
    if k8s is not None and args.keep:
        path = k8s.write_attach_file(settings.record())
        print(f"  the swarm runs on in namespace {args.namespace}: swarmrec run --attach {path.parent}")
    return 0


def print_mesh(m: MeshReport) -> None:
    """A mesh run's lines: its routers and links, the radio graph over time, the link bytes."""
    radio = (
        "every robot hears every other" if m.radio_range_m is None else f"radio range {m.radio_range_m:g} m"
    )
    waits = f"; followed in {max(m.converge_s):.2f} s at most" if m.converge_s else ""
    start = m.start_s
    print(
        f"  mesh: a router per robot ({m.routers}), {len(m.link_bytes)} links used, {radio}, up to "
        f"{m.max_hops} hops; {len(m.events)} link changes{waits}"
    )
    if start:
        print(
            f"    start: links {start.get('links_s', 0):.1f} s, routers {start.get('routers_s', 0):.1f} s, "
            f"first convergence {start.get('converge_s', 0):.1f} s"
        )
    for span in m.components[:6]:
        parts = span["components"]
        assert isinstance(parts, list)
        shape = "connected" if len(parts) == 1 else f"{len(parts)} components {parts}"
        print(f"    steps {span['start']}-{int(str(span['end'])) - 1}: {span['links']} links, {shape}")
    if len(m.components) > 6:
        print(f"    ... {len(m.components) - 6} more in summary.json")
    if m.held_placements:
        versions = ", ".join(f"version {h['version']} from step {h['step']}" for h in m.held_placements)
        agree = (
            "every part on it"
            if not m.split_disagreements
            else f"PARTS DISAGREED at {len(m.split_disagreements)} steps (summary.json)"
        )
        print(f"    while split: placement held ({versions}), {agree}")
    if m.deliver_s:
        print(f"    pending stores delivered after each link change in {max(m.deliver_s):.2f} s at most")
    busiest = max(m.link_bytes.items(), key=lambda kv: kv[1]["a_to_b"] + kv[1]["b_to_a"], default=None)
    most = "" if busiest is None else f" (busiest link {busiest[0]}: {sum(busiest[1].values()):.0f} B)"
    print(f"    bytes on the links between routers, measured: {m.link_bytes_per_query:.0f} B per query{most}")


def print_summary(s: PlacesSummary, out: Path) -> None:
    q, b, load, sw = s.queries, s.bytes, s.shard_load, s.swarm
    where = f"{sw.processes} processes" if sw.processes else sw.deployment
    frames = f"{s.dataset.frames} frames, {where}"
    print(f"swarm of {sw.robots} robots on {s.dataset.name} ({frames}), pace {sw.pace}")
    auc = f"AUC {s.auc:.4f}" if s.auc is not None else "AUC n/a (no ground truth)"
    if s.detector is not None:
        _print_detector(s.detector)
    print(f"  {q.queried} queries, {s.loop_closures.count} loop closures, {auc}")
    if s.funnel is not None:
        _print_funnel(s.funnel)
    lat = q.latency_ms
    if lat:
        print(f"  query latency p50 {lat['p50']:.2f} ms, p99 {lat['p99']:.2f} ms")
    print(f"  measured bytes between robots: {b.per_query:.1f} B per query ({b.per_frame:.1f} B per frame)")
    if b.replication_per_query or b.index_control_per_query:
        print(
            f"  and per query: {b.replication_per_query:.1f} B storing replicas, "
            f"{b.index_control_per_query:.1f} B index control; {b.all_per_query:.1f} B in all"
        )
    print(f"  partial queries per shard {load.partial_queries}; busiest / mean = {load.balance_ratio:.2f}")
    if s.index is not None:
        ix = s.index
        state = "settled" if ix.settled else f"NOT settled, {ix.pending_stores} stores pending"
        weight = "" if ix.store_weight is None else f"; a store costs {ix.store_weight:.2f} of a query (CPU)"
        print(
            f"  index: {ix.replicas} replicas a group, placement version {ix.version} "
            f"({ix.placements_published:.0f} published, {ix.handoff_records:.0f} descriptors handed off), "
            f"{state}{weight}"
        )
        _print_index_balance(ix)
    if s.positions_effect is not None:
        pe = s.positions_effect
        print(
            f"  positions in mm on the wire: offline AUC {pe.auc_offline_mm_positions:.4f} "
            f"(exact positions {pe.auc_offline_exact_positions:.4f}, "
            f"{pe.pair_scores_changed} pair scores changed)"
        )
    if s.links is not None:
        lk = s.links
        print(
            f"  links: {lk.rate_kbps or 'unlimited'} kB/s, {lk.latency_ms or 0} ms; {len(lk.events)} changes"
        )
        for when, event in lk.events[:10]:
            at = f"step {when:g}" if lk.schedule_unit == "step" else f"{when:g} s"
            print(f"    at {at}: {event}")
        if len(lk.events) > 10:
            print(f"    ... {len(lk.events) - 10} more in summary.json")
    if s.mesh is not None:
        print_mesh(s.mesh)
    if s.offline_check is not None:
        oc = s.offline_check
        verdict = "identical" if oc.identical else f"DIFFERENT ({oc})"
        if oc.split_steps:
            print(
                f"  pair scores vs the offline simulation of the same splits ({oc.split_steps} steps split; "
                f"{oc.unreached_group_queries} partial queries found no owner in reach, "
                f"{oc.unreachable_verifications} verifications were out of reach): {verdict}"
            )
        else:
            print(f"  pair scores vs offline decentralized evaluation: {verdict}")
    elif s.offline_not_compared:
        print(f"  pair scores vs offline decentralized evaluation: not compared ({s.offline_not_compared})")
    if q.missing_slots:
        by_robot = ", ".join(
            f"robot {r}: {n}" for r, n in sorted(q.missing_by_robot.items(), key=lambda x: int(x[0]))
        )
        print(f"  missing answers: {q.missing_slots} ({by_robot})")
    if q.late_frames or q.pending_frames:
        print(
            f"  frames delivered late from the detectors' outboxes: {q.late_frames}"
            + (f"; still waiting: {q.pending_frames}" if q.pending_frames else "")
        )
    if s.scrape_failed:
        print(f"  metrics not read from: {', '.join(s.scrape_failed)}")
    t = s.timings
    start = f"start {t['start_s']:.1f} s, " if "start_s" in t else ""
    print(f"  time: {start}replay {t['replay_s']:.1f} s, total {t['total_s']:.1f} s")
    print(f"  written to {out}/ (summary.json, pairs.csv, loop_closures.csv, funnel.csv, *.png)")


def _print_index_balance(ix: IndexSummary) -> None:
    """The hottest label groups with their owners, and why each placement came."""
    if ix.group_queries and ix.owners:
        hottest = sorted(range(len(ix.group_queries)), key=lambda g: -ix.group_queries[g])[:4]
        groups = ", ".join(f"{g}: {ix.group_queries[g]} on {ix.owners[g]}" for g in hottest)
        print(f"  hottest label groups (partial queries on owners): {groups}")
    for h in ix.history:
        why = h["reason"].replace("_", " ")
        plan = h.get("plan")
        if plan:
            busiest = f"{plan['busiest_before']:.0f} -> {plan['busiest_after']:.0f}"
            why += f" (busiest {busiest}, mean {plan['mean']:.0f})"
        moved = ", ".join(
            f"{g}" + (f" +{c['gained']}" if c["gained"] else "") + (f" -{c['lost']}" if c["lost"] else "")
            for g, c in h["groups"].items()
        )
        print(f"  placement {h['version']}: {why}" + (f"; groups {moved}" if moved else ""))


def _print_funnel(f: FunnelStats) -> None:
    stops = ", ".join(f"{reason.replace('_', ' ')} {n}" for reason, n in f.by_reason.items())
    print(
        f"  funnel: {f.candidates_returned} candidates returned ({f.distinct_candidates} distinct); "
        f"{stops or 'none'}"
    )
    if f.inconsistent_queries or not f.accepted_equals_loop_closures:
        print(
            f"  funnel DOES NOT ADD UP: {f.inconsistent_queries} queries inconsistent, "
            f"{f.accepted} accepted against the loop closures held"
        )


def _print_detector(d: DetectorFigures) -> None:
    if d.render:
        r = d.render
        print(f"  rendered {r['frames']} RGB-D frames in {r['total_s']:.1f} s into {r['folder']}")
    skipped = ", ".join(f"{k} {v}" for k, v in d.skipped.items()) or "none"
    dropped = sum(d.boxes_dropped.values())
    stages = ", ".join(f"{k} {v:.1f} ms" for k, v in d.stage_ms_mean.items())
    print(
        f"  detector {Path(d.model).name} (conf {d.conf_threshold:g}): {d.frames} frames, "
        f"skipped: {skipped}; {d.objects_per_frame:.1f} objects per frame, {dropped} boxes dropped (no depth)"
    )
    if stages:
        print(f"  detector time per frame: {stages}")
