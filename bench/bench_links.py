"""Links benchmark: the swarm over emulated radio links (docs/links.md).

    python bench/bench_links.py --out bench/results/links.json

Four robots of the synthetic world, one process per robot (``--hosting robot``: a
robot's own services talk inside its process, only its radio traffic crosses its
link), lock-step, every robot behind its own Toxiproxy link. Cases, each a whole run:

* ``direct``: no emulator (the baseline, measured in the same run);
* ``10 kB/s``: every link limited to 10 kilobytes a second each way;
* ``100 ms``: 100 ms of latency each way on every link;
* ``10 kB/s, 100 ms, outages``: both, and robots 1 and 2 out of range for a fifth
  of the steps each (``--outages``), from a schedule file as datasets publish them.

For each: AUC against the world's truth, loop closures, whether the pair scores equal
the offline evaluation's (they must, except where robots were out of range), bytes
between robots per query, the replay's wall time and query latency, the missing
slots (steps a robot was out of range) and frames still pending at the end (must be 0:
nothing stored is lost when a link comes back).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
from pathlib import Path
from typing import Any

from swarmrec.deployments.links import LinkSpec
from swarmrec.deployments.local import LocalDeployment, LocalSettings
from swarmrec.evaluation.source import DatasetSource
from swarmrec.experiments.places import PlacesSettings, main

REPO = Path(__file__).resolve().parents[1]
ROBOTS, FRAMES = 4, 400


def run(name: str, work: Path, link: LinkSpec | None, schedule: Path | None) -> dict[str, Any]:
    settings = PlacesSettings(
        source=DatasetSource(frames=FRAMES),
        robots=ROBOTS,
        out=work / name.replace(" ", "_").replace("/", "_").replace(",", ""),
        swarm="bench-links",
        request_timeout_s=10.0,
        progress=False,
        plots=False,
    )
    local = LocalSettings(hosting="robot", link=link or LinkSpec(), schedule=schedule)
    s = main(settings, LocalDeployment.for_run(settings.out, local))
    check = s.offline_check
    return {
        "case": name,
        "rate_kbps": link.rate_kbps if link else None,
        "latency_ms": link.latency_ms if link else None,
        "auc": s.auc,
        "loop_closures": s.loop_closures.count,
        "identical_to_offline": check.identical if check else None,
        "positive_pairs": check.positive_pairs_swarm if check else None,
        "positive_pairs_offline": check.positive_pairs_offline if check else None,
        "bytes_per_query": s.bytes.per_query,
        "bytes_all_per_query": s.bytes.all_per_query,
        "replay_s": s.timings.get("replay_s"),
        "query_latency_ms": s.queries.latency_ms,
        "missing_slots": s.queries.missing_slots,
        "missing_by_robot": s.queries.missing_by_robot,
        "pending_frames": s.queries.pending_frames,
        "late_frames": s.queries.late_frames,
        "link_events": s.links.events if s.links else [],
    }


def main_bench() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "links.json")
    ap.add_argument(
        "--outages",
        default="20,40,1;60,80,2",
        help="start,end,robot of each outage in lock-step steps, ';'-separated (default 20,40,1;60,80,2)",
    )
    args = ap.parse_args()
    result: dict[str, Any] = {
        "machine": {"python": platform.python_version(), "cpus": os.cpu_count()},
        "robots": ROBOTS,
        "frames": FRAMES,
        "hosting": "robot",
    }
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        schedule = work / "schedule.csv"
        rows = [row.split(",") for row in args.outages.split(";") if row]
        schedule.write_text("start,end,robot\n" + "".join(f"{a},{b},{r}\n" for a, b, r in rows))
        cases: list[tuple[str, LinkSpec | None, Path | None]] = [
            ("direct", None, None),
            ("10 kB/s", LinkSpec(rate_kbps=10.0), None),
            ("100 ms", LinkSpec(latency_ms=100.0), None),
            ("10 kB/s, 100 ms, outages", LinkSpec(rate_kbps=10.0, latency_ms=100.0), schedule),
        ]
        runs = []
        for name, link, sched in cases:
            print(f"{name} ...", flush=True)
            runs.append(run(name, work, link, sched))
        result["outages"] = [{"start": int(a), "end": int(b), "robot": int(r)} for a, b, r in rows]
    result["runs"] = runs
    base = runs[0]
    for r in runs:
        r["replay_over_direct"] = r["replay_s"] / base["replay_s"] if base["replay_s"] else None
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    for r in runs:
        print(
            f"{r['case']:<26} AUC {r['auc']:.3f}, {r['loop_closures']} closures, "
            f"identical {r['identical_to_offline']}, {r['bytes_per_query']:.0f} B/query, "
            f"replay {r['replay_s']:.1f} s (x{r['replay_over_direct']:.1f}), "
            f"p50 {r['query_latency_ms'].get('p50', float('nan')):.0f} ms, "
            f"missing {r['missing_slots']}, pending {r['pending_frames']}"
        )
    print(f"written to {args.out}")


if __name__ == "__main__":
    main_bench()
