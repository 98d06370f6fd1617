"""Elastic index benchmark: load balance, bytes and handoffs on the TUM sequence, and scaling.

    python bench/bench_elastic.py --out bench/results/elastic.json --plot docs/figures/elastic_balance.png

1. **Balance.** The TUM constellations (``../shared/data``) through a live 10-robot swarm in
   lock-step, three ways, in the same run: the paper's layout (one replica a label group,
   the published 2.67 busiest/mean), two replicas without rebalancing, two replicas
   rebalanced by the rule before the plan (``rebalance_rule="greedy"``, target 1.5), and two
   replicas rebalanced by the plan (swarmrec.core.rebalance, the default target). For each:
   the busiest shard's share of partial queries over the whole run and over its second half (after the
   coordinator has seen enough load to move groups), bytes per query (the two-step query,
   the replicas' copies, the index's own traffic), placements published, descriptors handed
   off, and whether the pair scores equal the offline evaluation's.
2. **Scaling.** The synthetic world on 3 robots; 3 more index shards join, then 4 of the 6
   are stopped at once (they drain first): how long each change takes to settle, and the
   descriptors copied.

Shard loads are counted from the query reports (which shard answered each label group), so
they do not depend on a shard's counter surviving to the end.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import tempfile
import time
from pathlib import Path
from typing import Any

from lockstep_load import Pacer, shard_loads

from swarmrec.core.placement import balance_ratio
from swarmrec.core.split import split_frames
from swarmrec.deployments.base import Deployment
from swarmrec.deployments.local import LocalDeployment
from swarmrec.evaluation.source import DatasetSource
from swarmrec.experiments.places import PlacesSettings, main
from swarmrec.services.settings import IndexSettings

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
TUM = DATA / "tum_fr3_long_office_household_constellations.zip"
ROBOTS = 10
#: The coordinator's tick in the balance runs: the lock-step replay lasts about 5 s, and with the
#: default 1 s tick the coordinator sees its load only a third of the way in.
TICK_S = 0.25
#: Each lock-step step of the balance runs lasts at least this (robots at 20 frames a second, a
#: 13 s replay): a replay over in 5 s measures mostly how long the coordinator took to see it.
STEP_S = 0.05


def balance(name: str, index: IndexSettings, work: Path) -> dict[str, Any]:
    out = work / name
    settings = PlacesSettings(
        source=DatasetSource(str(TUM)),
        robots=ROBOTS,
        out=out,
        swarm=f"elastic-{name}",
        request_timeout_s=5.0,
        progress=False,
        plots=False,
        index=index,
    )
    pace = Pacer(STEP_S)

    def on_step(t: int) -> None:
        pace()

    t0 = time.perf_counter()
    s = main(settings, LocalDeployment.for_run(settings.out), on_step=on_step)
    wall = time.perf_counter() - t0
    steps = max(len(b) for b in split_frames(s.dataset.frames, ROBOTS))
    whole = shard_loads(out, ROBOTS)
    second = shard_loads(out, ROBOTS, first_step=steps // 2)
    assert s.index is not None
    return {
        "name": name,
        "replicas": index.replicas,
        "rebalance_target": index.rebalance_target,
        "rebalance_rule": index.rebalance_rule,
        "step_s": STEP_S,
        "placement_tick_s": index.placement_tick_s,
        "loads": whole,
        "balance_ratio": balance_ratio(whole),
        "loads_second_half": second,
        "balance_ratio_second_half": balance_ratio(second),
        "bytes_per_query": s.bytes.per_query,
        "replication_per_query": s.bytes.replication_per_query,
        "index_control_per_query": s.bytes.index_control_per_query,
        "all_per_query": s.bytes.all_per_query,
        "placement_version": s.index.version,
        "placements_published": s.index.placements_published,
        "handoff_records": s.index.handoff_records,
        "owners": s.index.owners,
        "identical_to_offline": s.offline_check.identical if s.offline_check else None,
        "query_p50_ms": s.queries.latency_ms.get("p50"),
        "wall_s": wall,
    }


def scaling(work: Path) -> dict[str, Any]:
    """3 robots; shards 3-5 join at step 20, shards 2-5 stop at step 55."""
    held: list[LocalDeployment] = []
    figures: dict[str, float] = {}

    def hook(d: Deployment) -> None:
        assert isinstance(d, LocalDeployment)
        held.append(d)

    def settle(d: LocalDeployment, want: set[int]) -> float:
        t0 = time.perf_counter()
        with d.client(5.0) as client:
            while True:
                state = client.index_state()
                owners = {m for own in state.placement.owners for m in own} if state.placement else set()
                if (
                    state.settled
                    and owners <= want
                    and state.placement
                    and set(state.placement.members) == want
                ):
                    return time.perf_counter() - t0
                if time.perf_counter() - t0 > 120:
                    raise TimeoutError(f"not settled on {want}: {state}")
                time.sleep(0.1)

    def on_step(t: int) -> None:
        d = held[0]
        if t == 20:
            t0 = time.perf_counter()
            for shard in (3, 4, 5):
                d.start_robot(shard, ["index-shard"])
            d.wait_ready(60.0)
            figures["join_start_s"] = time.perf_counter() - t0
            figures["join_settle_s"] = settle(d, set(range(6)))
        if t == 55:
            t0 = time.perf_counter()
            going = [d.find("index-shard", s) for s in (2, 3, 4, 5)]
            for sp in going:
                sp.proc.send_signal(signal.SIGTERM)
            for sp in going:
                sp.proc.wait(timeout=120)
            figures["drain_s"] = time.perf_counter() - t0
            figures["leave_settle_s"] = settle(d, {0, 1})

    settings = PlacesSettings(
        source=DatasetSource(frames=330),
        robots=3,
        out=work / "scale",
        swarm="elastic-scale",
        request_timeout_s=2.0,
        progress=False,
        plots=False,
        index=IndexSettings(max_shards=6, rebalance_target=1000.0, member_grace_s=2.0),
    )
    s = main(settings, LocalDeployment.for_run(settings.out), swarm_hook=hook, on_step=on_step)
    assert s.index is not None
    return {
        **figures,
        "handoff_records": s.index.handoff_records,
        "placements_published": s.index.placements_published,
        "identical_to_offline": s.offline_check.identical if s.offline_check else None,
        "failed_shard_requests": s.queries.failed_shard_requests,
    }


def plot(results: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(results), figsize=(4.2 * len(results), 3.4), sharey=True)
    for ax, r in zip(axes, results, strict=True):
        loads = r["loads"]
        mean = sum(loads) / len(loads)
        ax.bar(range(len(loads)), loads, color="#4c72b0")
        ax.axhline(mean, color="k", lw=0.8, ls="--")
        ax.set_title(
            f"{r['name']}\nbusiest/mean {r['balance_ratio']:.2f} "
            f"(2nd half {r['balance_ratio_second_half']:.2f})",
            fontsize=9,
        )
        ax.set_xlabel("index shard")
    axes[0].set_ylabel("partial queries answered")
    fig.suptitle("TUM fr3 long office, 10 robots, lock-step: load on each index shard", fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main_bench() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "elastic.json")
    ap.add_argument("--plot", type=Path, default=REPO / "docs" / "figures" / "elastic_balance.png")
    args = ap.parse_args()
    if not TUM.exists():
        raise SystemExit(f"the TUM constellations are not at {TUM}")
    configs = [
        (
            "paper layout (1 replica)",
            IndexSettings(replicas=1, rebalance_target=1000.0, placement_tick_s=TICK_S),
        ),
        ("2 replicas", IndexSettings(replicas=2, rebalance_target=1000.0, placement_tick_s=TICK_S)),
        # The rule before the plan, as the baseline measured in the same run (its target then, 1.5).
        (
            "2 replicas, greedy rule",
            IndexSettings(replicas=2, rebalance_target=1.5, rebalance_rule="greedy", placement_tick_s=TICK_S),
        ),
        ("2 replicas, rebalanced", IndexSettings(replicas=2, placement_tick_s=TICK_S)),
    ]
    with tempfile.TemporaryDirectory(prefix="bench-elastic-") as tmp:
        work = Path(tmp)
        runs = []
        for name, index in configs:
            print(f"{name} ...", flush=True)
            runs.append(balance(name.split(" (")[0].replace(" ", "-").replace(",", ""), index, work))
            runs[-1]["name"] = name
        print("scaling 3 -> 6 -> 2 ...", flush=True)
        scale = scaling(work)
    result = {
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
        "dataset": str(TUM.name),
        "robots": ROBOTS,
        "balance": runs,
        "scaling": scale,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    plot(runs, args.plot)
    for r in runs:
        print(
            f"  {r['name']:<26} busiest/mean {r['balance_ratio']:.2f} "
            f"(2nd half {r['balance_ratio_second_half']:.2f}), "
            f"{r['bytes_per_query']:.0f} B/query + {r['replication_per_query']:.0f} replicas "
            f"+ {r['index_control_per_query']:.0f} control, identical {r['identical_to_offline']}"
        )
    print(f"  scaling: {scale}")


if __name__ == "__main__":
    main_bench()
