"""Mesh benchmark: a router per robot against the star's one router (docs/mesh.md).

    python bench/bench_mesh.py --out bench/results/mesh.json --plot docs/figures/mesh_hops.png

Every case is a whole lock-step run of ``swarmrec run`` (places, the default preset),
one process per robot (``--hosting robot``: a robot's services talk inside its process,
only its radio traffic leaves it), measured in this one invocation:

1. **TUM fr3, 10 robots, star and mesh** (full range: every robot hears every other).
   Pair scores against the offline evaluation, CPU per query of every process of the
   swarm (routers, Toxiproxy and this driver included) read from ``/proc`` when the swarm
   is up and when the replay is over, the start time, bytes on the links.
2. **The synthetic world, 10 robots, by hop count**: the full mesh; a radio range of 4 m
   over the robots' own positions (multi-hop, links changing as they move); a chain
   0 - 1 - ... - 9 for the middle half of the run (a schedule cutting every other link),
   full otherwise. Bytes each link carried during the replay, summed over links, per
   query, against the mean hop count between robots: relayed traffic is counted on every
   link it crosses, measured by the routers on the wire.
3. **Partitions** (the synthetic world, 10 robots): a chain for steps 10-29, then the
   chain cut in the middle (two parts, 0-4 and 5-9) for 50 steps, then healed; and a
   radio range of 3 m, at which the robots' own movements split the team twice (in parts
   that change as they move, up to 6 hops). Pair scores against the offline simulation of
   the same schedule (swarmrec.evaluation.partition), the stores pending when the split
   ends, and those left at the end (none: every one delivered).

The figure plots each case's bytes on the links a query against the mean number of hops
between two robots.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_cpu import account, snapshot

from swarmrec.core.split import split_frames
from swarmrec.deployments.base import Deployment
from swarmrec.deployments.local import LocalDeployment, LocalSettings
from swarmrec.deployments.radio import RadioGraph
from swarmrec.evaluation.source import DatasetSource
from swarmrec.experiments.places import PlacesSettings, main

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
TUM = DATA / "tum_fr3_long_office_household_constellations.zip"
ROBOTS = 10


def mean_hops(graph: RadioGraph) -> float:
    """The mean, over steps and pairs of robots, of the fewest links between them."""
    per_step = [sum(h.values()) / len(h) for t in range(graph.steps) if (h := graph.hops_at(t))]
    return sum(per_step) / len(per_step) if per_step else 0.0


def run(
    name: str, work: Path, source: DatasetSource, local: LocalSettings, *, pending_at: int | None = None
) -> dict[str, Any]:
    """One lock-step run; ``pending_at``: the step after which the stores the descriptors
    owe are counted (the last step of a split)."""
    marks: dict[str, Any] = {}

    def up(d: Deployment) -> None:
        assert isinstance(d, LocalDeployment)
        marks["before"], marks["t0"] = snapshot(d), time.perf_counter()
        marks["live"] = d

    def counted(t: int) -> None:
        if t != pending_at:
            return
        with marks["live"].operator(5.0) as operator:
            infos = [operator.descriptor_info(r) for r in range(ROBOTS)]
        marks["pending_at_split_end"] = sum(i.pending_items for i in infos if i is not None)

    def over(d: Deployment) -> None:
        assert isinstance(d, LocalDeployment)
        marks["after"], marks["t1"] = snapshot(d), time.perf_counter()
        marks["deployment"] = d
        marks["router_rss_mib"] = _router_rss_mib(d)

    print(f"{name} ...", flush=True)
    settings = PlacesSettings(
        source=source,
        robots=ROBOTS,
        out=work / name.replace(" ", "_").replace(",", ""),
        swarm="bench-mesh",
        request_timeout_s=10.0,
        progress=False,
        plots=False,
    )
    s = main(
        settings,
        LocalDeployment.for_run(settings.out, local),
        swarm_hook=up,
        after_replay=over,
        on_step=counted if pending_at is not None else None,
    )
    queries = s.queries.queried
    cpu = account(marks["before"], marks["after"], queries)
    check = s.offline_check
    d: LocalDeployment = marks["deployment"]
    out: dict[str, Any] = {
        "case": name,
        "topology": local.topology,
        "radio_range_m": local.radio_range_m,
        "queries": queries,
        "identical_to_offline": check.identical if check else None,
        "auc": s.auc,
        "start_s": s.timings["start_s"],
        "replay_s": s.timings["replay_s"],
        "cpu_ms_per_query": cpu["cpu_ms_per_query"],
        "cpu_ms_per_query_by_process": {
            k: v for k, v in sorted(cpu["cpu_ms_per_query_by_process"].items(), key=lambda kv: -kv[1])[:12]
        },
        "app_bytes_between_robots_per_query": s.bytes.per_query,
        "missing_slots": s.queries.missing_slots,
        "peer_failures": s.peer_failures,
    }
    if s.mesh is not None:
        assert d.radio is not None
        out |= {
            "link_bytes_per_query": s.mesh.link_bytes_per_query,
            "links": len(s.mesh.link_bytes),
            "link_changes": len(s.mesh.events),
            "converge_s_mean": sum(s.mesh.converge_s) / len(s.mesh.converge_s) if s.mesh.converge_s else None,
            "converge_s_max": max(s.mesh.converge_s, default=None),
            "max_hops": s.mesh.max_hops,
            "mean_hops": mean_hops(d.radio),
            "router_rss_mib": marks["router_rss_mib"],
            "mesh_start_s": s.mesh.start_s,
            "link_bytes": s.mesh.link_bytes,
        }
    if check is not None and check.split_steps:
        index = s.index
        out |= {
            "split_steps": check.split_steps,
            "components": s.mesh.components if s.mesh is not None else None,
            "unreached_group_queries": check.unreached_group_queries,
            "unreachable_verifications": check.unreachable_verifications,
            "pending_stores_at_split_end": marks.get("pending_at_split_end"),
            "pending_stores_at_end": index.pending_stores if index is not None else None,
            "index_settled": index.settled if index is not None else None,
            "held_placements": s.mesh.held_placements if s.mesh is not None else None,
            "split_disagreements": s.mesh.split_disagreements if s.mesh is not None else None,
            "deliver_s_max": max(s.mesh.deliver_s, default=None) if s.mesh is not None else None,
        }
    print(
        f"  identical {out['identical_to_offline']}, cpu {out['cpu_ms_per_query']:.2f} ms/query, "
        f"start {out['start_s']:.1f} s, link bytes/query {out.get('link_bytes_per_query', 0):.0f}",
        flush=True,
    )
    return out


def _router_rss_mib(d: LocalDeployment) -> float | None:
    """The mean resident memory of the mesh's routers (MiB), read from /proc."""
    sizes = []
    for sp in d.routers:
        try:
            for line in Path(f"/proc/{sp.proc.pid}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    sizes.append(int(line.split()[1]) / 1024)
        except OSError:
            continue
    return sum(sizes) / len(sizes) if sizes else None


def chain_schedule(path: Path, steps: int) -> Path:
    """Every link but robot r to r + 1 cut for the middle half of ``steps``."""
    start, end = steps // 4, 3 * steps // 4
    rows = [f"{start},{end},{a},{b}" for a in range(ROBOTS) for b in range(a + 2, ROBOTS)]
    path.write_text("start,end,robot_a,robot_b\n" + "\n".join(rows) + "\n")
    return path


def split_schedule(path: Path) -> Path:
    """A chain 0 - 1 - ... - 9 for steps 10-29; then the chain cut between 4 and 5 (two parts)
    for steps 30-79; whole again from step 80."""
    rows = [f"10,80,{a},{b}" for a in range(ROBOTS) for b in range(a + 2, ROBOTS)]
    rows.append("30,80,4,5")
    path.write_text("start,end,robot_a,robot_b\n" + "\n".join(rows) + "\n")
    return path


def plot(cases: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    mesh = [
        c
        for c in cases
        if c["topology"] == "mesh" and c["case"].startswith("synthetic") and not c.get("split_steps")
    ]
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot([c["mean_hops"] for c in mesh], [c["link_bytes_per_query"] for c in mesh], "o-")
    for c in mesh:
        ax.annotate(c["case"].removeprefix("synthetic, mesh, "), (c["mean_hops"], c["link_bytes_per_query"]))
    ax.set_xlabel("mean hops between two robots")
    ax.set_ylabel("bytes on all links per query (measured)")
    ax.set_title("synthetic world, 10 robots, a router per robot", fontsize=10)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)


def main_cli() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "mesh.json")
    p.add_argument("--plot", type=Path, default=REPO / "docs" / "figures" / "mesh_hops.png")
    p.add_argument("--frames", type=int, default=1000, help="synthetic frames (default 1000)")
    args = p.parse_args()
    cases: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        if TUM.exists():
            for topology in ("star", "mesh"):
                local = LocalSettings(hosting="robot", topology=topology)  # type: ignore[arg-type]
                cases.append(run(f"TUM fr3, {topology}", work, DatasetSource(str(TUM)), local))
        else:
            print(f"{TUM} is absent: the TUM cases are not measured", flush=True)
        synthetic = DatasetSource(frames=args.frames)
        steps = len(split_frames(args.frames, ROBOTS)[0])
        cases.append(run("synthetic, star", work, synthetic, LocalSettings(hosting="robot")))
        for name, local in (
            ("full range", LocalSettings(hosting="robot", topology="mesh")),
            ("4 m range", LocalSettings(hosting="robot", topology="mesh", radio_range_m=4.0)),
            (
                "chain half the run",
                LocalSettings(
                    hosting="robot", topology="mesh", schedule=chain_schedule(work / "chain.csv", steps)
                ),
            ),
        ):
            cases.append(run(f"synthetic, mesh, {name}", work, synthetic, local))
        split = LocalSettings(hosting="robot", topology="mesh", schedule=split_schedule(work / "split.csv"))
        cases.append(run("synthetic, mesh, chain then split 50 steps", work, synthetic, split, pending_at=79))
        ranged = LocalSettings(hosting="robot", topology="mesh", radio_range_m=3.0)
        cases.append(run("synthetic, mesh, 3 m range (splits)", work, synthetic, ranged))
    by = {c["case"]: c for c in cases}
    ratios: dict[str, float | None] = {}
    if "TUM fr3, star" in by:
        star, mesh = by["TUM fr3, star"], by["TUM fr3, mesh"]
        ratios["tum_cpu_mesh_over_star"] = mesh["cpu_ms_per_query"] / star["cpu_ms_per_query"]
    ratios["synthetic_cpu_mesh_over_star"] = (
        by["synthetic, mesh, full range"]["cpu_ms_per_query"] / by["synthetic, star"]["cpu_ms_per_query"]
    )
    result = {
        "machine": {
            "platform": platform.platform(),
            "cores": os.cpu_count(),
            "python": platform.python_version(),
        },
        "robots": ROBOTS,
        "hosting": "robot",
        "cases": cases,
        "ratios": ratios,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    plot(cases, args.plot)
    print(json.dumps(ratios), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main_cli())
