"""Swarm benchmark: the real TUM constellations through a local swarm of 10
robots over a real zenoh router on this machine, for each way of hosting the
robots' services (``--hostings``; default: one process per service, the
deployment the project started from, then one process per robot, then five
robots a process).

    python bench/bench_swarm.py --out bench/results/swarm.json

For each hosting two runs, and two baselines measured in the same run:

* lock-step over the whole sequence (2585 frames): wall time, query latency
  while all ten robots query at the same instant, measured bytes per query,
  worst shard balance ratio, and whether the pair scores equal the offline
  evaluation's. Baseline: the offline decentralized evaluation of the same
  sequence in one process (``swarm_wall / offline_wall``).
* paced: every robot replays its share at ``--rate`` frames per second at its
  own phase, as robots that are not synchronised would: query latency of a
  swarm that is not saturated. Baseline: a bare zenoh request/reply through
  a router, measured here back to back (``query_p50 / bare_round_trip_p50``)
  and, as the paced swarm asks, one request every 1 / (rate x 10 robots) s
  (``bare_round_trip_paced_ms``: each thread on the way is idle by then, and
  waking it costs more than the work): a two-step query makes two rounds of
  parallel requests, so twice the paced round trip is the floor.
  The paced run is repeated (``--paced-repeats``, 3 by default), each time right
  after its own paced bare round trip: on a shared machine the wake-up cost
  moves from one minute to the next, and one run can land in a busy one. The
  targets are judged on the median repeat (``paced``; every repeat is in
  ``paced_repeats`` with its baseline).

``targets`` says, per hosting, whether issue 17's targets were met on this
machine: whole lock-step run under 10 s, cold start under 3 s, paced query
p50 at most 2 ms and p99 at most 10 ms.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from swarmrec.core.presets import get_preset
from swarmrec.datasets.constellations import read_constellations
from swarmrec.datasets.labels import COCO_NAMES
from swarmrec.deployments.local import LocalDeployment, LocalSettings, free_port
from swarmrec.evaluation.scoring import score_decentralized
from swarmrec.evaluation.source import DatasetSource
from swarmrec.experiments.places import PlacesSettings, main
from swarmrec.experiments.places.pipeline import as_on_the_wire

REPO = Path(__file__).resolve().parents[1]
TUM_ZIP = REPO.parent / "shared" / "data" / "tum_fr3_long_office_household_constellations.zip"


def bare_round_trip(n: int = 2000, gap_s: float = 0.0) -> dict[str, float]:
    """p50/p99 of a 100-byte request/reply between two client sessions through a router:
    back to back, or each ``gap_s`` after the last answer (as a paced swarm asks: every
    thread on the way has gone idle, and waking it costs more than the work)."""

    def conf(mode: str, key: str, endpoint: str) -> zenoh.Config:
        c = zenoh.Config()
        c.insert_json5("mode", json.dumps(mode))
        c.insert_json5(key, json.dumps([endpoint]))
        c.insert_json5("scouting/multicast/enabled", "false")
        return c

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with (
        zenoh.open(conf("router", "listen/endpoints", endpoint)),
        zenoh.open(conf("client", "connect/endpoints", endpoint)) as server,
        zenoh.open(conf("client", "connect/endpoints", endpoint)) as client,
    ):
        q = server.declare_queryable("bench/echo")

        def serve() -> None:
            for query in q.handler:
                with query:
                    query.reply(query.key_expr, query.payload.to_bytes() if query.payload else b"")

        threading.Thread(target=serve, daemon=True).start()
        querier = client.declare_querier("bench/echo")
        deadline = time.monotonic() + 10
        while not querier.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.01)
        payload = b"x" * 100
        for _ in range(100):  # warm-up
            list(querier.get(payload=payload))
        times = []
        for _ in range(n):
            if gap_s:
                time.sleep(gap_s)
            t0 = time.perf_counter()
            list(querier.get(payload=payload))
            times.append(time.perf_counter() - t0)
        querier.undeclare()
        q.undeclare()
    arr = np.asarray(times) * 1e3
    return {"p50_ms": float(np.percentile(arr, 50)), "p99_ms": float(np.percentile(arr, 99))}


def offline_wall(seq_path: Path) -> float:
    t0 = time.perf_counter()
    seq = as_on_the_wire(read_constellations(seq_path, COCO_NAMES))
    score_decentralized(seq, 10, get_preset("paper"))
    return time.perf_counter() - t0


#: Issue 17's targets for 10 robots on TUM.
TARGETS = {"lockstep_wall_s": 10.0, "start_s": 3.0, "paced_p50_ms": 2.0, "paced_p99_ms": 10.0}


def targets(lock: dict[str, Any], paced: dict[str, Any]) -> dict[str, dict[str, Any]]:
    measured = {
        "lockstep_wall_s": lock["wall_s"],
        "start_s": lock["timings"]["start_s"],
        "paced_p50_ms": paced["latency_ms"]["p50"],
        "paced_p99_ms": paced["latency_ms"]["p99"],
    }
    return {
        k: {"measured": v, "target": TARGETS[k], "met": bool(v <= TARGETS[k])} for k, v in measured.items()
    }


def median_repeat(repeats: list[dict[str, Any]]) -> dict[str, Any]:
    """The repeat whose p50 is the median (the lower middle one of an even count); its
    p99 is replaced by the median of the repeats' p99s, so one busy minute does not
    decide either figure."""
    ordered = sorted(repeats, key=lambda r: r["latency_ms"]["p50"])
    chosen = dict(ordered[(len(ordered) - 1) // 2])
    p99s = sorted(r["latency_ms"]["p99"] for r in repeats)
    chosen["latency_ms"] = {**chosen["latency_ms"], "p99": p99s[(len(p99s) - 1) // 2]}
    chosen["repeats"] = len(repeats)
    return chosen


def _run(settings: PlacesSettings, hosting: str) -> dict[str, Any]:
    t0 = time.perf_counter()
    s = main(settings, LocalDeployment.for_run(settings.out, LocalSettings(hosting=hosting))).to_dict()
    wall = time.perf_counter() - t0
    return {
        "wall_s": wall,
        "timings": s["timings"],
        "queries": s["queries"]["queried"],
        "latency_ms": s["queries"]["latency_ms"],
        "step_latency_ms": s["queries"]["step_latency_ms"],
        "bytes_per_query": s["bytes"]["per_query"],
        "bytes_per_frame_slot": s["bytes"]["per_frame"],
        "bytes_per_query_by_message": s["bytes"]["per_query_by_message"],
        "balance_ratio": s["shard_load"]["balance_ratio"],
        "partial_queries_per_shard": s["shard_load"]["partial_queries"],
        "missing_slots": s["queries"]["missing_slots"],
        "offline_check": s.get("offline_check"),
    }


def main_bench() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "swarm.json")
    ap.add_argument("--rate", type=float, default=2.0, help="paced run: frames per second per robot")
    ap.add_argument("--paced-frames", type=int, default=600, help="paced run: frames of the sequence")
    ap.add_argument(
        "--paced-repeats",
        type=int,
        default=3,
        help="paced runs per hosting, each after its own paced bare round trip; targets on the median "
        "(default 3)",
    )
    ap.add_argument(
        "--hostings",
        default="service,robot,robots:5",
        help="how the services are hosted, each measured (default service,robot,robots:5)",
    )
    args = ap.parse_args()
    hostings = args.hostings.split(",")
    if not TUM_ZIP.exists():
        raise SystemExit(f"the TUM constellations are needed at {TUM_ZIP}")
    result: dict[str, Any] = {
        "machine": {"python": platform.python_version(), "cpus": os.cpu_count()},
        "dataset": TUM_ZIP.name,
        "robots": 10,
    }
    with tempfile.TemporaryDirectory() as tmp:
        print("baseline: bare zenoh request/reply through a router ...", flush=True)
        result["bare_round_trip_ms"] = bare_round_trip()
        # The paced swarm's robots query every 1 / (rate x robots) s between them.
        gap = 1.0 / (args.rate * 10)
        print(f"baseline: the same, one request every {gap * 1e3:.0f} ms ...", flush=True)
        result["bare_round_trip_paced_ms"] = {"gap_ms": gap * 1e3, **bare_round_trip(300, gap)}
        print("baseline: offline decentralized evaluation ...", flush=True)
        result["offline_decentralized_wall_s"] = offline_wall(TUM_ZIP)
        tum = DatasetSource(str(TUM_ZIP))
        bare = result["bare_round_trip_ms"]["p50_ms"]
        bare_paced = result["bare_round_trip_paced_ms"]["p50_ms"]
        result["by_hosting"] = {}
        for hosting in hostings:
            name = hosting.replace(":", "-")
            print(f"[{hosting}] swarm, lock-step, whole sequence ...", flush=True)
            lock = _run(
                PlacesSettings(source=tum, robots=10, out=Path(tmp) / f"lockstep-{name}", plots=False),
                hosting,
            )
            repeats = []
            for i in range(max(1, args.paced_repeats)):
                what = f"paced at {args.rate:g} frames/s per robot ({i + 1})"
                print(f"[{hosting}] swarm, {what} ...", flush=True)
                # This repeat's own baseline, measured just before it.
                bare_here = bare_round_trip(200, gap)
                run = _run(
                    PlacesSettings(
                        source=DatasetSource(str(TUM_ZIP), frames=args.paced_frames),
                        robots=10,
                        pace=f"{args.rate:g}",
                        out=Path(tmp) / f"paced-{name}-{i}",
                        plots=False,
                    ),
                    hosting,
                )
                run["bare_round_trip_paced_ms"] = bare_here
                repeats.append(run)
            paced = median_repeat(repeats)
            paced["rate_hz_per_robot"] = args.rate
            result["by_hosting"][hosting] = {
                "lockstep": lock,
                "paced": paced,
                "paced_repeats": [
                    {
                        "latency_ms": r["latency_ms"],
                        "bare_round_trip_paced_ms": r["bare_round_trip_paced_ms"],
                        "p50_over_bare_paced": (
                            r["latency_ms"]["p50"] / r["bare_round_trip_paced_ms"]["p50_ms"]
                        ),
                    }
                    for r in repeats
                ],
                "ratios": {
                    "lockstep_wall_over_offline": lock["wall_s"] / result["offline_decentralized_wall_s"],
                    "paced_query_p50_over_bare_round_trip": paced["latency_ms"]["p50"] / bare,
                    # A query is two rounds of requests: 2 is the floor.
                    "paced_query_p50_over_paced_bare_round_trip": paced["latency_ms"]["p50"] / bare_paced,
                    "lockstep_query_p50_over_bare_round_trip": lock["latency_ms"]["p50"] / bare,
                    "bytes_per_query_over_paper_model_490": lock["bytes_per_query"] / 490.0,
                },
                "targets": targets(lock, paced),
            }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    paced_bare = result["bare_round_trip_paced_ms"]
    print(
        f"bare round trip p50 {bare:.3f} ms (one every {paced_bare['gap_ms']:.0f} ms: "
        f"{paced_bare['p50_ms']:.3f} ms); offline {result['offline_decentralized_wall_s']:.2f} s"
    )
    for hosting, r in result["by_hosting"].items():
        lock, paced = r["lockstep"], r["paced"]
        print(
            f"[{hosting}] lock-step: wall {lock['wall_s']:.1f} s (start {lock['timings']['start_s']:.1f} s, "
            f"replay {lock['timings']['replay_s']:.1f} s), query p50 {lock['latency_ms']['p50']:.2f} ms, "
            f"{lock['bytes_per_query']:.1f} B/query, balance {lock['balance_ratio']:.2f}, "
            f"identical to offline: {lock['offline_check'] and lock['offline_check']['identical']}; "
            f"paced (median of {paced['repeats']}): p50 {paced['latency_ms']['p50']:.2f} ms "
            f"({', '.join(format(x['latency_ms']['p50'], '.2f') for x in r['paced_repeats'])}), "
            f"p99 {paced['latency_ms']['p99']:.2f} ms; "
            f"targets met: {sorted(k for k, t in r['targets'].items() if t['met'])}"
        )
    print(f"written to {args.out}")


if __name__ == "__main__":
    main_bench()
