"""The verifier endpoint alone: the Python implementation against the compiled one.

    python bench/bench_dataplane.py --out bench/results/dataplane.json

For each data plane, ``python`` and ``compiled``, side by side in this one run, a
local swarm of a router and one process, robot 0's verifier (``service`` hosting,
so the process is the verifier alone; the compiled one ``exec``s into
``swarmrec-dataplane``), is started on loopback in the explicit **insecure** mode
(no TLS: the figures are the service's, not the handshake's). Both get the same
requests in chunks of 100 taken in turn (who goes first alternating), so that load
from elsewhere on the machine falls on both alike; the other swarm meanwhile idles. A 10-robot swarm is
assumed, as in ``bench/bench_cpu.py``: the verifier stores robot 0's block of the
TUM constellations (``../shared/data``; the synthetic office when absent), as its
descriptor service would (millimetre positions), then answers the same ``M``
verify requests, the frames of robots 1..9 in lock-step order, each with the
candidates a lock-step query could name there: up to ``n_ret`` (4) of robot 0's
frames stored before that step, those sharing the most label counts with the
query (the index's semantic score). Requests are sent one at a time from this
process over a raw zenoh session (closed loop: the round trip is the latency).

Measured, per data plane:

* the verifier process's CPU per request, from ``/proc/<pid>/stat`` (utime + stime,
  clock ticks) and from every thread's ``schedstat`` (nanoseconds), and its context
  switches (every thread's, from ``status``); the router's CPU beside it;
* the round trip p50 / p99 / mean from the client;
* the floor: the same over the service's ``info`` endpoint (no payload, no work);
* the CPU it burns idle (its workers' wake-ups), per second, before the requests.

Every reply (store and verify) of the two implementations is compared byte for byte
(payload and encoding): ``identical``. The ratios are python / compiled (> 1: the
compiled verifier costs less).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import statistics
import subprocess
import tempfile
import time
from collections.abc import Iterator, Sequence
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from swarmrec.core.association import build_table
from swarmrec.core.presets import get_preset
from swarmrec.core.split import split_frames
from swarmrec.core.types import ConstellationSequence
from swarmrec.datasets.constellations import read_constellations
from swarmrec.datasets.labels import COCO_NAMES
from swarmrec.deployments.base import SwarmSpec
from swarmrec.deployments.local import LocalDeployment
from swarmrec.runtime import keys
from swarmrec.runtime.settings import BusSettings, DataPlane
from swarmrec.services.settings import PlaceSettings
from swarmrec.synthetic import OfficeConfig, generate_office, write_dataset
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import constellation_to_proto, schema_name

REPO = Path(__file__).resolve().parents[1]
TUM_ZIP = REPO.parent / "shared" / "data" / "tum_fr3_long_office_household_constellations.zip"
TICKS = os.sysconf("SC_CLK_TCK")
DATA_PLANES: tuple[DataPlane, ...] = ("python", "compiled")
ROBOTS = 10  # the swarm the requests are shaped for (bench_cpu.py's)
VERIFIER_ROBOT = 0
WARMUP = 100  # verify requests sent before measuring (not counted)
IDLE_S = 1.0
CHUNK = 100  # requests sent to one data plane before the other's turn


@dataclass(frozen=True)
class Usage:
    """A process's CPU and context switches at one moment."""

    ticks: int  # utime + stime of /proc/<pid>/stat (all threads), clock ticks
    sched_ns: int  # on-CPU time summed over the threads' schedstat, ns
    switches: int  # voluntary + involuntary, summed over the threads

    def minus(self, other: Usage) -> Usage:
        return Usage(self.ticks - other.ticks, self.sched_ns - other.sched_ns, self.switches - other.switches)


def usage(pid: int) -> Usage:
    stat = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    ticks = int(stat[11]) + int(stat[12])  # fields 14, 15: utime, stime
    sched_ns = switches = 0
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            sched_ns += int(Path(f"/proc/{pid}/task/{tid}/schedstat").read_text().split()[0])
            status = Path(f"/proc/{pid}/task/{tid}/status").read_text()
        except OSError:
            continue  # the thread ended meanwhile
        switches += sum(int(m) for m in re.findall(r"(?:non)?voluntary_ctxt_switches:\s+(\d+)", status))
    return Usage(ticks, sched_ns, switches)


def load_frames(dataset: Path | None) -> tuple[ConstellationSequence, str]:
    """The TUM constellations, else the synthetic office (written to a temporary folder)."""
    if dataset is not None and dataset.exists():
        return read_constellations(dataset, COCO_NAMES), dataset.name
    with tempfile.TemporaryDirectory() as tmp:
        write_dataset(generate_office(OfficeConfig(n_frames=2500)), Path(tmp))
        return read_constellations(Path(tmp), COCO_NAMES), "synthetic office (2500 frames)"


def workload(
    seq: ConstellationSequence, n_ret: int, n_requests: int
) -> tuple[list[pb.Constellation], list[pb.VerifyRequest]]:
    """Robot 0's frames to store, and the verify requests robots 1..9 send it (see the docstring)."""
    blocks = split_frames(len(seq), ROBOTS)
    own = blocks[VERIFIER_ROBOT]
    stores = [
        constellation_to_proto(seq.constellations[g], VERIFIER_ROBOT, f, seq.frame_ids[g])
        for f, g in enumerate(own)
    ]
    desc = build_table(seq.constellations, seq.n_labels).desc.astype(np.float64)
    stored = desc[list(own)]  # (frames, labels)
    sizes = stored.sum(axis=1)
    requests: list[pb.VerifyRequest] = []
    steps = max(len(b) for b in blocks)
    while len(requests) < n_requests:
        before = len(requests)
        for t in range(1, steps):
            for r in range(1, ROBOTS):
                if t >= len(blocks[r]) or len(requests) == n_requests:
                    continue
                g = blocks[r][t]
                q = desc[g]
                common = np.minimum(stored[: min(t, len(own))], q).sum(axis=1)
                score = common / (sizes[: common.shape[0]] + q.sum() - common + 1e-9)
                best = [int(f) for f in np.argsort(-score, kind="stable")[:n_ret] if common[f] > 0]
                if not best:
                    continue
                wire = constellation_to_proto(seq.constellations[g], r, t)
                # As the querying robot sends it (swarmrec/services/protocol.py): no frame id.
                query = pb.Constellation(
                    robot_id=r, frame_index=t, labels=wire.labels, positions_mm=wire.positions_mm
                )
                requests.append(
                    pb.VerifyRequest(
                        query_id=len(requests) + 1, query=query, candidate_frame_indices=sorted(best)
                    )
                )
        if len(requests) == before:
            raise SystemExit("no query shares a label with robot 0's frames: nothing to verify")
    return stores, requests


def get(
    session: zenoh.Session, key: str, payload: bytes | None, encoding: zenoh.Encoding | None
) -> tuple[str, bytes]:
    """One request, its one answer: (encoding, payload); an error answer is kept as such."""
    replies = list(session.get(key, payload=payload, encoding=encoding, timeout=10.0))
    if len(replies) != 1:
        raise SystemExit(f"{key}: {len(replies)} replies to one request")
    rep = replies[0]
    if rep.ok is not None:
        return str(rep.ok.encoding), rep.ok.payload.to_bytes()
    assert rep.err is not None
    return f"error {rep.err.encoding}", rep.err.payload.to_bytes()


def percentiles(times_s: list[float]) -> dict[str, float]:
    ms = np.asarray(times_s) * 1e3
    return {
        "p50_ms": float(np.percentile(ms, 50)),
        "p99_ms": float(np.percentile(ms, 99)),
        "mean_ms": float(ms.mean()),
        "max_ms": float(ms.max()),
    }


@dataclass
class Tally:
    """One endpoint of one data plane: round trips, CPU deltas and answers, summed over chunks."""

    times: list[float] = field(default_factory=list)
    used: dict[str, Usage] = field(default_factory=dict)
    answers: list[tuple[str, bytes]] = field(default_factory=list)
    wall_s: float = 0.0

    def figures(self) -> dict[str, Any]:
        n = len(self.times)
        out: dict[str, Any] = {"requests": n, "wall_s": self.wall_s, "round_trip": percentiles(self.times)}
        for name, d in self.used.items():
            out[name] = {
                # utime + stime ticks (1/SC_CLK_TCK s): a few ticks in all are a coarse figure.
                "cpu_ticks": d.ticks,
                "cpu_ms_per_request_stat": 1e3 * d.ticks / TICKS / n,
                "cpu_ms_per_request_schedstat": d.sched_ns / 1e6 / n,
                "context_switches_per_request": d.switches / n,
            }
        return out


@dataclass
class Plane:
    """A running swarm of one data plane: a router and robot 0's verifier."""

    name: DataPlane
    swarm: str
    deployment: LocalDeployment
    session: zenoh.Session
    pids: dict[str, int]
    exe: str
    dispatch: str
    start_s: float
    exit_codes: dict[str, int] = field(default_factory=dict)  # once stopped

    def key(self, endpoint: str) -> str:
        return keys.endpoint(self.swarm, "verifier", VERIFIER_ROBOT, endpoint)

    def send(
        self, endpoint: str, payloads: Sequence[bytes | None], encoding: zenoh.Encoding | None, tally: Tally
    ) -> None:
        """Send ``payloads`` one at a time (closed loop), into ``tally``."""
        key = self.key(endpoint)
        before = {name: usage(pid) for name, pid in self.pids.items()}
        t_start = time.perf_counter()
        for payload in payloads:
            t0 = time.perf_counter()
            tally.answers.append(get(self.session, key, payload, encoding))
            tally.times.append(time.perf_counter() - t0)
        tally.wall_s += time.perf_counter() - t_start
        for name, pid in self.pids.items():
            d = usage(pid).minus(before[name])
            old = tally.used.get(name, Usage(0, 0, 0))
            tally.used[name] = Usage(
                old.ticks + d.ticks, old.sched_ns + d.sched_ns, old.switches + d.switches
            )


@contextmanager
def running(plane: DataPlane, tmp: Path) -> Iterator[Plane]:
    """Start a router and robot 0's verifier served by ``plane``; stop them on exit."""
    swarm = f"bench-dataplane-{plane}"
    bus = BusSettings(swarm=swarm, n_robots=ROBOTS, data_plane=plane)
    places = PlaceSettings(n_labels=len(COCO_NAMES), lockstep=True)
    spec = SwarmSpec(bus, ("verifier",), (places,), swarm_kinds=())
    deployment = LocalDeployment(data_dir=tmp / "data", log_dir=tmp / "logs", security="insecure")
    started: Plane | None = None
    try:
        t0 = time.perf_counter()
        deployment.start_router(spec)
        sp = deployment.start_robot(VERIFIER_ROBOT, ["verifier"])[0]
        deployment.wait_started([sp], 60.0)
        with deployment.client(10.0) as client:
            client.wait_for({("verifier", VERIFIER_ROBOT)}, 30.0)
            start_s = time.perf_counter() - t0
            pid = deployment.find("verifier", VERIFIER_ROBOT).proc.pid
            assert deployment.router is not None
            exe = Path(os.readlink(f"/proc/{pid}/exe")).name
            if (exe == "swarmrec-dataplane") != (plane == "compiled"):
                raise SystemExit(f"data plane {plane} but the verifier process runs {exe}: not measured")
            pids = {"verifier": pid, "router": deployment.router.proc.pid}
            dispatch = str(sp.info.get("dispatch", ""))
            started = Plane(plane, swarm, deployment, client.session, pids, exe, dispatch, start_s)
            yield started
    finally:
        codes = deployment.stop()
        if started is not None:
            started.exit_codes = codes


def interleaved(
    planes: Sequence[Plane], endpoint: str, payloads: Sequence[bytes | None], encoding: zenoh.Encoding | None
) -> dict[str, Tally]:
    """Every plane gets every payload, in chunks taken in turn (the first plane alternating),
    so that load from elsewhere on the machine falls on both alike."""
    tallies: dict[str, Tally] = {p.name: Tally() for p in planes}
    for i, start in enumerate(range(0, len(payloads), CHUNK)):
        chunk = payloads[start : start + CHUNK]
        for p in planes if i % 2 == 0 else reversed(planes):
            p.send(endpoint, chunk, encoding, tallies[p.name])
    return tallies


def bench(
    tmp: Path, stores: list[pb.Constellation], requests: list[pb.VerifyRequest]
) -> tuple[dict[str, dict[str, Any]], dict[str, list[tuple[str, bytes]]]]:
    """Both data planes side by side: each one's figures and every store and verify answer."""
    enc_store = zenoh.Encoding.APPLICATION_PROTOBUF.with_schema(schema_name(pb.Constellation))
    enc_verify = zenoh.Encoding.APPLICATION_PROTOBUF.with_schema(schema_name(pb.VerifyRequest))
    store_payloads = [m.SerializeToString() for m in stores]
    verify_payloads = [m.SerializeToString() for m in requests]
    with ExitStack() as stack:
        planes = []
        for plane in DATA_PLANES:
            print(f"starting data plane {plane} ...", flush=True)
            planes.append(stack.enter_context(running(plane, tmp / plane)))
        print("storing, warming up, idle ...", flush=True)
        stored = interleaved(planes, "store", store_payloads, enc_store)
        for name, tally in stored.items():
            bad = [a for a in tally.answers if a[0].startswith("error")]
            if bad:
                raise SystemExit(f"{name}: {len(bad)} stores refused, the first: {bad[0]!r}")
        interleaved(planes, "verify", verify_payloads[:WARMUP], enc_verify)
        idle0 = {p.name: usage(p.pids["verifier"]) for p in planes}
        time.sleep(IDLE_S)
        idle = {p.name: usage(p.pids["verifier"]).minus(idle0[p.name]) for p in planes}
        print(f"{len(requests)} info requests, then {len(requests)} verify requests, to each ...", flush=True)
        info = interleaved(planes, "info", [None] * len(requests), None)
        verified = interleaved(planes, "verify", verify_payloads, enc_verify)
        results: dict[str, dict[str, Any]] = {}
        answers: dict[str, list[tuple[str, bytes]]] = {}
        for p in planes:
            replies = verified[p.name].answers
            errors = [a for a in replies if a[0].startswith("error")]
            matches = [
                len(pb.VerifyReply.FromString(b).matches) for e, b in replies if not e.startswith("error")
            ]
            results[p.name] = {
                "process": p.exe,
                "dispatch": p.dispatch,
                "start_s": p.start_s,
                "idle_cpu_ms_per_s": 1e3 * idle[p.name].sched_ns / 1e9 / IDLE_S,
                "store": stored[p.name].figures(),
                "info_floor": info[p.name].figures(),
                "verify": verified[p.name].figures(),
                "verify_errors": len(errors),
                "matches_per_reply_mean": statistics.fmean(matches) if matches else 0.0,
                "replies_with_a_match": sum(1 for m in matches if m),
            }
            answers[p.name] = stored[p.name].answers + replies
    for p in planes:
        results[p.name]["exit_codes"] = p.exit_codes
    return results, answers


def commit() -> str:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True, check=True
        )
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return out.stdout.strip()


def ratio(a: float, b: float) -> float | None:
    return a / b if b else None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "dataplane.json")
    ap.add_argument(
        "--dataset", type=Path, default=TUM_ZIP, help="constellations (synthetic office if absent)"
    )
    ap.add_argument("--requests", type=int, default=2000, help="verify requests (and info requests) sent (M)")
    args = ap.parse_args()
    if args.requests < 1:
        raise SystemExit("--requests must be >= 1")
    preset = get_preset("paper")
    seq, dataset = load_frames(args.dataset)
    stores, requests = workload(seq, preset.n_ret, args.requests)
    candidates = [len(r.candidate_frame_indices) for r in requests]
    objects = [len(r.query.labels) for r in requests]
    print(
        f"{dataset}: robot 0 stores {len(stores)} frames; {len(requests)} verify requests, "
        f"{statistics.fmean(candidates):.2f} candidates and "
        f"{statistics.fmean(objects):.1f} objects a request",
        flush=True,
    )
    with tempfile.TemporaryDirectory() as tmp:
        results, answers = bench(Path(tmp), stores, requests)
    py, comp = answers["python"], answers["compiled"]
    differ = [i for i, (a, b) in enumerate(zip(py, comp, strict=True)) if a != b]
    identical = not differ
    n_stores = len(stores)

    def which(i: int) -> str:
        return f"store {i}" if i < n_stores else f"verify {i - n_stores}"

    p, c = results["python"], results["compiled"]
    out = {
        "machine": {"nproc": os.cpu_count() or 1, "python": platform.python_version()},
        "commit": commit(),
        "dataset": dataset,
        "security": "insecure (no TLS, no access control: a benchmark of the service, on loopback)",
        "hosting": "service (a router and robot 0's verifier process, nothing else)",
        "swarm_robots": ROBOTS,
        "stored_frames": n_stores,
        "verify_requests": len(requests),
        "warmup_requests": min(WARMUP, len(requests)),
        "candidates_per_request_mean": statistics.fmean(candidates),
        "query_objects_per_request_mean": statistics.fmean(objects),
        "identical": identical,
        "replies_compared": len(py),
        "replies_differing": [which(i) for i in differ[:20]],
        "data_planes": results,
        "python_over_compiled": {
            "verify_cpu_ms_per_request_stat": ratio(
                p["verify"]["verifier"]["cpu_ms_per_request_stat"],
                c["verify"]["verifier"]["cpu_ms_per_request_stat"],
            ),
            "verify_cpu_ms_per_request_schedstat": ratio(
                p["verify"]["verifier"]["cpu_ms_per_request_schedstat"],
                c["verify"]["verifier"]["cpu_ms_per_request_schedstat"],
            ),
            "verify_context_switches_per_request": ratio(
                p["verify"]["verifier"]["context_switches_per_request"],
                c["verify"]["verifier"]["context_switches_per_request"],
            ),
            "verify_round_trip_p50": ratio(
                p["verify"]["round_trip"]["p50_ms"], c["verify"]["round_trip"]["p50_ms"]
            ),
            "verify_round_trip_p99": ratio(
                p["verify"]["round_trip"]["p99_ms"], c["verify"]["round_trip"]["p99_ms"]
            ),
            "info_cpu_ms_per_request_schedstat": ratio(
                p["info_floor"]["verifier"]["cpu_ms_per_request_schedstat"],
                c["info_floor"]["verifier"]["cpu_ms_per_request_schedstat"],
            ),
            "info_round_trip_p50": ratio(
                p["info_floor"]["round_trip"]["p50_ms"], c["info_floor"]["round_trip"]["p50_ms"]
            ),
            "idle_cpu": ratio(p["idle_cpu_ms_per_s"], c["idle_cpu_ms_per_s"]),
        },
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2) + "\n")

    def row(name: str, get_: Any, unit: str = "") -> None:
        a, b = get_(p), get_(c)
        r = ratio(a, b)
        print(f"{name:40} {a:>10.3f} {b:>10.3f} {'-' if r is None else f'{r:.2f}':>8} {unit}")

    print(f"{'':40} {'python':>10} {'compiled':>10} {'py/comp':>8}")
    row(
        "verify: verifier CPU a request (stat)",
        lambda x: x["verify"]["verifier"]["cpu_ms_per_request_stat"],
        "ms",
    )
    row(
        "verify: verifier CPU a request (sched)",
        lambda x: x["verify"]["verifier"]["cpu_ms_per_request_schedstat"],
        "ms",
    )
    row(
        "verify: verifier switches a request",
        lambda x: x["verify"]["verifier"]["context_switches_per_request"],
    )
    row(
        "verify: router CPU a request (sched)",
        lambda x: x["verify"]["router"]["cpu_ms_per_request_schedstat"],
        "ms",
    )
    row("verify: round trip p50", lambda x: x["verify"]["round_trip"]["p50_ms"], "ms")
    row("verify: round trip p99", lambda x: x["verify"]["round_trip"]["p99_ms"], "ms")
    row(
        "info: verifier CPU a request (sched)",
        lambda x: x["info_floor"]["verifier"]["cpu_ms_per_request_schedstat"],
        "ms",
    )
    row("info: round trip p50 (floor)", lambda x: x["info_floor"]["round_trip"]["p50_ms"], "ms")
    row("info: round trip p99 (floor)", lambda x: x["info_floor"]["round_trip"]["p99_ms"], "ms")
    row("store: round trip p50", lambda x: x["store"]["round_trip"]["p50_ms"], "ms")
    row("idle: verifier CPU a second", lambda x: x["idle_cpu_ms_per_s"], "ms")
    print(
        f"replies identical: {identical} ({len(py)} compared"
        + (f"; {len(differ)} differ, the first: {which(differ[0])})" if differ else ")")
    )


if __name__ == "__main__":
    main()
