"""Where a lock-step query's CPU goes: the 10-robot TUM swarm, accounted from /proc.

    python bench/bench_cpu.py --out bench/results/swarm_cpu.json

Issue 17 asks for a whole 10-robot TUM run under 10 s. This benchmark says what a
query costs the machine, so the gap can be reasoned about rather than guessed: it
replays the TUM constellations in lock-step through a local swarm (``--hosting``,
default ``robots:5``: the fastest hosting of ``bench/bench_swarm.py``), reads every
process's and thread's CPU time and context switches from ``/proc`` when the swarm
is up and again when the replay is over, and divides by the queries in between.

CPU is split three ways:

* by process: the robots' host processes, the router, the gateway, and the process
  that drives the replay (this one);
* by thread: threads that run Python (the services' workers and zenoh's callback
  threads; Linux names them all ``python``) against zenoh's own runtime threads
  (``tx-*``, ``rx-*``, ``net-*``, ``acc-*``, ``app-*``: I/O, routing, TLS);
* user against kernel time.

Baseline, in the same run: the CPU the offline decentralized evaluation of the
same sequence takes in one process, per query (``swarm / offline``).
``budget_for_10_s`` is the CPU a query could cost for the replay to fit in what
the 10 s target leaves after this run's start and stop, on this machine's cores.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from swarmrec.core.presets import get_preset
from swarmrec.datasets.constellations import read_constellations
from swarmrec.datasets.labels import COCO_NAMES
from swarmrec.datasets.source import DatasetSource
from swarmrec.deployments.base import Deployment
from swarmrec.deployments.local import LocalDeployment
from swarmrec.evaluation.scoring import score_decentralized
from swarmrec.experiments.places import PlacesSettings, main
from swarmrec.experiments.places.pipeline import as_on_the_wire

REPO = Path(__file__).resolve().parents[1]
TUM_ZIP = REPO.parent / "shared" / "data" / "tum_fr3_long_office_household_constellations.zip"
#: The names zenoh's runtime gives its threads (tokio pools); every other thread runs Python.
ZENOH_THREAD = re.compile(r"^(tx|rx|net|acc|app)-\d+$")
TICKS = os.sysconf("SC_CLK_TCK")


@dataclass
class Threads:
    """CPU seconds (user, kernel) and context switches of a process's threads, by class."""

    cpu: dict[tuple[str, str], float] = field(default_factory=dict)  # (class, user|kernel) -> s
    switches: dict[str, int] = field(default_factory=dict)  # class -> voluntary + involuntary


def read_threads(pid: int) -> Threads:
    """Every thread of ``pid`` now (threads that ended since are not counted; the
    services' threads live as long as the swarm)."""
    out = Threads()
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return out
    for tid in tids:
        base = f"/proc/{pid}/task/{tid}"
        try:
            comm = Path(f"{base}/comm").read_text().strip()
            stat = Path(f"{base}/stat").read_text().rsplit(")", 1)[1].split()
            status = Path(f"{base}/status").read_text()
        except OSError:
            continue  # the thread ended meanwhile
        kind = "zenoh_runtime" if ZENOH_THREAD.match(comm) else "python"
        # Fields 14 and 15 of stat (utime, stime), counted from after the ")" of the name.
        for part, value in (("user", int(stat[11])), ("kernel", int(stat[12]))):
            out.cpu[(kind, part)] = out.cpu.get((kind, part), 0.0) + value / TICKS
        switches = sum(int(m) for m in re.findall(r"(?:non)?voluntary_ctxt_switches:\s+(\d+)", status))
        out.switches[kind] = out.switches.get(kind, 0) + switches
    return out


def process_role(name: str) -> str:
    if name.startswith("host-"):
        return "robot hosts"
    return name.rsplit("-", 1)[0]  # router-0, gateway-0, index-shard-3 (one process a service)


def snapshot(d: LocalDeployment) -> dict[str, Threads]:
    procs = {sp.name: sp.proc.pid for sp in d.procs if sp.proc.poll() is None}
    if d.router is not None:
        procs[d.router.name] = d.router.proc.pid
    procs["replay driver (this process)"] = os.getpid()
    return {name: read_threads(pid) for name, pid in procs.items()}


def offline_cpu_s(seq_path: Path) -> float:
    t0 = time.process_time()
    seq = as_on_the_wire(read_constellations(seq_path, COCO_NAMES))
    score_decentralized(seq, 10, get_preset("paper"))
    return time.process_time() - t0


def account(before: dict[str, Threads], after: dict[str, Threads], queries: int) -> dict[str, Any]:
    """Per query: CPU ms by process role, by thread class and by user/kernel; switches."""
    by_role: dict[str, float] = {}
    by_thread: dict[str, float] = {}
    by_part: dict[str, float] = {}
    switches: dict[str, int] = {}
    for name, end in after.items():
        start = before.get(name, Threads())
        role = "replay driver" if name.startswith("replay driver") else process_role(name)
        for key, value in end.cpu.items():
            delta = value - start.cpu.get(key, 0.0)
            kind, part = key
            by_role[role] = by_role.get(role, 0.0) + delta
            by_thread[kind] = by_thread.get(kind, 0.0) + delta
            by_part[part] = by_part.get(part, 0.0) + delta
        for kind, n in end.switches.items():
            switches[kind] = switches.get(kind, 0) + n - start.switches.get(kind, 0)
    total = sum(by_role.values())

    def per_query_ms(d: dict[str, float]) -> dict[str, float]:
        return {k: 1e3 * v / queries for k, v in sorted(d.items())}

    return {
        "cpu_s": total,
        "cpu_ms_per_query": 1e3 * total / queries,
        "cpu_ms_per_query_by_process": per_query_ms(by_role),
        "cpu_ms_per_query_by_thread": per_query_ms(by_thread),
        "cpu_ms_per_query_user_kernel": per_query_ms(by_part),
        "context_switches_per_query": {k: v / queries for k, v in sorted(switches.items())},
    }


def main_bench() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "swarm_cpu.json")
    ap.add_argument("--hosting", default="robots:5", help="robots to a process (default robots:5)")
    ap.add_argument("--dataset", type=Path, default=TUM_ZIP)
    args = ap.parse_args()
    if not args.dataset.exists():
        raise SystemExit(f"{args.dataset} not found: this benchmark reads ../shared/data (see its README)")
    marks: dict[str, Any] = {}

    def swarm_up(d: Deployment) -> None:
        assert isinstance(d, LocalDeployment)
        marks["before"] = snapshot(d)
        marks["t0"] = time.perf_counter()

    def replay_over(d: Deployment) -> None:
        assert isinstance(d, LocalDeployment)
        marks["after"] = snapshot(d)
        marks["t1"] = time.perf_counter()

    print("offline evaluation (baseline) ...", flush=True)
    offline_s = offline_cpu_s(args.dataset)
    print(f"swarm of 10 robots, {args.hosting}, lock-step ...", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        settings = PlacesSettings(
            source=DatasetSource(str(args.dataset)),
            robots=10,
            hosting=args.hosting,
            out=Path(tmp) / "run",
            plots=False,
            progress=False,
        )
        s = main(settings, swarm_hook=swarm_up, after_replay=replay_over)
    queries = s.queries.queried
    acc = account(marks["before"], marks["after"], queries)
    window_s = marks["t1"] - marks["t0"]
    cores = os.cpu_count() or 1
    start_s, stop_s = s.timings.get("start_s", 0.0), s.timings.get("stop_s", 0.0)
    left_s = 10.0 - start_s - stop_s - s.timings.get("prepare_s", 0.0)
    result = {
        "machine": {"python": platform.python_version(), "cpus": cores},
        "dataset": args.dataset.name,
        "robots": 10,
        "hosting": args.hosting,
        "queries": queries,
        "identical_to_offline": s.offline_check.identical if s.offline_check else None,
        "timings": s.timings,
        "window_s": window_s,
        "cores_busy": acc["cpu_s"] / window_s,
        **acc,
        "offline_cpu_ms_per_query": 1e3 * offline_s / queries,
        "swarm_over_offline": acc["cpu_s"] / offline_s,
        # The CPU a query may cost for the replay to fit in what 10 s leave after this
        # run's preparation, start and stop, with every core busy all the time.
        "budget_for_10_s": {
            "replay_s_left": left_s,
            "cpu_ms_per_query": 1e3 * max(left_s, 0.0) * cores / queries,
        },
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(
        f"{queries} queries, identical {result['identical_to_offline']}: "
        f"{result['cpu_ms_per_query']:.1f} ms of CPU a query ({result['cores_busy']:.2f} cores busy), "
        f"offline {result['offline_cpu_ms_per_query']:.2f} ms; "
        f"a 10 s run allows {result['budget_for_10_s']['cpu_ms_per_query']:.1f} ms"
    )
    for title, key in (
        ("by process", "cpu_ms_per_query_by_process"),
        ("by thread", "cpu_ms_per_query_by_thread"),
        ("user / kernel", "cpu_ms_per_query_user_kernel"),
        ("context switches a query", "context_switches_per_query"),
    ):
        print(f"  {title}: " + ", ".join(f"{k} {v:.2f}" for k, v in result[key].items()))


if __name__ == "__main__":
    main_bench()
