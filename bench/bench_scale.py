"""Scale benchmark: swarms of 10 to 100 robots of the synthetic world on this machine.

    python bench/bench_scale.py --out bench/results/scale.json --plot docs/figures/scale.png

Each swarm replays the synthetic office (50 frames per robot, so 100 robots play 5000
frames) in lock-step, many robots per process (``--hosting robots:K``: every robot
keeps its own services, endpoints, liveliness and metrics; they share a zenoh session
and an interpreter), and checks its pair scores against the offline evaluation. For
each size it writes the wall time (start, replay), the memory of the processes (their
resident sets at the last step, children included: compiled hosts and shard
coordinators, in total and per robot), bytes per query measured on
the wire, the worst shard balance, whether the scores are identical, and how the processes
stopped (seconds after SIGTERM, exit codes).

Baseline, in the same run: the 10-robot swarm with one process per service (41
processes), the deployment the project started from: the ratio of its memory per
robot and wall time to the hosted swarm's of the same size.

Rebalancing is off by default here (``--rebalance-target 0`` turns it on at the
swarm's default): this benchmark measures what hosting many robots costs.
``bench/results/scale_rebalancing_on_100.json`` is the 100-robot swarm with it on;
docs/elastic-index.md ("Limits, honestly") has its figures.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import tempfile
import time
from pathlib import Path
from typing import Any

from lockstep_load import Pacer, shard_loads

from swarmrec.core.placement import balance_ratio
from swarmrec.deployments.base import Deployment
from swarmrec.deployments.local import LocalDeployment, LocalSettings
from swarmrec.evaluation.source import DatasetSource
from swarmrec.experiments.places import PlacesSettings, main
from swarmrec.services.settings import IndexSettings

REPO = Path(__file__).resolve().parents[1]
FRAMES_PER_ROBOT = 50


def rss_mb(pid: int) -> float:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return 0.0


def tree(pid: int) -> list[int]:
    """``pid`` and its descendants: a service's compiled host and its coordinator are
    processes of their own under the one the deployment started."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        for task in Path(f"/proc/{p}/task").glob("*/children"):
            with contextlib.suppress(OSError):  # the process ended meanwhile
                todo.extend(int(c) for c in task.read_text().split())
    return out


def tree_rss_mb(pid: int) -> float:
    return sum(rss_mb(p) for p in tree(pid))


def _versions_after_first_rebalance(history: list[dict[str, Any]]) -> int | None:
    """Placements published after the first rebalancing's (None: it never rebalanced)."""
    first = next((h["version"] for h in history if h["reason"] == "rebalance"), None)
    return None if first is None else sum(1 for h in history if h["version"] > first)


def run(
    robots: int, hosting: str, work: Path, rebalance_target: float, rule: str = "pack", step_s: float = 0.0
) -> dict[str, Any]:
    held: list[LocalDeployment] = []
    memory: dict[str, float] = {}
    steps = FRAMES_PER_ROBOT

    def hook(d: Deployment) -> None:
        assert isinstance(d, LocalDeployment)
        held.append(d)

    pace = Pacer(step_s)

    def on_step(t: int) -> None:
        pace()
        if t == steps - 1:  # the last step: every process holds all it will hold
            d = held[0]
            procs = [sp for sp in d.procs if sp.proc.poll() is None]
            memory["services_mb"] = sum(tree_rss_mb(sp.proc.pid) for sp in procs)
            memory["router_mb"] = rss_mb(d.router.proc.pid) if d.router else 0.0
            memory["processes"] = sum(len(tree(sp.proc.pid)) for sp in procs) + 1

    name = f"{robots}-{hosting.replace(':', '-')}-{rule}-{rebalance_target:g}".replace(".", "_")
    settings = PlacesSettings(
        source=DatasetSource(frames=FRAMES_PER_ROBOT * robots),
        robots=robots,
        out=work / name,
        swarm=f"scale-{name}",
        request_timeout_s=30.0,
        # Ticks of 0.25 s: a lock-step replay here lasts 1 to 5 s, and with the default 1 s tick
        # the coordinator would see its load only when it is nearly over.
        index=IndexSettings(
            rebalance_target=rebalance_target,
            rebalance_rule=rule,  # type: ignore[arg-type]  # a str from RULES, checked by IndexSettings
            placement_tick_s=TICK_S,
        ),
        progress=False,
        plots=False,
    )
    t0 = time.perf_counter()
    s = main(
        settings,
        LocalDeployment.for_run(settings.out, LocalSettings(hosting=hosting)),
        swarm_hook=hook,
        on_step=on_step,
    )
    wall = time.perf_counter() - t0
    total = memory.get("services_mb", 0.0) + memory.get("router_mb", 0.0)
    history = s.index.history if s.index else []
    second = shard_loads(settings.out, robots, first_step=steps // 2)
    return {
        "robots": robots,
        "hosting": hosting,
        "rebalance_target": rebalance_target,
        "rebalance_rule": rule,
        "placement_tick_s": TICK_S,
        "step_s": step_s,
        "frames": s.dataset.frames,
        "processes": memory.get("processes"),
        "wall_s": wall,
        "start_s": s.timings.get("start_s"),
        "replay_s": s.timings.get("replay_s"),
        # How long the processes took to stop after SIGTERM, and whether each exited by itself
        # (0) or was killed after the deployment's 10 s (-9).
        "stop_s": s.timings.get("stop_s"),
        "exit_codes": s.exit_codes,
        "memory_total_mb": total,
        "memory_per_robot_mb": total / robots,
        "bytes_per_query": s.bytes.per_query,
        "balance_ratio": s.shard_load.balance_ratio,
        "loads": s.shard_load.partial_queries,
        # The second half of the run: the placement the coordinator settled on.
        "balance_ratio_second_half": balance_ratio(second),
        "loads_second_half": second,
        "group_queries": s.index.group_queries if s.index else [],
        "history": history,
        "versions_after_first_rebalance": _versions_after_first_rebalance(history),
        # The index at the end: placement version, the most replicas a group got, what
        # storing replicas and index control cost a query, and the store weight measured.
        "placement_version": s.index.version if s.index else None,
        "max_group_replicas": max((len(o) for o in s.index.owners), default=0) if s.index else None,
        "replication_bytes_per_query": s.bytes.replication_per_query,
        "index_control_bytes_per_query": s.bytes.index_control_per_query,
        # The budget: replica stores and index control over the two-step query's bytes.
        "replicas_and_control_over_query_bytes": (
            (s.bytes.replication_per_query + s.bytes.index_control_per_query) / s.bytes.per_query
            if s.bytes.per_query
            else None
        ),
        "store_weight": s.index.store_weight if s.index else None,
        "query_p50_ms": s.queries.latency_ms.get("p50"),
        # A lock-step step: from the step's start until every robot's query of it is answered.
        "step_p50_ms": s.queries.step_latency_ms.get("p50"),
        "missing_slots": s.queries.missing_slots,
        "identical_to_offline": s.offline_check.identical if s.offline_check else None,
    }


def write(path: Path, result: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=2) + "\n")


def plot(results: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    robots = [r["robots"] for r in results]
    fig, axes = plt.subplots(1, 4, figsize=(15, 3.4))
    panels = [
        ("wall_s", "wall time of the run (s)"),
        ("memory_per_robot_mb", "memory per robot (MB)"),
        ("bytes_per_query", "bytes between robots per query"),
        ("balance_ratio", "busiest shard / mean"),
    ]
    for ax, (key, title) in zip(axes, panels, strict=True):
        ax.plot(robots, [r[key] for r in results], "o-")
        ax.set_xlabel("robots")
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3)
    fig.suptitle(
        f"synthetic world, {FRAMES_PER_ROBOT} frames per robot, lock-step, robots hosted many to a process, "
        "two replicas a group, rebalancing off"
    )
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


#: The coordinator's tick in these runs (see run()).
TICK_S = 0.25
#: In ``--rules`` runs each lock-step step lasts at least this (robots at 5 frames a second):
#: the coordinator rebalances on the load it sees, and a replay that is over in a few seconds
#: measures mostly how long it took to see it.
STEP_S = 0.2

#: What each name of ``--rules`` runs: (rebalance_target, rebalance_rule).
RULES = {"off": (1000.0, "pack"), "greedy": (1.5, "greedy"), "pack": (IndexSettings.rebalance_target, "pack")}


def plot_rules(result: dict[str, Any], path: Path) -> None:
    """Busiest / mean and the index's bytes a query against the swarm's size, a line a rule."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 3.8))
    names = {"off": "no rebalancing", "greedy": "the rule before (greedy)", "pack": "the plan (default)"}
    for rule in ("off", "greedy", "pack"):
        runs = sorted((r for r in result["runs"] if r["rule"] == rule), key=lambda r: r["robots"])
        if not runs:
            continue
        n = [r["robots"] for r in runs]
        left.plot(n, [r["balance_ratio"] for r in runs], "o-", label=names[rule])
        right.plot(
            n,
            [r["replication_bytes_per_query"] + r["index_control_bytes_per_query"] for r in runs],
            "o-",
            label=names[rule],
        )
    left.axhline(1.5, color="k", ls="--", lw=0.8)
    left.set(xlabel="robots", ylabel="busiest shard / mean (partial queries)", xscale="log")
    right.set(xlabel="robots", ylabel="bytes a query: replica stores + index control", xscale="log")
    for ax in (left, right):
        ax.set_xticks([10, 25, 50, 100], ["10", "25", "50", "100"])
        ax.legend(fontsize=8)
    fig.suptitle("synthetic world, 50 frames a robot, lock-step (a step at least 0.2 s)", fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def compare_rules(
    sizes: list[int], rules: list[str], processes: int, out: Path, plot_path: Path | None = None
) -> None:
    """Each size under each rule, one after the other in the same run (the same machine, the
    same hour): the balance, its bytes and the placements each rule published."""
    unknown = [r for r in rules if r not in RULES]
    if unknown:
        raise SystemExit(f"unknown rules {unknown}: choose from {sorted(RULES)}")
    result: dict[str, Any] = {"machine": {"python": platform.python_version(), "cpus": os.cpu_count()}}
    runs: list[dict[str, Any]] = []
    result["runs"] = runs
    with tempfile.TemporaryDirectory() as tmp:
        for n in sizes:
            for rule in rules:
                per = max(1, -(-n // processes))
                target, name = RULES[rule]
                print(f"{n} robots, {per} a process, rule {rule} ...", flush=True)
                r = run(n, f"robots:{per}", Path(tmp), target, name, STEP_S)
                r["rule"] = rule
                runs.append(r)
                write(out, result)
                print(
                    f"  busiest/mean {r['balance_ratio']:.2f} "
                    f"(2nd half {r['balance_ratio_second_half']:.2f}), "
                    f"{r['bytes_per_query']:.0f} B/query + {r['replication_bytes_per_query']:.0f} replicas "
                    f"+ {r['index_control_bytes_per_query']:.0f} control, version {r['placement_version']} "
                    f"({r['versions_after_first_rebalance']} after the first rebalancing), "
                    f"identical {r['identical_to_offline']}",
                    flush=True,
                )
    if plot_path is not None:
        plot_rules(result, plot_path)


def main_bench() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "scale.json")
    ap.add_argument("--plot", type=Path, default=REPO / "docs" / "figures" / "scale.png")
    ap.add_argument("--robots", default="10,25,50,100", help="swarm sizes (default 10,25,50,100)")
    ap.add_argument(
        "--processes", type=int, default=2, help="host processes per swarm (default 2: the cores)"
    )
    ap.add_argument(
        "--rebalance-target",
        type=float,
        default=1000.0,
        help="busiest / mean that triggers a rebalancing (default 1000: never; 0: the swarm's default)",
    )
    ap.add_argument(
        "--rules",
        default="",
        help="compare placements in the same run, each size under each (comma list of off: no "
        "rebalancing; greedy: the rule before the plan, target 1.5; pack: the plan, the default "
        "target); overrides --rebalance-target, and skips the process-per-service baseline",
    )
    args = ap.parse_args()
    target = args.rebalance_target or IndexSettings.rebalance_target
    sizes = [int(x) for x in args.robots.split(",")]
    if args.rules:
        compare_rules(sizes, args.rules.split(","), args.processes, args.out, args.plot)
        return
    result: dict[str, Any] = {"machine": {"python": platform.python_version(), "cpus": os.cpu_count()}}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        print("baseline: 10 robots, one process per service ...", flush=True)
        base = run(10, "service", work, target)
        result["baseline_process_per_service"] = base
        runs: list[dict[str, Any]] = []
        result["hosted"] = runs
        for n in sizes:
            per = max(1, -(-n // args.processes))
            # Written before and after each size: a size that never finishes (stopped by
            # hand, the machine out of memory) leaves the sizes before it on disk, and says so.
            result["unfinished"] = n
            write(args.out, result)
            print(f"{n} robots, {per} robots a process ...", flush=True)
            runs.append(run(n, f"robots:{per}", work, target))
            del result["unfinished"]
            write(args.out, result)
    ten = next((r for r in runs if r["robots"] == 10), None)
    if ten is not None:
        result["ratios_10_robots"] = {
            "memory_per_robot_hosted_over_process_per_service": ten["memory_per_robot_mb"]
            / base["memory_per_robot_mb"],
            "wall_hosted_over_process_per_service": ten["wall_s"] / base["wall_s"],
        }
    write(args.out, result)
    plot(runs, args.plot)
    for r in [base, *runs]:
        print(
            f"{r['robots']:>4} robots ({r['hosting']:<10}) {r['processes']} processes: "
            f"wall {r['wall_s']:.1f} s, "
            f"{r['memory_per_robot_mb']:.0f} MB a robot ({r['memory_total_mb']:.0f} MB), "
            f"{r['bytes_per_query']:.0f} B/query, balance {r['balance_ratio']:.2f}, "
            f"identical {r['identical_to_offline']}"
        )


if __name__ == "__main__":
    main_bench()
