"""The distributed Gauss-Seidel as slam services: time and bytes per link per iteration, measured.

    python bench/bench_slam_live.py --out bench/results/slam_live.json

Cases: the shared blocks world (2 and 4 robots, from the public implementation) and the
simulated 25-chairs and house worlds with 4 and 6 robots (seed 0), swarmrec's default
solver. Each runs through ``swarmrec slam run``'s pipeline: a router and one slam process
per robot on this machine, mutual TLS, the robots taking their turns on their own.

Baseline, measured in the same run on the same graph: :func:`swarmrec.slam.dgs.run_dgs`,
every agent in this one process (``per_iteration_ratio`` is the live solve's wall time per
iteration over it). Bytes: each link's SlamStep payloads as the sender counted them in
Prometheus, per iteration, against the 9/6-float model (8 B a float); the check says
whether every message, report and estimate equalled the in-process solve bit for bit.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

from swarmrec.deployments.local import LocalDeployment
from swarmrec.experiments.slam import LiveSlamSettings, main
from swarmrec.slam import DgsSettings, ScenarioSettings, generate_scenario, read_robot_folder, run_dgs

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("SWARMREC_SHARED_DATA", REPO.parent / "shared" / "data"))


def case(name: str, settings: LiveSlamSettings) -> dict[str, Any]:
    if settings.folder is not None:
        graph = read_robot_folder(settings.folder).graph
    else:
        graph = generate_scenario(
            ScenarioSettings(world=settings.world, robots=settings.robots, seed=0)
        ).graph
    t0 = time.perf_counter()
    reference = run_dgs(graph, DgsSettings())
    in_process = time.perf_counter() - t0
    summary = main(settings, LocalDeployment.for_run(settings.out))
    iterations = sum(n for _, _, n, _ in summary.stages)
    live = summary.timings["solve_s"]
    return {
        "case": name,
        "robots": summary.robots,
        "vertices": summary.vertices,
        "separators": summary.separators,
        "outcome": summary.outcome,
        "stages": summary.stages,
        "iterations": iterations,
        "identical_to_in_process": summary.check.identical if summary.check else None,
        "live_solve_s": live,
        "in_process_s": in_process,
        "per_iteration_ms": 1e3 * live / iterations,
        "per_iteration_ratio": (live / iterations) / (in_process / reference.total_iterations),
        "ate_vs_gtsam_m": summary.ate_poses_m,
        "ate_vs_truth_m": summary.ate_vs_truth_m,
        "bytes_per_iteration": summary.bytes_per_iteration,
        "links": [vars(link) for link in summary.links],
        "swarm_bytes": summary.swarm_bytes,
        "start_s": summary.timings["start_s"],
    }


def main_bench() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "slam_live.json")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="bench-slam-live-"))
    rows = []
    try:
        cases: list[tuple[str, dict[str, Any]]] = [
            (f"blocks_{n}robots", {"folder": SHARED / "dgs_blocks_world" / f"{n}robots"}) for n in (2, 4)
        ]
        cases += [(f"{w}_{n}", {"world": w, "robots": n}) for w in ("chairs", "house") for n in (4, 6)]
        for name, fields in cases:
            settings = LiveSlamSettings(out=work / name, progress=False, **fields)
            rows.append(case(name, settings))
            r = rows[-1]
            print(
                f"{name}: {r['iterations']} iterations, live {r['per_iteration_ms']:.1f} ms/iteration "
                f"(x{r['per_iteration_ratio']:.1f} in-process), identical {r['identical_to_in_process']}, "
                + ", ".join(
                    f"{st} {v['measured_bytes']:.0f} B vs {v['model_bytes']:.0f} B"
                    for st, v in r["bytes_per_iteration"].items()
                ),
                flush=True,
            )
    finally:
        shutil.rmtree(work, ignore_errors=True)
    result = {
        "machine": {
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
            "platform": platform.platform(),
        },
        "cases": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main_bench()
