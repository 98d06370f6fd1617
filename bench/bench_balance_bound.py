"""How even the index's load can get: the bound on busiest / mean for complete copies of the
label groups, what the rebalancing plan reaches, and how often a hot group's answer hangs on
a tie (issue 27). Offline: no swarm, no processes.

    python bench/bench_balance_bound.py --out bench/results/balance_bound.json \
        --plot docs/figures/balance_bound.png

1. **Load per group.** Partial queries (and stored slices, the same count) per label group,
   the paper's even ranges: the synthetic world at 10, 25, 50 and 100 robots (50 frames a
   robot) and the TUM sequence at 10 robots (``../shared/data``; skipped when absent). A
   frame queries, and stores, only with at least the preset's ``min_objects`` objects, as
   the descriptor service does.
2. **The bound** (swarmrec.evaluation.balance_bound, which does not read
   swarmrec.core.rebalance): a partial query is answered from one complete copy of its
   group, so with ``k_g`` copies a group's owners serve ``q_g / k_g`` each whatever the
   group is cut into; the least replica ShardStores for busiest / mean <= 1.5, and the
   whole trade-off curve. Then swarmrec.core.rebalance.rebalance from the ring layout (two
   replicas) for store weights 0, 0.1, 0.25, 0.4 and min_replica_gain 0.1, 0.05, 0: busiest
   / mean in partial queries and in work (owner_load), owners of the hottest group, replica
   stores per query, beside the bound for the same copies (packing_bound).
3. **Ties at the n_ret cut.** The 4 hottest groups at 100 robots in lock-step (robot r's
   frame t against every robot's frames < t, RangeIndex.candidates(before=t)): how often
   more than n_ret positive scores are >= the n_ret-th best, i.e. how often an exact merge
   of sub-group answers would need the sub-groups' whole score vectors.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from swarmrec.core.descriptor import semantic_descriptors
from swarmrec.core.index import RangeIndex
from swarmrec.core.placement import balance_ratio, groups_from_bounds, ring, shard_loads
from swarmrec.core.presets import get_preset
from swarmrec.core.ranges import even_ranges
from swarmrec.core.rebalance import rebalance
from swarmrec.core.split import split_frames
from swarmrec.evaluation.balance_bound import (
    FrontierPoint,
    copies_for_ratio,
    group_partial_queries,
    packing_bound,
    replica_stores,
    share_bound,
    share_frontier,
    tie_straddles_cut,
)
from swarmrec.evaluation.source import DatasetSource, load_dataset
from swarmrec.services.settings import IndexSettings

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
TUM = DATA / "tum_fr3_long_office_household_constellations.zip"
SCALE_100 = REPO / "bench" / "results" / "scale_rebalancing_on_100.json"
FRAMES_PER_ROBOT = 50
SYNTHETIC_ROBOTS = (10, 25, 50, 100)
TUM_ROBOTS = 10
WEIGHTS = (0.0, 0.1, 0.25, 0.4)
GAINS = (0.1, 0.05, 0.0)
TARGET_RATIO = 1.5  # the busiest / mean
BYTE_SHARE = 0.25  # the budget: replica stores + index control over query bytes
#: Bytes of one ShardStore and its StoreReply: 124.5 B of replica stores per query over the
#: 5.3 ShardStores a query the 100-robot run made (see byte_model in the results).
STORE_BYTES = 23.0
PRESET = get_preset("paper")
HOT_GROUPS = 4


def _world(name: str, source: DatasetSource, robots: int) -> dict[str, Any]:
    seq = load_dataset(source).sequence
    desc = semantic_descriptors(seq.constellations, seq.n_labels)
    queried = np.array([len(c) >= PRESET.min_objects for c in seq.constellations], bool)
    groups = groups_from_bounds(even_ranges(seq.n_labels, robots).tolist())
    loads = group_partial_queries(desc, groups, queried)
    with_labels = group_partial_queries(desc, groups)
    return {
        "name": name,
        "robots": robots,
        "frames": len(seq),
        "queried_frames": int(queried.sum()),
        "groups": groups,
        "loads": [int(q) for q in loads],
        "loads_all_frames": [int(q) for q in with_labels],
        "desc": desc,
        "queried": queried,
    }


def _bound(w: dict[str, Any], budget_stores: float | None) -> dict[str, Any]:
    loads: list[int] = w["loads"]
    n, queries = w["robots"], w["queried_frames"]
    total = sum(loads)
    hot = max(range(len(loads)), key=lambda g: (loads[g], -g))
    out: dict[str, Any] = {
        "partial_queries": total,
        "mean_per_shard": total / n,
        "hottest_group": hot,
        "hottest_labels": list(w["groups"][hot]),
        "hottest_partial_queries": loads[hot],
        "hottest_over_mean_one_copy": loads[hot] * n / total,
        "partial_queries_per_query": total / queries,
    }
    for floor in (1, 2):
        copies = copies_for_ratio(loads, n, TARGET_RATIO, floor=min(floor, n))
        stores = replica_stores(loads, copies)
        frontier = share_frontier(loads, n, floor=min(floor, n))
        out[f"floor_{floor}"] = {
            "copies_for_target": copies,
            "hottest_copies_for_target": copies[hot],
            "replica_stores_for_target": stores,
            "replica_stores_per_query_for_target": stores / queries,
            "replica_store_bytes_per_query_for_target": stores / queries * STORE_BYTES,
            "share_bound_at_floor": share_bound(loads, [min(floor, n)] * len(loads), n),
            "packing_bound_for_target_copies": packing_bound(loads, copies, n),
            "frontier": _truncated(frontier, queries),
        }
        pts = out[f"floor_{floor}"]["frontier"]
        reachable = budget_stores is not None and pts[0]["replica_stores_per_query"] <= budget_stores
        out[f"floor_{floor}"]["bound_within_byte_budget"] = (
            _frontier_at(pts, budget_stores) if reachable and budget_stores is not None else None
        )
    return out


def _truncated(frontier: list[FrontierPoint], queries: int) -> list[dict[str, float]]:
    """The frontier's corners per query, up to the first at or below the mean (more copies
    lower the share, but busiest / mean cannot go below 1)."""
    out = []
    for p in frontier:
        out.append(
            {
                "ratio": max(1.0, p.ratio),
                "share_ratio": p.ratio,
                "replica_stores_per_query": p.replica_stores / queries,
            }
        )
        if p.ratio <= 1.0:
            break
    return out


def _frontier_at(frontier: list[dict[str, float]], per_query: float) -> float:
    """The bound on busiest / mean with at most ``per_query`` replica stores a query: the
    lowest ratio of a frontier corner that costs no more (never below 1, the mean)."""
    return min(p["ratio"] for p in frontier if p["replica_stores_per_query"] <= per_query + 1e-12)


def _rebalanced(w: dict[str, Any], bound: dict[str, Any], target: float) -> list[dict[str, Any]]:
    loads: list[int] = w["loads"]
    n, queries = w["robots"], w["queried_frames"]
    start = ring(w["groups"], range(n), replicas=2)
    load_map = {g: float(q) for g, q in enumerate(loads)}
    rows = []
    for weight in WEIGHTS:
        for gain in GAINS:
            t0 = time.perf_counter()
            plan = rebalance(start, load_map, target=target, store_weight=weight, min_replica_gain=gain)
            copies = [len(o) for o in plan.owners]
            stores = replica_stores(loads, copies)
            rows.append(
                {
                    "store_weight": weight,
                    "min_replica_gain": gain,
                    "changed": plan != start,
                    "busiest_over_mean_partial_queries": balance_ratio(shard_loads(plan, load_map, 0.0)),
                    "busiest_over_mean_work": balance_ratio(shard_loads(plan, load_map, weight)),
                    "max_owners": max(copies),
                    "hottest_group_owners": copies[bound["hottest_group"]],
                    "replica_stores_per_query": stores / queries,
                    "replica_stores_per_frame": stores / w["frames"],
                    "packing_bound_same_copies": packing_bound(loads, copies, n),
                    "bound_same_replica_stores": _frontier_at(bound["floor_2"]["frontier"], stores / queries),
                    "plan_s": time.perf_counter() - t0,
                }
            )
    return rows


class _TieCounter(RangeIndex):
    """A RangeIndex that notes, for every lock-step query, the positive scores it chose
    from (its own scoring, untouched) before selecting as it always does."""

    def __init__(self, lo: int, hi: int, n_robots: int) -> None:
        super().__init__(lo, hi, n_robots)
        self.seen: list[tuple[int, int, bool]] = []  # (positive scores, scores >= kth, tie)

    def _select(
        self, values: npt.NDArray[np.float64], slots: npt.NDArray[np.int64], n_ret: int, t: int | None
    ) -> npt.NDArray[np.int64]:
        m = values.shape[0]
        tie = tie_straddles_cut(values, n_ret)
        at_cut = (
            int(np.count_nonzero(values >= -np.partition(-values, n_ret - 1)[n_ret - 1])) if m > n_ret else m
        )
        self.seen.append((m, at_cut, tie))
        return super()._select(values, slots, n_ret, t)


def ties(w: dict[str, Any], bound: dict[str, Any], every: int) -> dict[str, Any]:
    """Lock-step queries of the hottest groups (robots ``0, every, 2 every, ...`` query; every
    robot's frames are stored), counting ties at the n_ret cut."""
    loads: list[int] = w["loads"]
    n = w["robots"]
    desc, queried = w["desc"], w["queried"]
    blocks = split_frames(w["frames"], n)
    hottest = sorted(range(len(loads)), key=lambda g: (-loads[g], g))[:HOT_GROUPS]
    out = []
    t0 = time.perf_counter()
    for g in hottest:
        lo, hi = w["groups"][g]
        index = _TieCounter(lo, hi, n)
        frames = [
            (r, t, f)
            for r, block in enumerate(blocks)
            for t, f in enumerate(block)
            if queried[f] and desc[f, lo:hi].any()
        ]
        for r, t, f in frames:
            index.add(r, t, desc[f, lo:hi])
        asked = [(r, t, f) for r, t, f in frames if r % every == 0]
        with_stored = 0
        for _r, t, f in asked:
            before = len(index.seen)
            index.candidates(desc[f, lo:hi], PRESET.n_ret, before=t)
            with_stored += len(index.seen) > before and index.seen[-1][0] > 0
        seen = index.seen
        tied = [s for s in seen if s[2]]
        positives = [s[0] for s in tied]
        out.append(
            {
                "group": g,
                "labels": [lo, hi],
                "partial_queries": loads[g],
                "partial_queries_asked": len(asked),
                "with_a_positive_score": with_stored,
                "tie_at_cut": len(tied),
                "tie_fraction": len(tied) / len(asked) if asked else 0.0,
                "tie_fraction_with_a_positive_score": len(tied) / with_stored if with_stored else 0.0,
                "positive_scores_when_tied": _summary(positives),
                "scores_at_or_above_cut_when_tied": _summary([s[1] for s in tied]),
            }
        )
        print(
            f"  ties, group {g} (labels {lo}-{hi - 1}): {len(tied)} of {len(asked)} partial queries "
            f"({len(tied) / max(len(asked), 1):.1%}), {time.perf_counter() - t0:.0f} s",
            flush=True,
        )
    asked_all = sum(o["partial_queries_asked"] for o in out)
    tied_all = sum(o["tie_at_cut"] for o in out)
    stored_all = sum(o["with_a_positive_score"] for o in out)
    return {
        "world": w["name"],
        "n_ret": PRESET.n_ret,
        "sampled": (
            "every robot's frames stored; all queries of all robots asked"
            if every == 1
            else f"every robot's frames stored; the queries of robots 0, {every}, {2 * every}, ... asked"
        ),
        "groups": out,
        "partial_queries_asked": asked_all,
        "tie_at_cut": tied_all,
        "tie_fraction": tied_all / asked_all if asked_all else 0.0,
        "tie_fraction_with_a_positive_score": tied_all / stored_all if stored_all else 0.0,
        "wall_s": time.perf_counter() - t0,
    }


def _fmt(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def _summary(values: list[int]) -> dict[str, float]:
    if not values:
        return {}
    return {
        "min": min(values),
        "median": statistics.median(values),
        "p90": float(np.percentile(values, 90)),
        "max": max(values),
    }


def _byte_model() -> dict[str, Any]:
    measured: dict[str, Any] = {}
    if SCALE_100.exists():
        hosted = json.loads(SCALE_100.read_text())["hosted"][0]
        measured = {
            "query_bytes_per_query": hosted["bytes_per_query"],
            "replica_store_bytes_per_query": hosted["replication_bytes_per_query"],
            "index_control_bytes_per_query": hosted["index_control_bytes_per_query"],
        }
    query = measured.get("query_bytes_per_query")
    control = measured.get("index_control_bytes_per_query")
    budget = BYTE_SHARE * query if query is not None else None
    return {
        "store_bytes": STORE_BYTES,
        "store_bytes_source": (
            "bench/results/scale_rebalancing_on_100.json (hosted[0]: 100 robots, lock-step, "
            "rebalancing on, 50 robots a process): replication_bytes_per_query 124.5 B "
            "(ShardStore + StoreReply) over 5.3 ShardStores a query, rounded down to 23 B. The "
            "5.3 is not in that file: with two owners for every group a query makes one "
            "ShardStore per partial query, 24834 / 4709 = 5.27 here (floor_2's first frontier "
            "point), and that run gave a few groups a third owner"
        ),
        "measured": measured,
        "budget_share": BYTE_SHARE,
        "budget_bytes_per_query": budget,
        "budget_stores_per_query_without_index_control": budget / STORE_BYTES if budget else None,
        "budget_stores_per_query_after_measured_index_control": (
            (budget - control) / STORE_BYTES if budget is not None and control is not None else None
        ),
    }


def plot(
    world: dict[str, Any],
    bound: dict[str, Any],
    rows: list[dict[str, Any]],
    bytes_: dict[str, Any],
    path: Path,
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.6, 4.8))
    x_max = 1.1 * max(r["replica_stores_per_query"] for r in rows)
    for floor, style, label in (
        (1, "-", "bound: any copies (>= 1 a group)"),
        (2, "--", "bound: >= 2 copies a group (the ring's floor)"),
    ):
        pts = bound[f"floor_{floor}"]["frontier"]
        xs = [p["replica_stores_per_query"] for p in pts] + [x_max]
        ys = [p["ratio"] for p in pts] + [pts[-1]["ratio"]]
        ax.step(xs, ys, where="post", ls=style, color="k", lw=1.0, label=label)
    markers = {0.0: "o", 0.1: "s", 0.25: "^", 0.4: "D"}
    colors = {0.1: "#c44e52", 0.05: "#dd8452", 0.0: "#4c72b0"}
    for r in rows:
        ax.scatter(
            r["replica_stores_per_query"],
            r["busiest_over_mean_partial_queries"],
            marker=markers[r["store_weight"]],
            color=colors[r["min_replica_gain"]],
            s=40,
            zorder=3,
        )
    for w, m in markers.items():
        ax.scatter([], [], marker=m, color="grey", label=f"rebalance(), store weight {w}")
    for g, c in colors.items():
        ax.scatter([], [], marker="o", color=c, label=f"rebalance(), min_replica_gain {g}")
    ax.axhline(TARGET_RATIO, color="#55a868", lw=1.2, label=f"issue 27: busiest / mean {TARGET_RATIO}")
    need = bound["floor_1"]["replica_stores_per_query_for_target"]
    ax.annotate(
        f"{TARGET_RATIO} needs >= {need:.1f} stores a query\n"
        f"({need * STORE_BYTES:.0f} B at {STORE_BYTES:.0f} B a store)",
        (need, TARGET_RATIO),
        xytext=(14, 34),
        textcoords="offset points",
        fontsize=8,
        arrowprops={"arrowstyle": "->", "lw": 0.7},
    )
    today = next(r for r in rows if r["store_weight"] == 0.4 and r["min_replica_gain"] == 0.1)
    ax.annotate(
        "the coordinator's gain (0.1) at a measured weight",
        (today["replica_stores_per_query"], today["busiest_over_mean_partial_queries"]),
        xytext=(18, 16),
        textcoords="offset points",
        fontsize=8,
        arrowprops={"arrowstyle": "->", "lw": 0.7},
    )
    budget = bytes_["budget_stores_per_query_without_index_control"]
    if budget:
        ax.axvline(budget, color="#8172b2", ls=":", lw=1.4)
        ax.text(
            budget,
            12.0,
            f" 25 % of query bytes,\n no index control:\n {budget:.2f} stores a query",
            fontsize=8,
            color="#8172b2",
        )
    ax.set_yscale("log")
    ax.set_xlim(0, x_max)
    ax.set_ylim(1.0, 25.0)
    ax.set_yticks([1, 1.5, 2, 3, 5, 10, 20])
    ax.set_yticklabels(["1", "1.5", "2", "3", "5", "10", "20"])
    ax.set_xlabel("replica ShardStores per query")
    ax.set_ylabel("busiest / mean shard, partial queries")
    ax.set_title(
        f"synthetic world, {world['robots']} robots, {world['frames']} frames, from ring(replicas=2)",
        fontsize=10,
    )
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main_bench() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "balance_bound.json")
    ap.add_argument("--plot", type=Path, default=REPO / "docs" / "figures" / "balance_bound.png")
    ap.add_argument(
        "--tie-every",
        type=int,
        default=1,
        help="ask the lock-step queries of every n-th robot only in the tie count (1: all)",
    )
    args = ap.parse_args()
    t_start = time.perf_counter()
    target = IndexSettings().rebalance_target
    sources: list[tuple[str, DatasetSource, int]] = [
        (f"synthetic-{n}", DatasetSource(frames=FRAMES_PER_ROBOT * n), n) for n in SYNTHETIC_ROBOTS
    ]
    skipped = []
    if TUM.exists():
        sources.append(("tum-10", DatasetSource(str(TUM)), TUM_ROBOTS))
    else:
        skipped.append(f"TUM: the constellations are not at {TUM}; its rows are left out")
        print(f"skipping TUM: the constellations are not at {TUM}", flush=True)
    bytes_ = _byte_model()
    budget_stores = bytes_["budget_stores_per_query_without_index_control"]
    worlds, results = {}, []
    for name, source, robots in sources:
        print(f"{name}: loading, bounds, rebalance ({len(WEIGHTS) * len(GAINS)} plans) ...", flush=True)
        w = _world(name, source, robots)
        worlds[name] = w
        # The byte budget is the 100-robot run's (its query bytes): other worlds get none.
        b = _bound(w, budget_stores if name == "synthetic-100" else None)
        rows = _rebalanced(w, b, target)
        results.append(
            {
                "name": name,
                "robots": robots,
                "frames": w["frames"],
                "queried_frames": w["queried_frames"],
                "groups": [
                    {
                        "group": g,
                        "labels": list(rng),
                        "partial_queries": q,
                        "stored_slices": q,
                        "frames_with_labels": a,
                    }
                    for g, (rng, q, a) in enumerate(
                        zip(w["groups"], w["loads"], w["loads_all_frames"], strict=True)
                    )
                ],
                "bound": b,
                "rebalance": rows,
            }
        )
    print("ties at the n_ret cut, synthetic-100 ...", flush=True)
    by_name = {r["name"]: r for r in results}
    tie = ties(worlds["synthetic-100"], by_name["synthetic-100"]["bound"], args.tie_every)
    result = {
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
        "preset": {"name": "paper", "n_ret": PRESET.n_ret, "min_objects": PRESET.min_objects},
        "target_ratio": TARGET_RATIO,
        "rebalance_target": target,
        "start_placement": "swarmrec.core.placement.ring(replicas=2)",
        "note": (
            "partial queries per group count the frames with at least min_objects objects and a "
            "label in the group (each stores one slice there too); a query = a queried frame. "
            "The bound is in the issue's unit, one partial query per (frame, group): cutting a "
            "group into sub-groups that each get a message would add messages (raising the mean) "
            "without lowering the busiest owner's q_g / k_g"
        ),
        "skipped": skipped,
        "worlds": results,
        "ties": tie,
        "byte_model": bytes_,
        "wall_s": time.perf_counter() - t_start,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    r100 = by_name["synthetic-100"]
    plot(worlds["synthetic-100"], r100["bound"], r100["rebalance"], bytes_, args.plot)
    print(
        f"\n{'world':<14} {'Q':>6} {'mean':>6} {'hot q':>6} {'1 copy':>7} {'k hot':>5} "
        f"{'stores/q >=1':>12} {'>=2':>6} {'in budget >=1':>13} {'>=2':>5}"
    )
    for r in results:
        b = r["bound"]
        f1, f2 = b["floor_1"], b["floor_2"]
        print(
            f"{r['name']:<14} {b['partial_queries']:>6} {b['mean_per_shard']:>6.1f} "
            f"{b['hottest_partial_queries']:>6} {b['hottest_over_mean_one_copy']:>7.2f} "
            f"{f1['hottest_copies_for_target']:>5} {f1['replica_stores_per_query_for_target']:>12.2f} "
            f"{f2['replica_stores_per_query_for_target']:>6.2f} "
            f"{_fmt(f1['bound_within_byte_budget']):>13} {_fmt(f2['bound_within_byte_budget']):>5}"
        )
    print(f"\nrebalance from ring(replicas=2), target {target}, synthetic-100:")
    print(
        f"{'weight':>6} {'gain':>5} {'pq b/m':>7} {'work b/m':>8} {'owners':>6} "
        f"{'stores/q':>8} {'pack LB':>7} {'bound':>6}"
    )
    for row in r100["rebalance"]:
        print(
            f"{row['store_weight']:>6} {row['min_replica_gain']:>5} "
            f"{row['busiest_over_mean_partial_queries']:>7.2f} {row['busiest_over_mean_work']:>8.2f} "
            f"{row['max_owners']:>6} {row['replica_stores_per_query']:>8.2f} "
            f"{row['packing_bound_same_copies']:>7.2f} {row['bound_same_replica_stores']:>6.2f}"
        )
    print(
        f"\nties at the n_ret={PRESET.n_ret} cut, 4 hottest groups: {tie['tie_at_cut']} of "
        f"{tie['partial_queries_asked']} ({tie['tie_fraction']:.1%}; "
        f"{tie['tie_fraction_with_a_positive_score']:.1%} of those with a stored match)"
    )
    print(
        f"byte budget: {bytes_['budget_bytes_per_query']} B a query = "
        f"{bytes_['budget_stores_per_query_without_index_control']} stores without index control, "
        f"{bytes_['budget_stores_per_query_after_measured_index_control']} after the measured control"
    )
    print(f"wrote {args.out} and {args.plot} ({result['wall_s']:.0f} s)")


if __name__ == "__main__":
    main_bench()
