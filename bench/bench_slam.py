"""Multi-robot object-based SLAM benchmark: the paper's Tables 1-2 on simulated worlds, and beyond.

    python bench/bench_slam.py --out bench/results/slam.json --plots docs/figures

On the simulated "25 chairs" and "house" worlds (:mod:`swarmrec.slam.scenarios`),
averaged over ``--runs`` seeds (the paper: 10 Monte Carlo runs):

- Table 1: 2 to 6 robots at the default noise (5 deg, 0.1 m);
- Table 2: 6 robots at the paper's four noise levels;

each row with the paper's columns, for the paper's method (plain Gauss-Seidel,
one linearisation) at eta 0.1 and 0.01: iterations (rotation + pose stages),
cost, gtsam Gauss-Newton's cost, ATE* and ARE* of poses and objects against
Gauss-Newton at eta 0.1; and the same for swarmrec's defaults (SOR gamma 1.9,
eta 0.01, one relinearisation). Also:

- the blocks-world data sets (../shared/data/dgs_blocks_world), both settings;
- over-relaxation and ordering: iterations and ATE* for gamma in 1 .. 1.95 and
  the three orderings, and a convergence trace (ATE* per iteration, GS vs SOR);
- robustness: wrong associations injected, PCM's and GNC's precision and recall,
  and ATE* of the distributed solve with all separators, after PCM, and GNC's,
  against Gauss-Newton on the graph without the wrong ones;
- Table 3: per-robot memory and rendezvous bandwidth of a dense point-cloud map
  against the object map, from frames of the office renderer;
- floats and bytes per link by the 9/6-float model.

Figures (``--plots``): Fig. 4-style maps (trajectories and objects, distributed
against centralized), the convergence trace, and the robustness curves.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from swarmrec.slam.centralized import solve_centralized, solve_two_stage
from swarmrec.slam.dgs import DgsSettings, DistributedResult, run_dgs
from swarmrec.slam.g2o import read_robot_folder
from swarmrec.slam.graph import PoseGraph, is_landmark_key
from swarmrec.slam.lie import Pose
from swarmrec.slam.metrics import accuracy, ate_star
from swarmrec.slam.robust import gnc, pcm
from swarmrec.slam.scenarios import PAPER_NOISE_LEVELS, Scenario, ScenarioSettings, generate_scenario
from swarmrec.synthetic.office import generate_office
from swarmrec.synthetic.render import SequenceRenderer

REPO = Path(__file__).resolve().parents[1]
BLOCKS_WORLD = REPO.parent / "shared" / "data" / "dgs_blocks_world"
PAPER_01 = DgsSettings.paper(1e-1)
PAPER_001 = DgsSettings.paper(1e-2)
DEFAULT = DgsSettings()
COLOURS = plt.get_cmap("tab10")


def _mean(values: Sequence[float]) -> float:
    finite = [v for v in values if math.isfinite(v)]
    return float(np.mean(finite)) if finite else math.nan


def _iterations(result: DistributedResult) -> int:
    return result.rotation_iterations + sum(result.pose_iterations)


def run_case(settings: ScenarioSettings) -> dict[str, Any]:
    """One scenario: Gauss-Newton, the paper's method at eta 0.1 and 0.01, swarmrec's defaults."""
    scenario = generate_scenario(settings)
    graph = scenario.graph
    t0 = time.perf_counter()
    gn = solve_centralized(graph)
    row: dict[str, Any] = {
        "gn_cost": gn.cost,
        "gn_s": time.perf_counter() - t0,
        "vertices": len(graph.poses),
        "edges": len(graph.edges),
        "separators": len(graph.separators()),
    }
    for name, dgs in (("paper_eta_0.1", PAPER_01), ("paper_eta_0.01", PAPER_001), ("swarmrec", DEFAULT)):
        t0 = time.perf_counter()
        result = run_dgs(graph, dgs)
        acc = accuracy(graph, result.poses, gn.poses)
        row[name] = {
            "iterations": _iterations(result),
            "rotation_iterations": result.rotation_iterations,
            "pose_iterations": list(result.pose_iterations),
            "cost": acc.cost,
            "ate_poses": acc.ate_poses,
            "ate_landmarks": acc.ate_landmarks,
            "are_poses_deg": acc.are_poses_deg,
            "are_landmarks_deg": acc.are_landmarks_deg,
            "floats": result.total_floats,
            "links": len(result.floats_per_link()),
            "seconds": time.perf_counter() - t0,
        }
    return row


def average(rows: Sequence[dict[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {
        k: _mean([r[k] for r in rows]) for k in ("gn_cost", "vertices", "edges", "separators")
    }
    for name in ("paper_eta_0.1", "paper_eta_0.01", "swarmrec"):
        keys = [k for k, v in rows[0][name].items() if isinstance(v, int | float)]
        out[name] = {k: _mean([r[name][k] for r in rows]) for k in keys}
    return out


def table_rows(runs: int, progress: Callable[[str], None]) -> dict[str, Any]:
    tables: dict[str, Any] = {"table1": {}, "table2": {}}
    for world in ("chairs", "house"):
        tables["table1"][world] = {}
        for robots in range(2, 7):
            rows = [run_case(ScenarioSettings(world=world, robots=robots, seed=s)) for s in range(runs)]
            tables["table1"][world][str(robots)] = average(rows)
            progress(f"table 1 {world} {robots} robots")
        tables["table2"][world] = {}
        for sigma_r, sigma_t in PAPER_NOISE_LEVELS:
            rows = [
                run_case(
                    ScenarioSettings(
                        world=world, robots=6, seed=s, sigma_rotation_deg=sigma_r, sigma_translation=sigma_t
                    )
                )
                for s in range(runs)
            ]
            tables["table2"][world][f"{sigma_r:g}deg_{sigma_t:g}m"] = average(rows)
            progress(f"table 2 {world} {sigma_r} deg {sigma_t} m")
    return tables


def blocks_world() -> dict[str, Any]:
    out: dict[str, Any] = {}
    for name in ("2robots", "4robots"):
        folder = BLOCKS_WORLD / name
        if not folder.is_dir():
            out[name] = "not found"
            continue
        graph = read_robot_folder(folder).graph
        gn = solve_centralized(graph)
        two_stage = solve_two_stage(graph).poses
        entry: dict[str, Any] = {
            "gn_cost": gn.cost,
            "two_stage_ate_vs_gn": ate_star(two_stage, gn.poses, graph.keys),
        }
        for label, dgs in (
            ("paper_eta_0.1", PAPER_01),
            ("paper_eta_0.001", DgsSettings.paper(1e-3)),
            ("swarmrec", DEFAULT),
        ):
            result = run_dgs(graph, dgs)
            acc = accuracy(graph, result.poses, gn.poses)
            entry[label] = {
                "rotation_iterations": result.rotation_iterations,
                "pose_iterations": list(result.pose_iterations),
                "cost": acc.cost,
                "ate_vs_gn": acc.ate_poses,
                "are_vs_gn_deg": acc.are_poses_deg,
                "ate_vs_two_stage": ate_star(result.poses, two_stage, graph.keys),
                "floats": result.total_floats,
                "floats_per_link": {f"{s}->{r}": n for (s, r), n in result.floats_per_link().items()},
            }
        out[name] = entry
    return out


TARGET_ATE = 0.05  # metres: "equal accuracy" for the iteration comparison
TRACE_ETA = 1e-3
TRACE_MAX = 300


def _iterations_to_target(
    graph: PoseGraph, reference: dict[int, Pose], settings: DgsSettings
) -> tuple[int | None, list[int], list[float]]:
    """First iteration (rotation stage counted) whose pose-stage estimate is within TARGET_ATE of GN."""
    traced = DgsSettings(
        settings.mode,
        settings.order,
        settings.gamma,
        TRACE_ETA,
        TRACE_ETA,
        TRACE_MAX,
        settings.pose_linearisations,
    )
    result = run_dgs(graph, traced, trace=True)
    xs, ys = [], []
    for n, entry in enumerate(result.trace, start=1):
        if entry.stage == "pose":
            xs.append(n)
            ys.append(ate_star(entry.poses, reference, graph.keys))
    first = next((x for x, y in zip(xs, ys, strict=True) if y < TARGET_ATE), None)
    return first, xs, ys


def improvement(runs: int, plots: Path | None) -> dict[str, Any]:
    """Over-relaxation and orderings against plain Gauss-Seidel.

    Two measures per variant: (a) at its own stopping rule (eta 0.01, two
    linearisations), iterations and ATE* against Gauss-Newton; (b) at equal
    accuracy: the first iteration whose estimate is within 5 cm (ATE*) of
    Gauss-Newton, every stage run to eta 1e-3 or 300 iterations (None: never).
    """
    graphs: dict[str, list[PoseGraph]] = {
        "chairs_6": [
            generate_scenario(ScenarioSettings(world="chairs", robots=6, seed=s)).graph for s in range(runs)
        ],
        "house_6": [
            generate_scenario(ScenarioSettings(world="house", robots=6, seed=s)).graph for s in range(runs)
        ],
    }
    for name in ("2robots", "4robots"):
        if (BLOCKS_WORLD / name).is_dir():
            graphs[f"blocks_{name}"] = [read_robot_folder(BLOCKS_WORLD / name).graph]
    references = {k: [solve_centralized(g).poses for g in gs] for k, gs in graphs.items()}
    variants: list[tuple[str, DgsSettings]] = [
        (f"gamma_{g:g}", DgsSettings(gamma=g)) for g in (1.0, 1.5, 1.8, 1.9, 1.95)
    ]
    variants += [
        ("order_greedy_gamma_1.9", DgsSettings(order="greedy")),
        ("order_natural_gamma_1.9", DgsSettings(order="natural")),
        ("order_natural_gamma_1", DgsSettings(gamma=1.0, order="natural")),
        ("jacobi_gamma_1", DgsSettings(mode="jacobi")),
    ]
    out: dict[str, Any] = {
        "target_ate_m": TARGET_ATE,
        "trace_eta": TRACE_ETA,
        "trace_max_iterations": TRACE_MAX,
    }
    curves: dict[str, tuple[list[int], list[float]]] = {}
    for name, gs in graphs.items():
        out[name] = {}
        for label, dgs in variants:
            results = [run_dgs(g, dgs) for g in gs]
            to_target = []
            for g, ref in zip(gs, references[name], strict=True):
                first, xs, ys = _iterations_to_target(g, ref, dgs)
                to_target.append(first)
                if name == "chairs_6" and label in ("gamma_1", "gamma_1.9") and g is gs[0]:
                    curves[label] = (xs, ys)
            reached = [t for t in to_target if t is not None]
            out[name][label] = {
                "iterations": _mean([_iterations(r) for r in results]),
                "ate_vs_gn": _mean(
                    [
                        ate_star(r.poses, ref, g.keys)
                        for r, ref, g in zip(results, references[name], gs, strict=True)
                    ]
                ),
                "floats": _mean([r.total_floats for r in results]),
                "iterations_to_5cm": _mean(reached) if reached else None,
                "reached_5cm": f"{len(reached)}/{len(to_target)}",
            }
    if plots is not None and curves:
        fig, ax = plt.subplots(figsize=(6, 4))
        for label, (xs, ys) in curves.items():
            ax.semilogy(xs, ys, label=label.replace("_", " "))
        ax.axhline(TARGET_ATE, color="0.5", ls=":", lw=1)
        ax.set_xlabel("iteration (rotation stage first, then the pose stages)")
        ax.set_ylabel("ATE* against Gauss-Newton (m)")
        ax.set_title("25 chairs, 6 robots: pose-stage estimates")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
        fig.tight_layout()
        fig.savefig(plots / "slam-convergence.png", dpi=120)
        plt.close(fig)
    return out


def robustness(runs: int, plots: Path | None) -> dict[str, Any]:
    out: dict[str, Any] = {}
    counts = (0, 2, 5, 10, 20)
    for world in ("chairs", "house"):
        out[world] = {}
        for outliers in counts:
            rows = []
            for seed in range(runs):
                scenario = generate_scenario(
                    ScenarioSettings(world=world, robots=4, seed=seed, outliers=outliers)
                )
                rows.append(_robust_case(scenario))
            out[world][str(outliers)] = {k: _mean([r[k] for r in rows]) for k in rows[0]}
    if plots is not None:
        fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
        for ax, world in zip(axes, ("chairs", "house"), strict=True):
            for key, label in (
                ("ate_all", "DGS, all separators"),
                ("ate_pcm", "DGS after PCM"),
                ("ate_gnc", "gtsam GNC (centralized)"),
            ):
                ax.semilogy(counts, [out[world][str(c)][key] for c in counts], marker="o", label=label)
            ax.set_title(f"{world}, 4 robots")
            ax.set_xlabel("wrong associations injected")
            ax.grid(True, which="both", alpha=0.3)
        axes[0].set_ylabel("ATE* against GN without them (m)")
        axes[0].legend()
        fig.tight_layout()
        fig.savefig(plots / "slam-robustness.png", dpi=120)
        plt.close(fig)
    return out


def _robust_case(scenario: Scenario) -> dict[str, float]:
    graph = scenario.graph
    wrong = {s.edge.keys for s in scenario.separators if not s.correct}
    clean = graph.with_edges(e for e in graph.edges if e.keys not in wrong)
    reference = solve_centralized(clean).poses

    def precision_recall(rejected: set[tuple[int, int]]) -> tuple[float, float]:
        if not wrong:
            return (math.nan, math.nan) if not rejected else (0.0, math.nan)
        hit = len(rejected & wrong)
        return (hit / len(rejected) if rejected else math.nan, hit / len(wrong))

    pcm_result = pcm(graph)
    gnc_result = gnc(graph)
    p_pcm, r_pcm = precision_recall({e.keys for e in pcm_result.rejected})
    p_gnc, r_gnc = precision_recall({e.keys for e in gnc_result.rejected})
    return {
        "separators": float(len(scenario.separators)),
        "pcm_precision": p_pcm,
        "pcm_recall": r_pcm,
        "gnc_precision": p_gnc,
        "gnc_recall": r_gnc,
        "pcm_rejected_correct": float(len({e.keys for e in pcm_result.rejected} - wrong)),
        "ate_all": ate_star(run_dgs(graph, DEFAULT).poses, reference, graph.keys),
        "ate_pcm": ate_star(run_dgs(pcm_result.graph(graph), DEFAULT).poses, reference, graph.keys),
        "ate_gnc": ate_star(gnc_result.poses, reference, graph.keys),
    }


def figure_maps(plots: Path) -> list[str]:
    """Fig. 4-style: trajectories and objects, centralized GN against the distributed estimates."""
    written = []
    for world in ("chairs", "house"):
        scenario = generate_scenario(ScenarioSettings(world=world, robots=6, seed=0))
        graph = scenario.graph
        estimates = {
            "centralized Gauss-Newton": solve_centralized(graph).poses,
            "distributed, paper (eta 0.1)": run_dgs(graph, PAPER_01).poses,
            "distributed, swarmrec defaults": run_dgs(graph, DEFAULT).poses,
        }
        fig, axes = plt.subplots(1, 3, figsize=(15, 5), sharex=True, sharey=True)
        for ax, (title, poses) in zip(axes, estimates.items(), strict=True):
            _draw(ax, graph, poses, scenario)
            ax.set_title(title)
        fig.suptitle(f"{world}: 6 robots, noise 5 deg / 0.1 m (x: true objects)")
        fig.tight_layout()
        path = plots / f"slam-fig4-{world}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(str(path.relative_to(REPO)) if path.is_relative_to(REPO) else str(path))
    return written


def _draw(ax: Any, graph: PoseGraph, poses: dict[int, Pose], scenario: Scenario) -> None:
    truth = np.array([o.pose.translation[:2] for o in scenario.objects])
    ax.scatter(truth[:, 0], truth[:, 1], marker="x", c="0.6", s=30)
    for robot in graph.robots:
        keys = graph.robot_keys(robot)
        path = np.array([poses[k].translation[:2] for k in keys if not is_landmark_key(k)])
        objects = np.array([poses[k].translation[:2] for k in keys if is_landmark_key(k)])
        ax.plot(path[:, 0], path[:, 1], "-", color=COLOURS(robot), lw=1.2)
        if len(objects):
            ax.scatter(objects[:, 0], objects[:, 1], color=COLOURS(robot), s=12)
    ax.set_aspect("equal")
    ax.grid(True, alpha=0.3)


def table3(frames: int) -> dict[str, Any]:
    """Memory and bandwidth of a dense point-cloud map against the object map (the paper's Table 3).

    From ``frames`` frames rendered along the office sequence: K = valid depth
    pixels per frame, P = points of an object "model" (its largest visible pixel
    count over the frames rendered), for 10 robots splitting the 2500 frames.
    C = 32 B per point (PCL's PointXYZRGB, the paper's toolchain); an object on
    the wire is L = 29 B (1 B label + 7 float32 pose); each robot meets each other once.
    """
    ds = generate_office()
    renderer = SequenceRenderer(ds)
    robots = 10
    n_frames = len(renderer)
    sample = np.linspace(0, n_frames - 1, frames).astype(int)
    valid, model_points = [], {}
    for i in sample:
        frame = renderer.render(int(i))
        valid.append(int((frame.depth > 0).sum()))
        for obj, pixels in zip(frame.objects, frame.pixels, strict=True):
            model_points[int(obj)] = max(model_points.get(int(obj), 0), int(pixels))
    k = float(np.mean(valid))
    p = float(np.mean(list(model_points.values())))
    c, label_pose = 32, 29
    per_robot = n_frames // robots
    objects_per_robot = _mean(
        [
            len(set(np.concatenate(ds.visible[r * per_robot : (r + 1) * per_robot]).tolist()))
            for r in range(robots)
        ]
    )
    meetings = robots - 1
    return {
        "frames_rendered": frames,
        "K_points_per_frame": k,
        "P_points_per_object_model": p,
        "C_bytes_per_point": c,
        "L_bytes_per_object": label_pose,
        "frames_per_robot": per_robot,
        "objects_per_robot": objects_per_robot,
        "rendezvous_per_robot": meetings,
        "memory_pcd_MB": per_robot * k * c / 1e6,
        "memory_obj_MB": objects_per_robot * p * c / 1e6,
        "bandwidth_pcd_MB": meetings * k * c / 1e6,
        "bandwidth_obj_MB": objects_per_robot * label_pose / 1e6,
    }


def _finite(value: Any) -> Any:
    """NaN (a precision with nothing rejected, no objects) as null, so the file is strict JSON."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    return value


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "slam.json")
    parser.add_argument("--plots", type=Path, default=None, help="folder for the figures")
    parser.add_argument("--runs", type=int, default=10, help="Monte Carlo runs per table row (paper: 10)")
    parser.add_argument("--table3-frames", type=int, default=40, help="frames rendered for Table 3 (0: skip)")
    args = parser.parse_args()
    if args.plots is not None:
        args.plots.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()

    def progress(text: str) -> None:
        print(f"[{time.perf_counter() - start:7.1f} s] {text}", flush=True)

    results: dict[str, Any] = {
        "machine": {
            "python": platform.python_version(),
            "processor": platform.machine(),
            "cpus": os.cpu_count(),
        },
        "runs": args.runs,
        "settings": {
            "paper": "Gauss-Seidel, gamma 1, one linearisation, eta 0.1 or 0.01",
            "swarmrec": "Gauss-Seidel SOR gamma 1.9, eta 0.01, two linearisations",
        },
    }
    results["blocks_world"] = blocks_world()
    progress("blocks world")
    results.update(table_rows(args.runs, progress))
    results["improvement"] = improvement(min(args.runs, 3), args.plots)
    progress("over-relaxation and ordering")
    results["robustness"] = robustness(min(args.runs, 5), args.plots)
    progress("robustness")
    if args.plots is not None:
        results["figures"] = figure_maps(args.plots)
        progress("figures")
    if args.table3_frames > 0:
        results["table3"] = table3(args.table3_frames)
        progress("table 3")
    results["seconds"] = time.perf_counter() - start
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(_finite(results), indent=1, default=float, allow_nan=False) + "\n")
    print(f"written {args.out}")


if __name__ == "__main__":
    main()
