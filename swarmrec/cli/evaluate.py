"""``swarmrec evaluate``: score a dataset offline as the constellation paper did."""

from __future__ import annotations

import argparse
from pathlib import Path

from swarmrec.cli.common import Subparsers, add_dataset_flags
from swarmrec.evaluation.offline import EvaluationSettings
from swarmrec.evaluation.offline import main as evaluate

__all__ = ["add", "run"]


def add(sub: Subparsers) -> None:
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
    add_dataset_flags(p)
    p.add_argument(
        "--gt-rules",
        choices=["none", "tum-fr3-office"],
        default="none",
        help="hand-made ground-truth rules of the published fr3/long_office_household evaluation",
    )
    p.add_argument(
        "--mode", choices=["centralized", "decentralized", "both"], default="both", help="(default both)"
    )
    p.add_argument("--robots", type=int, default=10, help="robots of the decentralized mode (default 10)")
    p.add_argument("--out", type=Path, default=Path("runs/evaluate"), help="output folder")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
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
    ds = summary.dataset
    print(f"dataset {ds.name}: {ds.frames} frames, {ds.ignored_frames} with too few objects")
    for name, result in summary.results.items():
        auc = f"AUC {result.auc:.4f}" if result.auc is not None else "AUC n/a (no ground truth)"
        print(f"  {name:<20} {auc}, {result.positive_pairs} pairs scored > 0")
    if summary.bandwidth is not None:
        bw = summary.bandwidth
        print(
            f"  byte model: {bw.paper_byte_model_per_query['total']:.1f} B per query; "
            f"busiest range holder / mean = {bw.holder_load['balance_ratio']:.2f}"
        )
    timings = ", ".join(f"{k[:-2]} {v:.2f} s" for k, v in summary.timings.items())
    print(f"  time: {timings}")
    print(f"  written to {settings.out}/ (summary.json, scores_*.npz, best_matches_*.csv, *.png)")
    return 0
