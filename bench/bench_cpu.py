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

``--data-plane`` picks the implementation of the kinds that have a compiled one
(the verifier; docs/dataplane.md): ``python`` (default), ``compiled``, or ``both``:
the same replay twice in this invocation, Python first, as each other's baseline.
The top-level keys are then the Python run's (as with ``python`` alone), and

* ``data_planes``: each run's figures, ``python`` and ``compiled``;
* ``python_over_compiled``: their ratios (CPU and context switches a query, whole and
  by process, thread class and user/kernel; > 1: the compiled run costs less) and the
  CPU a query the compiled run saves.

A compiled host is a process of its own: with ``robots:K`` hosting, the child each
``swarmrec host`` starts for its compiled kinds (role ``robot hosts
(swarmrec-dataplane)``); with ``service`` hosting, the ``verifier`` processes (exec'd).
Every descendant of a started process is counted under its parent's role. The
compiled host serves requests in zenoh's callbacks on its one runtime thread
(``app-0``), so its verify work is ``zenoh_runtime`` CPU; its other threads (main,
metrics) are the ``compiled`` class.

``--zenoh-runtime`` picks zenoh's runtime in the service processes (the router keeps
zenoh's pools; docs/dataplane.md): ``single`` (swarmrec's default), ``pools``, or
``both``: the last data plane's replay again on zenoh's pools, in this run; then

* ``zenoh_runtimes``: that data plane's figures, ``single`` and ``pools``;
* ``pools_over_single``: their ratios (> 1: one thread costs less).

Each run says whether its pair scores equal the offline evaluation
(``identical_to_offline``; None when they could not be compared because frames went
missing or were stored late) and what went wrong in the replay (``replay_faults``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

from swarmrec.core.presets import get_preset
from swarmrec.datasets.constellations import read_constellations
from swarmrec.datasets.labels import COCO_NAMES
from swarmrec.deployments.base import Deployment
from swarmrec.deployments.local import LocalDeployment, LocalSettings
from swarmrec.evaluation.scoring import score_decentralized
from swarmrec.evaluation.source import DatasetSource
from swarmrec.experiments.places import PlacesSettings, main
from swarmrec.experiments.places.pipeline import as_on_the_wire
from swarmrec.runtime.settings import DataPlane, ZenohRuntime

REPO = Path(__file__).resolve().parents[1]
TUM_ZIP = REPO.parent / "shared" / "data" / "tum_fr3_long_office_household_constellations.zip"
#: The names zenoh's runtime gives its threads (tokio pools); every other thread runs
#: Python, but in the compiled host (its main and metrics threads: class "compiled").
ZENOH_THREAD = re.compile(r"^(tx|rx|net|acc|app)-\d+$")
TICKS = os.sysconf("SC_CLK_TCK")
#: The compiled host's executable (swarmrec.services.compiled.BINARY).
COMPILED_EXE = "swarmrec-dataplane"
DATA_PLANES: tuple[DataPlane, ...] = ("python", "compiled")
ZENOH_RUNTIMES: tuple[ZenohRuntime, ...] = ("pools", "single")
#: The variable every service process reads its zenoh_runtime from (the router ignores it).
RUNTIME_ENV = "SWARMREC_ZENOH_RUNTIME"


@dataclass
class Threads:
    """CPU seconds (user, kernel) and context switches of a process's threads, by class."""

    cpu: dict[tuple[str, str], float] = field(default_factory=dict)  # (class, user|kernel) -> s
    switches: dict[str, int] = field(default_factory=dict)  # class -> voluntary + involuntary


def executable(pid: int) -> str:
    """The file name of ``pid``'s executable ("" when it cannot be read)."""
    try:
        return Path(os.readlink(f"/proc/{pid}/exe")).name
    except OSError:
        return ""


def read_threads(pid: int) -> Threads:
    """Every thread of ``pid`` now (threads that ended since are not counted; the
    services' threads live as long as the swarm)."""
    out = Threads()
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return out
    other = "compiled" if executable(pid) == COMPILED_EXE else "python"
    for tid in tids:
        base = f"/proc/{pid}/task/{tid}"
        try:
            comm = Path(f"{base}/comm").read_text().strip()
            stat = Path(f"{base}/stat").read_text().rsplit(")", 1)[1].split()
            status = Path(f"{base}/status").read_text()
        except OSError:
            continue  # the thread ended meanwhile
        kind = "zenoh_runtime" if ZENOH_THREAD.match(comm) else other
        # Fields 14 and 15 of stat (utime, stime), counted from after the ")" of the name.
        for part, value in (("user", int(stat[11])), ("kernel", int(stat[12]))):
            out.cpu[(kind, part)] = out.cpu.get((kind, part), 0.0) + value / TICKS
        switches = sum(int(m) for m in re.findall(r"(?:non)?voluntary_ctxt_switches:\s+(\d+)", status))
        out.switches[kind] = out.switches.get(kind, 0) + switches
    return out


def process_role(name: str) -> str:
    """A process's role from its name; ``parent/exe-pid`` names a child of ``parent``
    (the compiled host a ``swarmrec host`` starts): ``<parent's role> (exe)``."""
    if "/" in name:
        parent, child = name.split("/", 1)
        return f"{process_role(parent)} ({child.rsplit('-', 1)[0]})"
    if name.startswith("host-"):
        return "robot hosts"
    return name.rsplit("-", 1)[0]  # router-0, gateway-0, index-shard-3 (one process a service)


def descendants(parents: dict[int, int], root: int) -> list[int]:
    """Every process under ``root`` in ``parents`` (pid -> parent pid), nearest first."""
    out: list[int] = []
    frontier = [root]
    while frontier:
        frontier = sorted(pid for pid, ppid in parents.items() if ppid in frontier)
        out += frontier
    return out


def parent_pids() -> dict[int, int]:
    """pid -> parent pid of every process now."""
    out: dict[int, int] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            stat = Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        out[int(entry)] = int(stat[1])  # field 4, ppid
    return out


def snapshot(d: LocalDeployment) -> dict[str, Threads]:
    procs = {sp.name: sp.proc.pid for sp in d.procs if sp.proc.poll() is None}
    # The swarm's router, or a mesh's router per robot and its link emulator.
    for sp in d.routers or ([d.router] if d.router is not None else []):
        if sp.proc.poll() is None:
            procs[sp.name] = sp.proc.pid
    if d.mesh_links is not None and d.mesh_links.emulator.proc is not None:
        procs["toxiproxy"] = d.mesh_links.emulator.proc.pid
    parents = parent_pids()
    for name, pid in list(procs.items()):
        for child in descendants(parents, pid):
            procs[f"{name}/{executable(child) or 'child'}-{child}"] = child
    procs["replay driver (this process)"] = os.getpid()
    return {name: read_threads(pid) for name, pid in procs.items()}


def compiled_processes(snap: dict[str, Threads]) -> int:
    """Processes of ``snap`` running the compiled host (their threads of class "compiled")."""
    return sum(1 for t in snap.values() if "compiled" in t.switches)


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


def ratio(a: float | None, b: float | None) -> float | None:
    """``a / b``; None where either is missing or ``b`` is 0."""
    return a / b if a is not None and b else None


def with_children(by_role: dict[str, float]) -> dict[str, float]:
    """``by_role`` with each child's role (``parent (exe)``) added into its parent's."""
    out: dict[str, float] = {}
    for role, value in by_role.items():
        parent = role.split(" (", 1)[0]
        out[parent] = out.get(parent, 0.0) + value
    return dict(sorted(out.items()))


def compare(base: dict[str, Any], other: dict[str, Any]) -> dict[str, Any]:
    """``base / other`` of two runs' per-query figures (> 1: ``other`` costs less); a
    figure only one run has (a process role) is None."""

    def ratios(a: dict[str, float], b: dict[str, float]) -> dict[str, float | None]:
        return {k: ratio(a.get(k), b.get(k)) for k in sorted(a.keys() | b.keys())}

    def total_switches(run: dict[str, Any]) -> float:
        return float(sum(run["context_switches_per_query"].values()))

    key = "cpu_ms_per_query_by_process"
    return {
        "cpu_ms_per_query": ratio(base["cpu_ms_per_query"], other["cpu_ms_per_query"]),
        "cpu_ms_saved_per_query": base["cpu_ms_per_query"] - other["cpu_ms_per_query"],
        "context_switches_per_query": ratio(total_switches(base), total_switches(other)),
        "context_switches_per_query_by_thread": ratios(
            base["context_switches_per_query"], other["context_switches_per_query"]
        ),
        key: ratios(base[key], other[key]),
        # A compiled host started by a `swarmrec host` counted with its parent's role.
        "cpu_ms_per_query_by_process_with_children": ratios(
            with_children(base[key]), with_children(other[key])
        ),
        "cpu_ms_per_query_by_thread": ratios(
            base["cpu_ms_per_query_by_thread"], other["cpu_ms_per_query_by_thread"]
        ),
        "cpu_ms_per_query_user_kernel": ratios(
            base["cpu_ms_per_query_user_kernel"], other["cpu_ms_per_query_user_kernel"]
        ),
        "window_s": ratio(base["window_s"], other["window_s"]),
        "replay_s": ratio(base["timings"].get("replay_s"), other["timings"].get("replay_s")),
    }


def run_swarm(
    dataset: Path, hosting: str, data_plane: DataPlane, offline_s: float, runtime: ZenohRuntime = "pools"
) -> dict[str, Any]:
    """One lock-step replay of ``dataset`` through a 10-robot local swarm, accounted, every
    service process on zenoh's ``runtime`` (the router keeps its pools)."""
    marks: dict[str, Any] = {}
    saved = os.environ.get(RUNTIME_ENV)
    os.environ[RUNTIME_ENV] = runtime
    try:
        result = _run_swarm(dataset, hosting, data_plane, offline_s, marks)
    finally:
        if saved is None:
            os.environ.pop(RUNTIME_ENV, None)
        else:
            os.environ[RUNTIME_ENV] = saved
    return {**result, "zenoh_runtime": runtime}


def _run_swarm(
    dataset: Path, hosting: str, data_plane: DataPlane, offline_s: float, marks: dict[str, Any]
) -> dict[str, Any]:

    def swarm_up(d: Deployment) -> None:
        assert isinstance(d, LocalDeployment)
        marks["before"] = snapshot(d)
        marks["t0"] = time.perf_counter()

    def replay_over(d: Deployment) -> None:
        assert isinstance(d, LocalDeployment)
        marks["after"] = snapshot(d)
        marks["t1"] = time.perf_counter()

    runtime = os.environ.get(RUNTIME_ENV, "pools")
    print(
        f"swarm of 10 robots, {hosting}, lock-step, data plane {data_plane}, zenoh {runtime} ...", flush=True
    )
    with tempfile.TemporaryDirectory() as tmp:
        settings = PlacesSettings(
            source=DatasetSource(str(dataset)),
            robots=10,
            out=Path(tmp) / "run",
            plots=False,
            progress=False,
            data_plane=data_plane,
        )
        s = main(
            settings,
            LocalDeployment.for_run(settings.out, LocalSettings(hosting=hosting)),
            swarm_hook=swarm_up,
            after_replay=replay_over,
        )
    compiled = compiled_processes(marks["after"])
    if (compiled > 0) != (data_plane == "compiled"):
        raise SystemExit(f"data plane {data_plane} but {compiled} compiled host processes ran: not measured")
    queries = s.queries.queried
    acc = account(marks["before"], marks["after"], queries)
    window_s = marks["t1"] - marks["t0"]
    cores = os.cpu_count() or 1
    start_s, stop_s = s.timings.get("start_s", 0.0), s.timings.get("stop_s", 0.0)
    left_s = 10.0 - start_s - stop_s - s.timings.get("prepare_s", 0.0)
    return {
        "data_plane": data_plane,
        "compiled_host_processes": compiled,
        "queries": queries,
        # None: not compared, because a frame was missing or stored after its step (below).
        "identical_to_offline": s.offline_check.identical if s.offline_check else None,
        # Lock-step query latency (the detector's process call, end to end), ms.
        "query_latency_ms": s.queries.latency_ms,
        "replay_faults": {
            "missing_slots": s.queries.missing_slots,
            "late_frames": s.queries.late_frames,
            "failed_shard_requests": s.queries.failed_shard_requests,
            "failed_verifier_requests": s.queries.failed_verifier_requests,
            "errors": s.queries.errors[:5],
        },
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


def commit() -> str:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True, check=True
        )
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return out.stdout.strip()


def print_run(result: dict[str, Any]) -> None:
    print(
        f"[{result['data_plane']}, zenoh {result['zenoh_runtime']}] {result['queries']} queries, "
        f"identical {result['identical_to_offline']}: "
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


def print_comparison(
    py: dict[str, Any],
    comp: dict[str, Any],
    ratios: dict[str, Any],
    names: tuple[str, str] = ("python", "compiled"),
) -> None:
    def fmt(v: float | None) -> str:
        return "-" if v is None else f"{v:.2f}"

    rows: list[tuple[str, float | None, float | None, float | None]] = [
        ("CPU ms a query", py["cpu_ms_per_query"], comp["cpu_ms_per_query"], ratios["cpu_ms_per_query"]),
        (
            "context switches a query",
            sum(py["context_switches_per_query"].values()),
            sum(comp["context_switches_per_query"].values()),
            ratios["context_switches_per_query"],
        ),
    ]
    key = "cpu_ms_per_query_by_process_with_children"
    a, b = (
        with_children(py["cpu_ms_per_query_by_process"]),
        with_children(comp["cpu_ms_per_query_by_process"]),
    )
    rows += [(f"  CPU ms, {k}", a.get(k), b.get(k), ratios[key][k]) for k in ratios[key]]
    for k, r in ratios["cpu_ms_per_query_by_thread"].items():
        a_t, b_t = py["cpu_ms_per_query_by_thread"], comp["cpu_ms_per_query_by_thread"]
        rows.append((f"  CPU ms, {k} threads", a_t.get(k), b_t.get(k), r))
    rows.append(
        ("replay s", py["timings"].get("replay_s"), comp["timings"].get("replay_s"), ratios["replay_s"])
    )
    print(f"{'':34} {names[0]:>9} {names[1]:>9} {'ratio':>8}")
    for name, x, y, r in rows:
        print(f"{name:34} {fmt(x):>9} {fmt(y):>9} {fmt(r):>8}")


def main_bench() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "swarm_cpu.json")
    ap.add_argument("--hosting", default="robots:5", help="robots to a process (default robots:5)")
    ap.add_argument("--dataset", type=Path, default=TUM_ZIP)
    ap.add_argument(
        "--data-plane",
        choices=(*DATA_PLANES, "both"),
        default="python",
        help="the verifier's implementation; both: python then compiled, in this run (default python)",
    )
    ap.add_argument(
        "--zenoh-runtime",
        choices=(*ZENOH_RUNTIMES, "both"),
        default="single",
        help="zenoh's runtime in the service processes (the router keeps its pools); both: the last "
        "data plane's run again on zenoh's pools, in this run (default single, swarmrec's default)",
    )
    args = ap.parse_args()
    if not args.dataset.exists():
        raise SystemExit(f"{args.dataset} not found: this benchmark reads ../shared/data (see its README)")
    planes = DATA_PLANES if args.data_plane == "both" else (cast(DataPlane, args.data_plane),)

    print("offline evaluation (baseline) ...", flush=True)
    offline_s = offline_cpu_s(args.dataset)
    default_runtime: ZenohRuntime = "pools" if args.zenoh_runtime == "pools" else "single"
    runs = {
        plane: run_swarm(args.dataset, args.hosting, plane, offline_s, default_runtime) for plane in planes
    }
    first = runs[planes[0]]
    by_runtime: dict[str, dict[str, Any]] = {}
    if args.zenoh_runtime == "both":
        last = planes[-1]
        by_runtime = {
            "single": runs[last],
            "pools": run_swarm(args.dataset, args.hosting, last, offline_s, "pools"),
        }
    result: dict[str, Any] = {
        "machine": {"python": platform.python_version(), "cpus": os.cpu_count() or 1},
        "dataset": args.dataset.name,
        "robots": 10,
        "hosting": args.hosting,
        "commit": commit(),
        # The first run's figures (the Python one with --data-plane both) at the top level.
        **first,
    }
    if len(runs) > 1:
        result["data_planes"] = runs
        result["python_over_compiled"] = compare(runs["python"], runs["compiled"])
    if by_runtime:
        # The same data plane with zenoh's pools and on one thread, every process alike.
        result["zenoh_runtimes"] = by_runtime
        result["pools_over_single"] = compare(by_runtime["pools"], by_runtime["single"])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    for run in runs.values():
        print_run(run)
    if by_runtime:
        print_run(by_runtime["pools"])
    if len(runs) > 1:
        print_comparison(runs["python"], runs["compiled"], result["python_over_compiled"])
    if by_runtime:
        print_comparison(
            by_runtime["pools"], by_runtime["single"], result["pools_over_single"], ("pools", "single")
        )


if __name__ == "__main__":
    main_bench()
