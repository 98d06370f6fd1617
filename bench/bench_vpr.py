"""Decentralized place recognition from full-image descriptors (issue 13): the paper's Figs. 6
and 7 on the office world, the re-balancing, the quantised codes and the byte model.

    python bench/bench_vpr.py --out bench/results/vpr.json

Runs :func:`swarmrec.vpr.evaluation.main` (every run's descriptors, centres and assignment
go to ``--work``, default ``runs/vpr``), copies its figures to ``docs/figures/vpr_fig6.png``
and ``docs/figures/vpr_fig7.png`` (docs/vpr.md shows them), and times the pieces a robot
runs: the descriptor model per frame, routing, and an owner's query-then-store with a few
thousand entries. Baseline, measured in the same run: the centralized search on the same
descriptors (relative AUC is over it) and the paper's random assignment (the balance is
compared with it).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from swarmrec.vpr.clusters import Router, random_assignment, train_centres
from swarmrec.vpr.data import render_world
from swarmrec.vpr.evaluation import EvaluationSettings, main
from swarmrec.vpr.index import OwnerIndex
from swarmrec.vpr.model import DescriptorModel

REPO = Path(__file__).resolve().parents[1]
FIGURES = REPO / "docs" / "figures"


def _percentiles(seconds: list[float]) -> dict[str, float]:
    ms = 1000 * np.asarray(seconds)
    return {"p50_ms": float(np.percentile(ms, 50)), "p99_ms": float(np.percentile(ms, 99))}


def timings(descriptors: np.ndarray, other: np.ndarray) -> dict[str, Any]:
    """What one robot pays per frame: describing it, routing it, an owner answering it."""
    model = DescriptorModel(intra_op_threads=1)
    world = render_world(20_261_124, 600, 4, vary=False)
    model.describe(world.images[:4])  # warm up onnxruntime
    per_frame = []
    for image in world.images[:100]:
        t0 = time.perf_counter()
        model.describe(image)
        per_frame.append(time.perf_counter() - t0)
    router = Router(train_centres(other, 20, 0), random_assignment(20, 1, 0))
    routes = []
    for x in descriptors[:500]:
        t0 = time.perf_counter()
        router.route(x)
        routes.append(time.perf_counter() - t0)
    index = OwnerIndex(descriptors.shape[1])
    queries = []
    for i, x in enumerate(descriptors):
        t0 = time.perf_counter()
        index.query_then_store(x, i % 20, i)
        queries.append(time.perf_counter() - t0)
    return {
        "describe_one_frame_1_thread": _percentiles(per_frame),
        "route_one_descriptor_k20": _percentiles(routes),
        "query_then_store": {"entries_at_end": len(index), **_percentiles(queries[-500:])},
    }


def main_bench(out: Path, work: Path, runs: int) -> dict[str, Any]:
    settings = EvaluationSettings(out=work, runs=runs)
    started = time.perf_counter()
    summary = main(settings)
    FIGURES.mkdir(parents=True, exist_ok=True)
    for name in ("fig6", "fig7"):
        shutil.copyfile(work / f"{name}.png", FIGURES / f"vpr_{name}.png")
    with np.load(work / "descriptors.npz") as data:
        timing = timings(data["deployment"], data["other"])
    result = {
        "what": "issue 13: decentralized place recognition from full-image descriptors, office world",
        "settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(settings).items()},
        **summary.to_json(),
        "timings": timing,
        "seconds": time.perf_counter() - started,
        "machine": {
            "platform": platform.platform(),
            "python": platform.python_version(),
            "cpus": os.cpu_count(),
        },
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1) + "\n")
    return result


def _line(result: dict[str, Any]) -> str:
    fig6 = {row["n_robots"]: row for row in result["fig6"]}
    balance = result["balance"]
    one = balance["one_cluster_per_robot"]
    return (
        f"relative AUC n={min(fig6)} {fig6[min(fig6)]['relative_auc_mean']:.3f}, "
        f"n={max(fig6)} {fig6[max(fig6)]['relative_auc_mean']:.3f}; "
        f"20 robots, 1 cluster each: balance {one['worst_balance_ratio_mean']:.2f}, "
        f"re-balanced: {balance['worst_balance_ratio_mean']:.2f} at relative AUC "
        f"{balance['relative_auc_mean']:.3f} (vs {one['relative_auc_mean']:.3f})"
    )


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "vpr.json")
    parser.add_argument("--work", type=Path, default=REPO / "runs" / "vpr", help="the evaluation's files")
    parser.add_argument("--runs", type=int, default=10, help="seeds per configuration")
    args = parser.parse_args()
    print(_line(main_bench(args.out, args.work, args.runs)))
