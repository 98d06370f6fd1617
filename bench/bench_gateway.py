"""What the gRPC gateway and TLS cost a client's query, measured in one run.

    python bench/bench_gateway.py --out bench/results/gateway.json

Two local swarms run side by side, one with mutual TLS on every zenoh link (the
default: the router enforces the access control, the gateway's gRPC port is TLS
with client certificates), one in the explicit insecure mode (plaintext zenoh,
plaintext gRPC). Each replays the same first frames of the synthetic world in
lock-step so its shards and verifiers hold them; then the same query
constellations are sent, one at a time, by four clients, round-robin so a
noisy neighbour on the shared cores hits all of them alike:

    zenoh/mtls      ZenohClient with the client.cli certificate -> router -> shards, verifiers
    gateway/mtls    GatewayClient (TLS) -> gateway (the same two-step query from its session)
    zenoh/insecure  as zenoh/mtls, plaintext
    gateway/insecure

A query is the shards' label ranges (``*/*/info``, scatter), then the two
steps; the gateway adds one gRPC round trip and the protobuf conversions.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import os
import platform
import statistics
import tempfile
import time
from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import numpy as np

from swarmrec.client import SwarmClient
from swarmrec.deployments.base import SwarmSpec
from swarmrec.deployments.local import LocalDeployment
from swarmrec.runtime.settings import BusSettings
from swarmrec.services.registry import WORKLOADS
from swarmrec.services.settings import DetectorSettings, PlaceSettings
from swarmrec.synthetic import OfficeConfig, generate_office, write_dataset

MODES = ("zenoh/mtls", "gateway/mtls", "zenoh/insecure", "gateway/insecure")


def _percentiles(ms: list[float]) -> dict[str, float]:
    a = np.asarray(ms)
    return {
        "p50": round(float(np.percentile(a, 50)), 3),
        "p90": round(float(np.percentile(a, 90)), 3),
        "p99": round(float(np.percentile(a, 99)), 3),
        "mean": round(float(a.mean()), 3),
        "n": len(ms),
    }


def _swarm(root: Path, dataset: Path, robots: int, security: str, stack: ExitStack) -> LocalDeployment:
    name = security.replace("/", "-")
    deployment = LocalDeployment(
        data_dir=root / name / "data",
        log_dir=root / name / "logs",
        security="insecure" if security == "insecure" else "mtls",
    )
    stack.callback(deployment.stop)
    spec = SwarmSpec(
        BusSettings(swarm=f"bench_{name}", n_robots=robots, request_timeout_s=5.0),
        WORKLOADS["places"],
        (PlaceSettings(lockstep=True), DetectorSettings(dataset=str(dataset))),
    )
    deployment.start(spec, timeout_s=180)
    deployment.wait_ready(120)
    return deployment


def _replay(deployment: LocalDeployment, steps: int) -> None:
    with deployment.client(30.0) as operator:
        for t in range(steps):
            replies = operator.step(t, timeout_s=30)
            bad = [r for r in replies if isinstance(r, Exception)]
            if bad:
                raise SystemExit(f"step {t} failed: {bad}")


def _rounds(
    clients: dict[str, SwarmClient], queries: list[Any], rounds: int
) -> Iterator[tuple[int, str, float]]:
    for rnd in range(rounds):
        for q in queries:
            for mode in MODES:
                t0 = time.perf_counter()
                result = clients[mode].query(q)
                elapsed = (time.perf_counter() - t0) * 1e3
                if not result.complete:
                    raise SystemExit(f"{mode}: partial answer {result}")
                yield rnd, mode, elapsed


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("bench/results/gateway.json"))
    parser.add_argument("--robots", type=int, default=2)
    parser.add_argument("--steps", type=int, default=40, help="lock-step frames replayed per robot first")
    parser.add_argument("--queries", type=int, default=20, help="query constellations per round")
    parser.add_argument("--rounds", type=int, default=10)
    parser.add_argument("--warmup", type=int, default=2, help="rounds dropped at the start")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory(prefix="bench-gateway-") as tmp, ExitStack() as stack:
        root = Path(tmp)
        world = generate_office(OfficeConfig(n_frames=400))
        write_dataset(world, root / "dataset")
        t0 = time.perf_counter()
        swarms = {
            sec: _swarm(root, root / "dataset", args.robots, sec, stack) for sec in ("mtls", "insecure")
        }
        start_s = time.perf_counter() - t0
        for d in swarms.values():
            _replay(d, args.steps)
        clients: dict[str, SwarmClient] = {}
        for sec, d in swarms.items():
            clients[f"zenoh/{sec}"] = stack.enter_context(d.client(10.0, role="client"))
            clients[f"gateway/{sec}"] = stack.enter_context(d.gateway_client(10.0))
        constellations = [c for c in world.sequence.constellations[: args.steps] if len(c) >= 3][
            : args.queries
        ]
        # The answers are the same whichever way they travel.
        for q in constellations[:3]:
            answers = {
                m: [(p.match_robot_id, p.match_frame_index, p.score) for p in c.query(q).matches]
                for m, c in clients.items()
            }
            if len({json.dumps(a) for a in answers.values()}) != 1:
                raise SystemExit(f"the clients disagree: {answers}")
        samples: dict[str, list[float]] = {m: [] for m in MODES}
        per_round: dict[str, list[float]] = {m: [] for m in MODES}
        current: dict[str, list[float]] = {m: [] for m in MODES}
        last = -1
        for rnd, mode, ms in _rounds(clients, constellations, args.rounds + args.warmup):
            if rnd != last:
                for m in MODES:
                    if current[m] and last >= args.warmup:
                        per_round[m].append(round(statistics.median(current[m]), 3))
                    current[m] = []
                last = rnd
            current[mode].append(ms)
            if rnd >= args.warmup:
                samples[mode].append(ms)
        for m in MODES:
            if current[m]:
                per_round[m].append(round(statistics.median(current[m]), 3))
    stats = {m: _percentiles(samples[m]) | {"round_medians_ms": per_round[m]} for m in MODES}
    p50 = {m: stats[m]["p50"] for m in MODES}
    result = {
        "what": "one client query (members + two-step read-only query) latency, ms",
        "setup": {
            "robots": args.robots,
            "frames_replayed_per_robot": args.steps,
            "queries_per_round": len(constellations),
            "rounds": args.rounds,
            "warmup_rounds": args.warmup,
            "swarms_start_s": round(start_s, 1),
        },
        "modes": stats,
        "gateway_overhead_p50_ms": {
            "mtls": round(p50["gateway/mtls"] - p50["zenoh/mtls"], 3),
            "insecure": round(p50["gateway/insecure"] - p50["zenoh/insecure"], 3),
        },
        "tls_cost_p50_ms": {
            "zenoh": round(p50["zenoh/mtls"] - p50["zenoh/insecure"], 3),
            "gateway": round(p50["gateway/mtls"] - p50["gateway/insecure"], 3),
        },
        "machine": {
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
            "zenoh": importlib.metadata.version("eclipse-zenoh"),
            "grpcio": importlib.metadata.version("grpcio"),
            "load_average_1m": round(os.getloadavg()[0], 2),
        },
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    for m in MODES:
        s = stats[m]
        print(f"{m:18} p50 {s['p50']:8.2f} ms  p99 {s['p99']:8.2f} ms  (n={s['n']})")
    print(f"gateway overhead p50: {result['gateway_overhead_p50_ms']}")
    print(f"TLS cost p50: {result['tls_cost_p50_ms']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
