"""Landmark simulation benchmark: the WNBC paper's experiment (118 street configurations
x 10 robots, the paper's four lambdas and the adaptive law) through real processes over
a zenoh router, once with the views the CNN was trained on and once with harsh views.

    python bench/bench_landmarks.py --out bench/results/landmarks.json

For each view preset it records the recognition rate after k incorporated messages per
law, bytes per round and the checks of ``swarmrec landmarks``, and copies the three
figures to ``docs/figures/landmarks-<preset>-*.png`` (docs/landmarks.md shows them).

Baseline, measured in the same run on the same configurations and views: the core's
in-process simulation (:func:`swarmrec.fusion.simulate_flooding` in synchronous steps,
then :class:`swarmrec.fusion.FusionState` per robot and law). ``per_round_ratio`` is the
swarm's wall time per round over the core's; the rates of both are written, so how much
zenoh's delivery order (not the graph's breadth-first order) moves the results shows too.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import platform
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from swarmrec.deployments.local import LocalDeployment
from swarmrec.experiments.landmarks import DEFAULT_LAWS, VIEW_PRESETS, LandmarkSettings, main
from swarmrec.experiments.landmarks.simulation import render_views
from swarmrec.fusion import FusionState, generate_configurations, simulate_flooding
from swarmrec.fusion.classifier import LandmarkClassifier

REPO = Path(__file__).resolve().parents[1]
FIGURES = REPO / "docs" / "figures"


def core_rates(settings: LandmarkSettings) -> tuple[dict[str, list[float]], float]:
    """The same experiment in one process with the core alone: rates per law, and seconds."""
    t0 = time.perf_counter()
    configs = generate_configurations(
        settings.configurations, seed=settings.seed, settings=settings.street_settings()
    )
    views = render_views(configs, settings.seed, VIEW_PRESETS[settings.views])
    classifier = LandmarkClassifier()
    n = settings.robots
    correct = {law.key: np.zeros(n) for law in settings.laws}
    for config, images in zip(configs, views, strict=True):
        # float32 as on the wire, so both runs fuse the same numbers.
        probs = classifier.classify(images).astype(np.float32).astype(np.float64)
        probs /= probs.sum(axis=1, keepdims=True)
        flood = simulate_flooding(config.adjacency, probs, config.yaws)
        for robot, law in itertools.product(range(n), settings.laws):
            state = FusionState(probs[robot], float(config.yaws[robot]), law.law(), own_id=robot)
            for heard in flood.heard[robot]:
                state.incorporate(heard.origin, heard.likelihood, heard.hops, heard.yaw)
            for k in range(n):
                correct[law.key][k] += state.decision_after(k) == config.landmarks[robot]
    total = settings.configurations * n
    return {k: [round(float(v) / total, 4) for v in c] for k, c in correct.items()}, time.perf_counter() - t0


def run_preset(views: str, configurations: int, work: Path) -> dict[str, Any]:
    settings = LandmarkSettings(out=work / views, configurations=configurations, views=views, progress=False)
    baseline, core_s = core_rates(settings)
    summary = main(settings, LocalDeployment.for_run(settings.out)).to_dict()
    rounds = configurations * len(DEFAULT_LAWS)
    swarm_s = summary["timings_s"]["rounds_s"]
    FIGURES.mkdir(parents=True, exist_ok=True)
    for name in ("fig3_recognition", "fig4_configurations", "fig5_confusion"):
        shutil.copy(settings.out / f"{name}.png", FIGURES / f"landmarks-{views}-{name}.png")
    return {
        "recognition": {k: v["rate"] for k, v in summary["recognition"].items()},
        "core_recognition": baseline,
        "bytes": {k: v for k, v in summary["bytes"].items() if k != "note"},
        "checks": summary["checks"],
        "timings_s": summary["timings_s"],
        "swarm_ms_per_round": round(1000 * swarm_s / rounds, 2),
        "core_ms_per_round": round(1000 * core_s / rounds, 2),
        "per_round_ratio": round(swarm_s / core_s, 2),
    }


def main_cli() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "landmarks.json")
    p.add_argument("--configurations", type=int, default=118)
    a = p.parse_args()
    results: dict[str, Any] = {
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
        "configurations": a.configurations,
        "robots": 10,
        "laws": [law.key for law in DEFAULT_LAWS],
    }
    with tempfile.TemporaryDirectory() as tmp:
        for views in ("nominal", "harsh"):
            print(f"{views} views ...", flush=True)
            results[views] = run_preset(views, a.configurations, Path(tmp))
            r = results[views]
            print(
                f"  {r['swarm_ms_per_round']} ms per round over zenoh, {r['per_round_ratio']}x the core; "
                + "; ".join(
                    f"{k} {100 * v[0]:.1f} -> {100 * v[-1]:.1f} %" for k, v in r["recognition"].items()
                ),
                flush=True,
            )
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(results, indent=1) + "\n", encoding="utf-8")
    print(f"written {a.out}")


if __name__ == "__main__":
    main_cli()
