"""Full-image place recognition on the command line (docs/vpr.md).

* ``swarmrec vpr evaluate``: the offline evaluation (:func:`swarmrec.vpr.evaluation.main`:
  the paper's Figs. 6 and 7, the re-balancing, the quantised codes);
* ``swarmrec vpr centres``: k-means centres for any k (:func:`swarmrec.vpr.centres.main`);
* ``swarmrec run --method dvpr|both``: the live swarm (the flags are added to ``run`` by
  :func:`add_method_flags`, the run handed over by :func:`run_method`).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

from swarmrec.cli.common import Subparsers
from swarmrec.deployments.base import Deployment
from swarmrec.deployments.local import LocalDeployment, LocalSettings
from swarmrec.errors import ConfigError
from swarmrec.experiments.places import PlacesSettings, PlacesSummary
from swarmrec.experiments.vpr import BothSummary, Comparison, DvprSettings, DvprSummary, VprRunSettings
from swarmrec.experiments.vpr import main as vpr_main
from swarmrec.experiments.vpr.settings import METHODS
from swarmrec.vpr.centres import CentresSettings
from swarmrec.vpr.centres import main as centres_main
from swarmrec.vpr.evaluation import EvaluationSettings, EvaluationSummary
from swarmrec.vpr.evaluation import main as evaluation_main

__all__ = ["add", "add_method_flags", "print_comparison", "print_dvpr", "run_method"]


def _ints(text: str) -> tuple[int, ...]:
    try:
        values = tuple(int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated integers such as 2,10,20, got {text!r}"
        ) from None
    return values


def add(sub: Subparsers) -> None:
    p = sub.add_parser(
        "vpr",
        help="full-image place recognition offline: the evaluation (paper Figs. 6, 7) and k-means centres",
        description="Decentralized place recognition from full-image descriptors, offline (docs/vpr.md). "
        "The live swarm is `swarmrec run --method dvpr --from-pixels`.",
    )
    cmds = p.add_subparsers(dest="vpr_command", required=True, metavar="COMMAND")
    e = cmds.add_parser(
        "evaluate",
        help="the offline evaluation: Figs. 6 and 7, re-balancing, quantised codes, byte model",
        description="Render a held-out office, describe it, and run the paper's experiments through real "
        "owner indexes; writes descriptors.npz, runs.npz, runs.json, summary.json, fig6.png, fig7.png.",
    )
    d = EvaluationSettings(out=Path("runs/vpr"))
    e.add_argument("--out", type=Path, default=d.out, help=f"output folder (default {d.out})")
    e.add_argument("--model", type=Path, help="descriptor ONNX (default: the shipped model)")
    e.add_argument("--robots", type=_ints, default=d.robots, metavar="N,N,...",
                   help="robot counts of Fig. 6 (default 2..20)")  # fmt: skip
    e.add_argument(
        "--fig7-robots", type=int, default=d.fig7_robots, help=f"robots of Fig. 7 (default {d.fig7_robots})"
    )
    e.add_argument("--clusters-per-robot", type=_ints, default=d.clusters_per_robot, metavar="C,C,...",
                   help="clusters per robot of Fig. 7 (default 1,2,3,4,6,8,12,16)")  # fmt: skip
    e.add_argument("--runs", type=int, default=d.runs, help=f"seeds per configuration (default {d.runs})")
    e.add_argument("--deployment-seed", type=int, default=d.deployment_seed,
                   help=f"the held-out office (default {d.deployment_seed})")  # fmt: skip
    e.add_argument("--deployment-frames", type=int, default=d.deployment_frames,
                   help=f"its frames (default {d.deployment_frames})")  # fmt: skip
    e.add_argument(
        "--other-worlds",
        type=int,
        default=d.other_worlds,
        help=f"varied offices the k-means centres are trained on (default {d.other_worlds})",
    )
    e.add_argument("--copy-neighbours", type=int, default=d.copy_neighbours,
                   help="re-balancing: boundary copies go to the owners of up to this many next-nearest "
                   f"cells (default {d.copy_neighbours})")  # fmt: skip
    e.add_argument("--threads", type=int, default=d.threads, help="faiss and onnxruntime threads (default 1)")
    e.add_argument("--quiet", action="store_true", help="no progress display")
    e.set_defaults(handler=run_evaluate)
    c = cmds.add_parser(
        "centres",
        help="k-means centres of the descriptor for any k, trained on other worlds than a swarm's",
        description="Describe varied office worlds and train k-means centres for each k into one .npz "
        "(swarmrec run --method dvpr --centres FILE, or a place-owner's --vpr-centres).",
    )
    dc = CentresSettings(out=Path("centres.npz"))
    c.add_argument("--out", type=Path, required=True, help="the .npz to write (one array per k)")
    c.add_argument("--model", type=Path, help="descriptor ONNX (default: the shipped model)")
    c.add_argument(
        "--ks",
        type=_ints,
        default=dc.ks,
        metavar="K,K,...",
        help="numbers of centres (default 10,20,40,80,160)",
    )
    c.add_argument(
        "--worlds", type=int, default=dc.worlds, help=f"varied office worlds (default {dc.worlds})"
    )
    c.add_argument(
        "--seed-base", type=int, default=dc.seed_base, help=f"their seeds start here (default {dc.seed_base})"
    )
    c.add_argument(
        "--stride", type=int, default=dc.stride, help=f"describe every n-th frame (default {dc.stride})"
    )
    c.add_argument("--seed", type=int, default=dc.seed, help="k-means seed (default 0)")
    c.set_defaults(handler=run_centres)


def run_evaluate(args: argparse.Namespace) -> int:
    settings = EvaluationSettings(
        out=args.out,
        model=args.model,
        robots=args.robots,
        fig7_robots=args.fig7_robots,
        clusters_per_robot=args.clusters_per_robot,
        runs=args.runs,
        deployment_seed=args.deployment_seed,
        deployment_frames=args.deployment_frames,
        other_worlds=args.other_worlds,
        copy_neighbours=args.copy_neighbours,
        threads=args.threads,
        progress=not args.quiet,
    )
    summary = evaluation_main(settings)
    print_evaluation(summary, settings)
    return 0


def print_evaluation(summary: EvaluationSummary, settings: EvaluationSettings) -> None:
    """The evaluation's tables, each under a heading (summary.json holds every run's values)."""
    runs = f"mean of {settings.runs} runs" if settings.runs > 1 else "one run"
    print(
        f"full-image place recognition on office {settings.deployment_seed} ({settings.deployment_frames} "
        f"frames), {runs} a row; relative AUC = decentralized / centralized, balance = busiest / mean robot"
    )
    print("Fig. 6: one k-means cluster per robot")
    print(f"  {'robots':>6} {'relative AUC':>13} {'worst balance':>14} {'bytes a query':>14}")
    for row in summary.fig6:
        print(
            f"  {row['n_robots']:>6} {row['relative_auc_mean']:>13.3f} "
            f"{row['worst_balance_ratio_mean']:>14.2f} {row['bytes_per_query_mean']:>14.1f}"
        )
    print(f"Fig. 7: {settings.fig7_robots} robots, c clusters per robot")
    print(f"  {'c':>6} {'relative AUC':>13} {'worst balance':>14} {'bytes a query':>14}")
    for row in summary.fig7:
        print(
            f"  {row['clusters_per_robot']:>6} {row['relative_auc_mean']:>13.3f} "
            f"{row['worst_balance_ratio_mean']:>14.2f} {row['bytes_per_query_mean']:>14.1f}"
        )
    b = summary.balance
    if "relative_auc_mean" in b:
        after = b.get("worst_balance_ratio_after_first_period_runs") or []
        worst_after = f", after the first period {max(after):.2f}" if after else ""
        print(
            f"re-balancing ({b['n_robots']} robots, {b['clusters_per_robot_start']} clusters each to start; "
            "beyond the paper)"
        )
        print(
            f"  relative AUC {b['relative_auc_mean']:.3f}, worst balance {b['worst_balance_ratio_mean']:.2f}"
            f"{worst_after}, boundary copies {b['copies_per_query_mean']:.2f} a query, "
            f"migration {b['migration_bytes_per_query_mean']:.1f} B a query"
        )
    if summary.quantisation:
        print("descriptor codes (the model card's protocol: recall and AUC against float32)")
        print(f"  {'code':>8} {'bytes':>6} {'recall@1':>9} {'recall@5':>9} {'AUC':>7}")
        for q in summary.quantisation:
            print(
                f"  {q['code']:>8} {q['descriptor_bytes']:>6} {q['recall_at_1']:>9.3f} "
                f"{q['recall_at_5']:>9.3f} {q['auc']:>7.3f}"
            )
    seconds = summary.seconds["total"]
    print(f"written to {summary.out}/ (summary.json, runs.json, fig6.png, fig7.png) in {seconds:.0f} s")


def run_centres(args: argparse.Namespace) -> int:
    summary = centres_main(
        CentresSettings(args.out, args.model, args.ks, args.worlds, args.seed_base, args.stride, args.seed)
    )
    print(
        f"{len(summary.ks)} sets of centres (k = {', '.join(map(str, summary.ks))}) from "
        f"{summary.descriptors} descriptors -> {summary.path} ({summary.seconds:.0f} s)"
    )
    return 0


# --- swarmrec run --method ------------------------------------------------------------


def add_method_flags(p: argparse.ArgumentParser) -> None:
    """``--method`` and the full-image method's flags, on ``swarmrec run``."""
    p.add_argument(
        "--method",
        choices=METHODS,
        default="constellations",
        help="constellations (default: objects and a two-step query); dvpr (a full-image descriptor per "
        "frame, sent to the owner of its nearest k-means centre; needs --from-pixels or --rgbd); both "
        "(each on its own swarm, the same frames, side by side)",
    )
    d = DvprSettings()
    g = p.add_argument_group("full-image method (--method dvpr, both)", 'docs/vpr.md, "The live swarm"')
    g.add_argument("--clusters-per-robot", type=int, default=d.clusters_per_robot,
                   help="k-means clusters each robot owns (the paper's c; default 1)")  # fmt: skip
    g.add_argument("--assignment-seed", type=int, default=d.assignment_seed,
                   help="seed of the random assignment of clusters to robots (default 0)")  # fmt: skip
    g.add_argument(
        "--assignment",
        type=Path,
        metavar="JSON",
        help="an assignment table instead (swarmrec.vpr.assignment/1)",
    )
    g.add_argument("--centres", type=Path, metavar="NPZ",
                   help="k-means centres (default: the shipped ones, or trained into OUT/centres.npz for a k "
                   "they lack)")  # fmt: skip
    g.add_argument("--vpr-wire-code", choices=("int8", "float32"), default=d.wire_code,
                   help="how a query carries its descriptor: int8 (132 B, default) or float32 (512 B, "
                   "the paper's)")  # fmt: skip
    g.add_argument(
        "--descriptor-model", default="", metavar="ONNX", help="the descriptor model (default: the project's)"
    )
    g.add_argument("--rebalance-every", type=int, default=d.rebalance_every, metavar="STEPS",
                   help="re-balance the cluster owners live after every STEPS lock-step steps (default 0: "
                   "never); start with more clusters per robot, e.g. --clusters-per-robot 8 (docs/vpr.md, "
                   '"Re-balancing a live swarm")')  # fmt: skip


def run_method(
    args: argparse.Namespace,
    run: PlacesSettings,
    local: LocalSettings,
    print_places: Callable[[PlacesSummary, Path], None],
    swarm_at: Callable[[Path], Deployment] | None = None,
) -> int:
    """``swarmrec run --method dvpr|both`` with the run's shared settings ``run``, on local
    processes (``local``) or, with ``swarm_at``, on the deployment it gives for each method's
    folder (``--deployment k8s``); ``print_places`` prints the constellation run's summary
    (``swarmrec run``'s own printer)."""
    if args.attach is not None:
        raise ConfigError(
            "--method dvpr and both start their own local swarms; --attach replays constellations"
        )
    settings = VprRunSettings(
        run=run,
        dvpr=DvprSettings(
            clusters_per_robot=args.clusters_per_robot,
            assignment_seed=args.assignment_seed,
            wire_code=args.vpr_wire_code,
            centres=args.centres,
            assignment=args.assignment,
            descriptor_model=args.descriptor_model,
            rebalance_every=args.rebalance_every,
        ),
        method=args.method,
    )
    if swarm_at is None:
        swarm_at = lambda folder: LocalDeployment.for_run(folder, local)  # noqa: E731
    result = vpr_main(settings, swarm_at, say=print)
    if isinstance(result, BothSummary):
        print("constellations:")
        print_places(result.constellations, settings.out / "constellations")
        print("dvpr:")
        print_dvpr(result.dvpr, settings.out / "dvpr")
        print_comparison(result.comparison, settings.out)
    else:
        print_dvpr(result, settings.out)
    return 0


def print_dvpr(s: DvprSummary, out: Path) -> None:
    sw, q, b, load = s.swarm, s.queries, s.bytes, s.load
    # Compose and Kubernetes start no process of this run's (their stop reports none): their description.
    where = f"{sw['processes']} processes" if sw["processes"] else sw["deployment"]
    print(
        f"swarm of {sw['robots']} robots on {s.dataset['name']} ({s.dataset['frames']} frames, "
        f"{where}), full-image descriptors, pace {sw['pace']}"
    )
    if s.detector is not None and s.detector.stage_ms_mean:
        stages = ", ".join(f"{k} {v:.1f} ms" for k, v in s.detector.stage_ms_mean.items())
        print(f"  detector time per frame: {stages}")
    print(
        f"  {sw['clusters']} clusters ({sw['clusters_per_robot']} per robot, assignment version "
        f"{sw['assignment']['version']}), queries carry {sw['wire_code']} descriptors"
    )
    auc = "AUC n/a (no ground truth)" if s.auc is None else f"AUC {s.auc:.4f}"
    if s.relative_auc is not None and s.centralized_auc is not None:
        auc += f" (centralized {s.centralized_auc:.4f}, relative {s.relative_auc:.3f})"
    print(
        f"  {q.frames} queries, {q.matched} answered with a match, {q.verified} verified, "
        f"{q.loop_closures} loop closures, {auc}"
    )
    op = s.operating_point
    if op is not None:
        print(
            f"  loop closures: precision {op.precision:.3f}, recall {op.recall:.3f} "
            f"({op.true_cross_robot} of {op.cross_robot} cross-robot closures show the same place)"
        )
    if q.latency_ms:
        print(f"  query latency p50 {q.latency_ms['p50']:.2f} ms, p99 {q.latency_ms['p99']:.2f} ms")
    print(
        f"  measured bytes between robots: {b.per_query:.1f} B per query ({b.query_per_query:.1f} B the "
        f"query and its answer, {b.verification_per_query:.1f} B verification)"
    )
    print(
        f"  paper's byte model on these answers: {b.model_float32['total']:.1f} B per query with float32 "
        f"({b.model_wire_code['total']:.1f} B with {sw['wire_code']}); "
        f"{100 * b.model_float32['remote_share']:.0f} % of queries went to another robot"
    )
    print(f"  queries per owner {load.queries}; busiest / mean = {load.balance_ratio:.2f}")
    if s.rebalancing and s.load_before_rebalancing is not None:
        before = s.load_before_rebalancing
        print(f"  live re-balancing: busiest / mean {before.balance_ratio:.2f} before the first table")
        for rb in s.rebalancing:
            if rb.copy_margin is None:
                margin = "every descriptor"
            else:
                margin = "none" if rb.copy_margin < 0 else f"descriptors with gap <= {rb.copy_margin:.3g}"
            print(
                f"    after step {rb.after_step}: table version {rb.version}, {rb.clusters} clusters, "
                f"planned on {rb.observed_queries} queries, {rb.moved} descriptors moved, copies of "
                f"{margin}; then busiest / mean {rb.balance_ratio:.2f}"
            )
    if s.offline_check is not None:
        oc = s.offline_check
        verdict = "identical" if oc.identical else f"DIFFERENT ({oc})"
        print(f"  owners, matches and distances vs the offline simulation: {verdict}")
    if q.missing_slots:
        print(f"  missing answers: {q.missing_slots}")
    t = s.timings
    print(f"  time: start {t.get('start_s', 0):.1f} s, replay {t.get('replay_s', 0):.1f} s")
    print(f"  written to {out}/ (summary.json, answers.csv, loop_closures.csv, *.png)")


def _num(value: float | None, fmt: str) -> str:
    return "n/a" if value is None else format(value, fmt)


def print_comparison(c: Comparison, out: Path) -> None:
    print(f"side by side, {c.robots} robots, the same {c.frames} frames:")
    rows = [
        ("AUC (each paper's protocol)", [_num(m.auc, ".4f") for m in c.methods]),
        ("loop closures", [str(m.loop_closures) for m in c.methods]),
        ("precision at the operating point", [_num(m.precision, ".3f") for m in c.methods]),
        ("recall at the operating point", [_num(m.recall, ".3f") for m in c.methods]),
        ("bytes per query, measured", [f"{m.bytes_per_query:.1f}" for m in c.methods]),
        ("bytes per frame, measured", [f"{m.bytes_per_frame:.1f}" for m in c.methods]),
        ("bytes per query, dvpr byte model", [_num(m.byte_model_per_query, ".1f") for m in c.methods]),
        ("busiest / mean load", [f"{m.balance_ratio:.2f}" for m in c.methods]),
        (
            "query latency p50 / p99, ms",
            [f"{_num(m.latency_p50_ms, '.2f')} / {_num(m.latency_p99_ms, '.2f')}" for m in c.methods],
        ),
    ]
    print(f"  {'':36}" + "".join(f"{m.method:>18}" for m in c.methods))
    for name, values in rows:
        print(f"  {name:36}" + "".join(f"{v:>18}" for v in values))
    print(f"  written to {out}/comparison.json")
