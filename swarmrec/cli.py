"""The ``swarmrec`` command line.

Each subcommand parses its arguments into a settings object and calls the
``main(settings)`` of the module that does the work, so tests call the same
code without a shell.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from swarmrec.core.presets import PRESETS
from swarmrec.errors import ConfigError, SwarmrecError

__all__ = ["build_parser", "main"]


def _add_evaluate(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "evaluate",
        help="score a dataset as the constellation paper did (centralized and N robots)",
        description=(
            "Score every frame pair of a constellation dataset centralized and/or with the "
            "decentralized two-step query of N robots; write pair scores, best matches, "
            "precision-recall/AUC against ground truth, the paper's byte model, the load "
            "on each range holder and plots."
        ),
    )
    p.add_argument(
        "--dataset",
        default="synthetic",
        help="'synthetic' (built-in office world) or a folder/.zip of <timestamp>.txt "
        "constellation files (default: synthetic)",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the synthetic world (default 0)")
    p.add_argument("--frames", type=int, help="use only the first N frames (synthetic: generate N)")
    p.add_argument("--labels", type=Path, help="label list, one name a line (default: COCO 80)")
    p.add_argument(
        "--groundtruth",
        type=Path,
        help="TUM trajectory (groundtruth.txt) for precision-recall; default: "
        "groundtruth.txt beside the constellations, or the synthetic world's poses",
    )
    p.add_argument(
        "--gt-rules",
        choices=["none", "tum-fr3-office"],
        default="none",
        help="hand-made ground-truth rules of the published fr3/long_office_household evaluation",
    )
    p.add_argument(
        "--mode",
        choices=["centralized", "decentralized", "both"],
        default="both",
        help="(default both)",
    )
    p.add_argument("--robots", type=int, default=10, help="robots of the decentralized mode (default 10)")
    p.add_argument("--preset", choices=sorted(PRESETS), default="paper", help="(default paper)")
    p.add_argument("--out", type=Path, default=Path("runs/evaluate"), help="output folder")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def _add_synth(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "synth",
        help="write the synthetic office world as constellation files + groundtruth.txt",
    )
    p.add_argument("--out", type=Path, required=True, help="folder to write")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--frames", type=int, help="number of frames (default: the world's default)")


def _add_dataset_arguments(p: argparse.ArgumentParser) -> None:
    """What the swarm replays: shared by `run` and `compose`."""
    p.add_argument(
        "--dataset",
        default="synthetic",
        help="'synthetic' (built-in office world) or a folder/.zip of constellation files",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the synthetic world (default 0)")
    p.add_argument("--frames", type=int, help="use only the first N frames (synthetic: generate N)")
    p.add_argument("--labels", type=Path, help="label list, one name a line (default: COCO 80)")
    p.add_argument("--groundtruth", type=Path, help="TUM trajectory for precision-recall")
    p.add_argument("--preset", choices=sorted(PRESETS), default="paper", help="(default paper)")


def _add_run(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
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
    _add_dataset_arguments(p)
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
    p.add_argument("--out", type=Path, default=Path("runs/swarm"), help="output folder")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
    p.add_argument(
        "--no-offline-check",
        action="store_true",
        help="skip comparing the pair scores with the offline evaluation",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bars")
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
    p.add_argument(
        "--attach",
        type=Path,
        metavar="DIR",
        help="start nothing: replay through the running swarm that `swarmrec compose up --out DIR` "
        "started (its dataset, robots and preset; --pace, --out, --no-plots still apply)",
    )


def _camera(text: str) -> tuple[float, float, float, float]:
    try:
        fx, fy, cx, cy = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected FX,FY,CX,CY such as 535.4,539.2,320.1,247.6, got {text!r}"
        ) from None
    return fx, fy, cx, cy


def _add_compose(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    from swarmrec.swarm.compose import MAX_ROBOTS

    p = sub.add_parser(
        "compose",
        help="the swarm as containers: write a compose file for N robots, bring it up or down",
        description=(
            "write: generate compose.yml (router, each robot's detector, descriptor, index-shard and "
            "verifier, Prometheus), prometheus.yml, swarm.json and the dataset under --out. "
            "up: write, then start every container and wait until all are healthy. "
            "down: stop and remove the containers, the network and (unless --keep-volumes) the volumes. "
            "Build the images first (make images). Then `swarmrec run --attach DIR` replays through it "
            "(--workload landmarks: a detector in classifier mode and a fusion service per robot, "
            "driven by `swarmrec landmarks --attach DIR`)."
        ),
    )
    p.add_argument("action", choices=("write", "up", "down"))
    p.add_argument("--robots", type=int, default=4, help=f"robots, 1 .. {MAX_ROBOTS} (default 4)")
    p.add_argument(
        "--workload",
        choices=("places", "landmarks"),
        default="places",
        help="places: detector, descriptor, index-shard, verifier per robot; landmarks: detector "
        "(classifier mode) and fusion per robot (default places)",
    )
    _add_dataset_arguments(p)
    p.add_argument("--swarm", default="compose", help="swarm name (default compose)")
    p.add_argument("--project", default="swarmrec", help="compose project name (default swarmrec)")
    p.add_argument("--router-port", type=int, default=7447, help="router port on 127.0.0.1 (default 7447)")
    p.add_argument(
        "--prometheus-port", type=int, default=9090, help="Prometheus port on 127.0.0.1 (default 9090)"
    )
    p.add_argument(
        "--free", action="store_true", help="compose for free replay (--pace fast or a rate), not lock-step"
    )
    p.add_argument("--timeout", type=float, default=5.0, help="seconds a service waits for a peer")
    p.add_argument("--out", type=Path, default=Path("runs/compose"), help="folder (default runs/compose)")
    p.add_argument("--keep-volumes", action="store_true", help="down: keep the named volumes")


def _add_serve(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    from swarmrec.services import SERVICES
    from swarmrec.services.config import add_arguments

    p = sub.add_parser(
        "serve",
        help="run one service of one robot (router, detector, descriptor, index-shard, verifier, fusion)",
        description=(
            "Run one swarm service until SIGTERM/SIGINT. Settings come from defaults < --config "
            "TOML file < SWARMREC_* environment < flags. Prints one JSON 'ready' line on stdout "
            "when serving; logs are JSON lines on stderr."
        ),
    )
    p.add_argument("kind", choices=SERVICES, help="which service")
    add_arguments(p)


def _add_clients(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    def common(p: argparse.ArgumentParser) -> None:
        p.add_argument(
            "--connect",
            default="tcp/127.0.0.1:7447",
            help="router endpoint(s), comma-separated (default tcp/127.0.0.1:7447)",
        )
        p.add_argument("--swarm", default="local", help="swarm name (default local)")
        p.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for answers (default 5)")
        p.add_argument("--json", action="store_true", help="print JSON instead of a table")

    p = sub.add_parser("query", help="ask a running swarm where a constellation was seen (nothing is stored)")
    p.add_argument(
        "constellation", type=Path, help="a constellation file (one 'label x y z' line per object)"
    )
    p.add_argument("--labels", type=Path, help="label list (default: COCO 80)")
    p.add_argument("--preset", choices=sorted(PRESETS), default="paper", help="(default paper)")
    p.add_argument("--top", type=int, default=10, help="matches to show (default 10)")
    common(p)
    p = sub.add_parser("members", help="list a running swarm's live services and shard label ranges")
    common(p)
    p = sub.add_parser("loop-closures", help="fetch the loop closures a robot has found")
    p.add_argument("robot", type=int, help="robot id")
    p.add_argument("--min-score", type=float, default=0.0, help="only closures at least this good")
    common(p)


def _add_landmarks(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    from swarmrec.swarm.landmarks import DEFAULT_LAWS, VIEW_PRESETS

    p = sub.add_parser(
        "landmarks",
        help="cooperative landmark recognition: a simulated street, each robot's CNN, fusion over zenoh",
        description=(
            "Simulate a swarm in a street of 19 landmarks (the WNBC paper's experiment): each robot "
            "renders what it faces, its detector (classifier mode) classifies it, the fusion services "
            "flood the outputs to their radio neighbours over a real zenoh router and fuse them with "
            "the weighted naive Bayes classifier. Writes the recognition rate against incorporated "
            "messages per weight law (Fig. 3), two configurations (Fig. 4), the confusion matrix "
            "(Fig. 5), bytes per round and checks to OUT (docs/landmarks.md)."
        ),
    )
    p.add_argument("--configurations", type=int, default=118, help="street configurations (default 118)")
    p.add_argument("--robots", type=int, default=10, help="robots (default 10)")
    p.add_argument(
        "--laws",
        default=",".join(law.key for law in DEFAULT_LAWS),
        help="weight laws to compare, comma-separated: paper:LAMBDA or agreement[:PRIOR_LAMBDA] "
        "(default: the paper's four lambdas and the adaptive law)",
    )
    p.add_argument(
        "--views",
        choices=sorted(VIEW_PRESETS),
        default="nominal",
        help="nominal: the nuisances the CNN was trained on; harsh: occluded, dark, noisy views "
        "(single robot near the paper's 68 %%) (default nominal)",
    )
    p.add_argument("--radio-range", type=float, default=7.0, help="talk below this distance (m, default 7)")
    p.add_argument("--seed", type=int, default=0, help="configurations and views (default 0)")
    p.add_argument("--model", default="", help="classifier ONNX (default: the shipped one)")
    p.add_argument("--figure-law", help="law of Figs. 4 and 5 (default paper:2 when run)")
    p.add_argument(
        "--attach",
        type=Path,
        metavar="DIR",
        help="run the rounds through the compose swarm of DIR (swarmrec compose up --workload landmarks) "
        "instead of starting local processes",
    )
    p.add_argument("--out", type=Path, default=Path("runs/landmarks"), help="report folder")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="swarmrec",
        description="Decentralized place recognition for robot swarms (constellations of objects).",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    _add_evaluate(sub)
    _add_synth(sub)
    _add_run(sub)
    _add_compose(sub)
    _add_landmarks(sub)
    _add_serve(sub)
    _add_clients(sub)
    return parser


def _evaluate(args: argparse.Namespace) -> int:
    from swarmrec.evaluation.offline import EvaluationSettings
    from swarmrec.evaluation.offline import main as evaluate

    settings = EvaluationSettings(
        dataset=args.dataset,
        seed=args.seed,
        frames=args.frames,
        labels=args.labels,
        groundtruth=args.groundtruth,
        gt_rules=args.gt_rules,
        mode=args.mode,
        robots=args.robots,
        preset=args.preset,
        out=args.out,
        plots=not args.no_plots,
        progress=not args.quiet,
    )
    summary = evaluate(settings)
    ds = summary["dataset"]
    print(f"dataset {ds['name']}: {ds['frames']} frames, {ds['ignored_frames']} with too few objects")
    for name, result in summary["results"].items():
        auc = f"AUC {result['auc']:.4f}" if "auc" in result else "AUC n/a (no ground truth)"
        print(f"  {name:<20} {auc}, {result['positive_pairs']} pairs scored > 0")
    if "bandwidth" in summary:
        bw = summary["bandwidth"]
        print(
            f"  byte model: {bw['paper_byte_model_per_query']['total']:.1f} B per query; "
            f"busiest range holder / mean = {bw['holder_load']['balance_ratio']:.2f}"
        )
    timings = ", ".join(f"{k[:-2]} {v:.2f} s" for k, v in summary["timings"].items())
    print(f"  time: {timings}")
    print(f"  written to {settings.out}/ (summary.json, scores_*.npz, best_matches_*.csv, *.png)")
    return 0


def _synth(args: argparse.Namespace) -> int:
    from swarmrec.synthetic import OfficeConfig, generate_office, write_dataset

    config = (
        OfficeConfig(seed=args.seed)
        if args.frames is None
        else OfficeConfig(seed=args.seed, n_frames=args.frames)
    )
    ds = generate_office(config)
    write_dataset(ds, args.out)
    print(json.dumps({"out": str(args.out), "frames": len(ds.sequence)}))
    return 0


def _serve(args: argparse.Namespace) -> int:
    from swarmrec.services import service_factory
    from swarmrec.services.config import load_settings

    settings = load_settings(args)
    if args.kind == "router":
        from swarmrec.services.router import run_router

        return run_router(settings)
    from swarmrec.services.runner import run_service

    return run_service(settings, args.kind, service_factory(args.kind))


def _run(args: argparse.Namespace) -> int:
    from swarmrec.swarm.job import SwarmSettings
    from swarmrec.swarm.job import main as run_swarm

    if args.attach is not None:
        from swarmrec.swarm.attached import main_attached

        out = args.out if args.out != Path("runs/swarm") else args.attach / "report"
        s = main_attached(
            args.attach,
            out=out,
            pace=args.pace,
            plots=not args.no_plots,
            progress=not args.quiet,
            check_offline=not args.no_offline_check,
        )
        _print_summary(s, out)
        return 0
    settings = SwarmSettings(
        dataset=args.dataset,
        seed=args.seed,
        frames=args.frames,
        labels=args.labels,
        groundtruth=args.groundtruth,
        robots=args.robots,
        preset=args.preset,
        pace=args.pace,
        swarm=args.swarm,
        request_timeout_s=args.timeout,
        out=args.out,
        plots=not args.no_plots,
        progress=not args.quiet,
        check_offline=not args.no_offline_check,
        from_pixels=args.from_pixels,
        rgbd=args.rgbd,
        model=args.model,
        conf_threshold=args.conf_threshold,
        detector_threads=args.detector_threads,
        camera=args.camera,
        depth_scale=args.depth_scale,
    )
    s = run_swarm(settings)
    _print_summary(s, settings.out)
    return 0


def _print_summary(s: dict[str, Any], out: Path) -> None:
    q, b, load, sw = s["queries"], s["bytes"], s["shard_load"], s["swarm"]
    where = f"{sw['processes']} processes" if sw["processes"] else sw["deployment"]
    print(
        f"swarm of {sw['robots']} robots on {s['dataset']['name']} ({s['dataset']['frames']} frames, "
        f"{where}), pace {sw['pace']}"
    )
    auc = f"AUC {s['auc']:.4f}" if "auc" in s else "AUC n/a (no ground truth)"
    if "detector" in s:
        _print_detector(s["detector"])
    print(f"  {q['queried']} queries, {s['loop_closures']['count']} loop closures, {auc}")
    lat = q["latency_ms"]
    if lat:
        print(f"  query latency p50 {lat['p50']:.2f} ms, p99 {lat['p99']:.2f} ms")
    per_frame = f"{b['per_frame']:.1f} B per frame"
    print(f"  measured bytes between robots: {b['per_query']:.1f} B per query ({per_frame})")
    print(
        f"  partial queries per shard {load['partial_queries']}; busiest / mean = {load['balance_ratio']:.2f}"
    )
    if "offline_check" in s:
        oc = s["offline_check"]
        verdict = "identical" if oc["identical"] else f"DIFFERENT ({oc})"
        print(f"  pair scores vs offline decentralized evaluation: {verdict}")
    if q["missing_slots"]:
        print(f"  missing answers: {q['missing_slots']} (by robot {q['missing_by_robot']})")
    if s["scrape_failed"]:
        print(f"  metrics not read from: {', '.join(s['scrape_failed'])}")
    t = s["timings"]
    start = f"start {t['start_s']:.1f} s, " if "start_s" in t else ""
    print(f"  time: {start}replay {t['replay_s']:.1f} s, total {t['total_s']:.1f} s")
    print(f"  written to {out}/ (summary.json, pairs.csv, loop_closures.csv, *.png)")


def _print_detector(d: dict[str, Any]) -> None:
    if d.get("render"):
        r = d["render"]
        print(f"  rendered {r['frames']} RGB-D frames in {r['total_s']:.1f} s into {r['folder']}")
    skipped = ", ".join(f"{k} {v}" for k, v in d["skipped"].items()) or "none"
    dropped = sum(d["boxes_dropped"].values())
    stages = ", ".join(f"{k} {v:.1f} ms" for k, v in d["stage_ms_mean"].items())
    print(
        f"  detector {Path(d['model']).name} (conf {d['conf_threshold']:g}): {d['frames']} frames, "
        f"skipped: {skipped}; {d['objects_per_frame']:.1f} objects per frame, "
        f"{dropped} boxes dropped (no depth)"
    )
    if stages:
        print(f"  detector time per frame: {stages}")


def _compose(args: argparse.Namespace) -> int:
    from swarmrec.swarm import compose

    settings = compose.ComposeSettings(
        robots=args.robots,
        workload=args.workload,
        dataset=args.dataset,
        seed=args.seed,
        frames=args.frames,
        labels=args.labels,
        groundtruth=args.groundtruth,
        preset=args.preset,
        swarm=args.swarm,
        project=args.project,
        out=args.out,
        router_port=args.router_port,
        prometheus_port=args.prometheus_port,
        lockstep=not args.free,
        request_timeout_s=args.timeout,
    )
    if args.action == "down":
        info = compose.read_swarm_file(args.out)
        compose.down(info, volumes=not args.keep_volumes)
        print(f"compose project {info.project}: containers and network removed", end="")
        print("" if args.keep_volumes else ", volumes removed")
        return 0
    info = compose.write_compose(settings)
    containers = len(info.services) * settings.robots + 2
    what = f"{settings.robots} robots, {settings.workload}, {containers} containers"
    print(f"wrote {info.compose_file} ({what})")
    if args.action == "up":
        print("starting containers; waiting until every one is healthy ...", flush=True)
        seconds = compose.up(info)
        print(f"swarm up in {seconds:.1f} s: router {info.router_endpoint}, Prometheus {info.prometheus_url}")
        if settings.workload == "landmarks":
            print(f"simulate the street through it: swarmrec landmarks --attach {args.out}")
        else:
            print(f"replay through it: swarmrec run --attach {args.out}")
    return 0


def _client(args: argparse.Namespace) -> Any:
    from swarmrec.client import SwarmClient

    return SwarmClient(
        [e.strip() for e in args.connect.split(",") if e.strip()], args.swarm, timeout_s=args.timeout
    )


def _query(args: argparse.Namespace) -> int:
    from swarmrec.datasets.constellations import parse_constellation
    from swarmrec.datasets.labels import COCO_NAMES, LabelMap, read_label_names

    names = read_label_names(args.labels) if args.labels else COCO_NAMES
    try:
        text = args.constellation.read_text(encoding="utf-8")
    except OSError as e:
        raise ConfigError(f"cannot read {args.constellation}: {e.strerror}") from None
    constellation = parse_constellation(text, LabelMap(names), str(args.constellation))
    with _client(args) as swarm:
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
    with _client(args) as swarm:
        members = swarm.members()
    if args.json:
        print(json.dumps([m.__dict__ for m in members]))
        return 0 if members else 3
    if not members:
        print(f"no live member in swarm {args.swarm!r}", file=sys.stderr)
        return 3
    print(f"{'service':<12} {'robot':>5} {'labels':>10} {'stored':>7} {'version':>8}  metrics")
    for m in members:
        rng = f"{m.label_range[0]}-{m.label_range[1]}" if m.label_range else ""
        print(f"{m.kind:<12} {m.robot:>5} {rng:>10} {m.stored_items:>7} {m.version:>8}  {m.metrics_url}")
    return 0


def _loop_closures(args: argparse.Namespace) -> int:
    with _client(args) as swarm:
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


def _landmarks(args: argparse.Namespace) -> int:
    from swarmrec.swarm.landmarks import LandmarkSettings, parse_law
    from swarmrec.swarm.landmarks import main as simulate

    laws = tuple(parse_law(text) for text in args.laws.split(",") if text.strip())
    if args.figure_law and args.figure_law not in {law.key for law in laws}:
        raise ConfigError(f"--figure-law {args.figure_law} is not one of --laws ({args.laws})")
    settings = LandmarkSettings(
        out=args.out,
        configurations=args.configurations,
        robots=args.robots,
        seed=args.seed,
        laws=laws,
        views=args.views,
        radio_range=args.radio_range,
        model=args.model,
        progress=not args.quiet,
    )
    summary = simulate(settings, args.figure_law, attach=args.attach)
    st, checks = summary["settings"], summary["checks"]
    print(
        f"{st['configurations']} configurations x {st['robots']} robots, {st['views']} views: "
        f"{checks['robot_rounds']} of {checks['expected_robot_rounds']} robot-rounds recorded"
    )
    print(f"correct recognition (%) after k incorporated messages, k = 0 .. {st['robots'] - 1}:")
    for key, rec in summary["recognition"].items():
        rates = " ".join("  - " if r is None else f"{100 * r:4.1f}" for r in rec["rate"])
        print(f"  {key:<14} {rates}")
    b = summary["bytes"]
    print(
        f"bytes between robots per round: {b['classifier_output_bytes_per_round']:.0f} "
        f"({b['classifier_output_messages_per_round']:.0f} ClassifierOutput messages)"
    )
    print(f"core check: largest posterior difference {checks['core_max_difference']}")
    print(f"report: {args.out / 'report.md'}")
    return 0 if checks["robot_rounds"] == checks["expected_robot_rounds"] else 1


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    handlers = {
        "evaluate": _evaluate,
        "synth": _synth,
        "serve": _serve,
        "run": _run,
        "query": _query,
        "members": _members,
        "loop-closures": _loop_closures,
        "compose": _compose,
        "landmarks": _landmarks,
    }
    try:
        return handlers[args.command](args)
    except SwarmrecError as exc:
        print(f"swarmrec {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
