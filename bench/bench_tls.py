"""What mutual TLS and the access control cost: request/reply through a router.

    python bench/bench_tls.py --out bench/results/tls.json

Three processes per mode, as in a swarm: a router, a service answering at
``verifier/0/verify`` (256 B replies, on its own key) and this process as the
caller, one request at a time. The modes are measured in the same run,
round-robin so that a noisy neighbour on the shared cores hits all of them:

    tcp       plaintext, no authentication (today's swarm)
    tls       mutual TLS, every node with a certificate of the swarm CA
    tls+acl   mutual TLS and the router's default-deny ACL of a 10-robot swarm

It also times opening a client session (TCP connect, or the TLS handshake
with both certificates checked), which a service pays once at start.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import os
import platform
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from swarmrec.deployments.local import free_port
from swarmrec.runtime import keys
from swarmrec.runtime.tls import TlsFiles, configure_client_tls, tls_endpoint
from swarmrec.security.acl import access_control
from swarmrec.security.pki import PkiSettings, init_pki

SWARM = "bench"
ROBOTS = 10
MODES = ("tcp", "tls", "tls+acl")
KEY = keys.endpoint(SWARM, "verifier", 0, "verify")

# Run in a child process: a router (role "router") or the answering service (role "server").
_CHILD = """
import json, signal, sys, threading
from pathlib import Path
import zenoh
from swarmrec.security.acl import access_control, configure_access_control
from swarmrec.runtime.tls import TlsFiles, configure_client_tls, configure_router_tls

a = json.loads(sys.argv[1])
stop = threading.Event()
signal.signal(signal.SIGTERM, lambda *_: stop.set())
conf = zenoh.Config()
conf.insert_json5("scouting/multicast/enabled", "false")
tls = a["mode"] != "tcp"
if a["role"] == "router":
    conf.insert_json5("mode", '"router"')
    if tls:
        configure_router_tls(conf, TlsFiles.in_dir(Path(a["pki"]), "router." + a["swarm"]), [a["endpoint"]])
    else:
        conf.insert_json5("listen/endpoints", json.dumps([a["endpoint"]]))
    if a["mode"] == "tls+acl":
        acl = access_control(a["swarm"], a["robots"], clients=["cli"], operators=["job"])
        configure_access_control(conf, acl)
else:
    conf.insert_json5("mode", '"client"')
    if tls:
        files = TlsFiles.in_dir(Path(a["pki"]), "r0.verifier." + a["swarm"])
        configure_client_tls(conf, files, [a["endpoint"]])
    else:
        conf.insert_json5("connect/endpoints", json.dumps([a["endpoint"]]))
payload = bytes(a["size"])
with zenoh.open(conf) as session:
    if a["role"] == "server":
        def serve(q):
            q.reply(a["key"], payload)  # its own concrete key: what the ACL lets through
        queryable = session.declare_queryable(a["key"].rsplit("/", 1)[0] + "/*", serve)
    print(json.dumps({"event": "ready"}), flush=True)
    stop.wait()
"""


@contextmanager
def child(role: str, mode: str, endpoint: str, pki: Path, size: int) -> Iterator[None]:
    args = {
        "role": role,
        "mode": mode,
        "endpoint": endpoint,
        "pki": str(pki),
        "swarm": SWARM,
        "robots": ROBOTS,
        "key": KEY,
        "size": size,
    }
    proc = subprocess.Popen(
        [sys.executable, "-c", _CHILD, json.dumps(args)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert proc.stdout is not None
        if '"ready"' not in proc.stdout.readline():
            raise RuntimeError(f"{role} ({mode}) exited with {proc.wait()}")
        yield
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        if proc.stdout is not None:
            proc.stdout.close()


def caller_config(mode: str, endpoint: str, pki: Path) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    if mode == "tcp":
        conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    else:
        configure_client_tls(conf, TlsFiles.in_dir(pki, f"client.cli.{SWARM}"), [endpoint])
    return conf


def one_request(session: zenoh.Session) -> float:
    t0 = time.perf_counter()
    replies = list(session.get(KEY, timeout=5.0))
    dt = time.perf_counter() - t0
    if len(replies) != 1 or replies[0].ok is None:
        raise RuntimeError(f"expected one reply, got {len(replies)}")
    return dt


def measure(mode: str, pki: Path, n: int, warmup: int, opens: int, size: int) -> dict[str, list[float]]:
    endpoint = tls_endpoint("127.0.0.1", free_port()) if mode != "tcp" else f"tcp/127.0.0.1:{free_port()}"
    with ExitStack() as stack:
        stack.enter_context(child("router", mode, endpoint, pki, size))
        stack.enter_context(child("server", mode, endpoint, pki, size))
        open_s = []
        for _ in range(opens):
            t0 = time.perf_counter()
            with zenoh.open(caller_config(mode, endpoint, pki)):
                open_s.append(time.perf_counter() - t0)
        with zenoh.open(caller_config(mode, endpoint, pki)) as session:
            querier = session.declare_querier(KEY)
            deadline = time.monotonic() + 10
            while not querier.matching_status.matching:  # type: ignore[attr-defined]  # a MatchingStatus, not bool as the stub says
                if time.monotonic() > deadline:
                    raise RuntimeError("the service never became reachable")
                time.sleep(0.01)
            querier.undeclare()  # type: ignore[no-untyped-call]  # untyped in zenoh's stub
            for _ in range(warmup):
                one_request(session)
            return {"request_s": [one_request(session) for _ in range(n)], "open_s": open_s}


def summary(seconds: list[float]) -> dict[str, float]:
    us = np.asarray(seconds) * 1e6
    return {
        "n": int(us.size),
        "p50_us": round(float(np.percentile(us, 50)), 1),
        "p90_us": round(float(np.percentile(us, 90)), 1),
        "p99_us": round(float(np.percentile(us, 99)), 1),
        "mean_us": round(float(us.mean()), 1),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--requests", type=int, default=3000, help="per mode and round")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--warmup", type=int, default=300)
    ap.add_argument("--opens", type=int, default=20, help="session opens timed per mode and round")
    ap.add_argument("--size", type=int, default=256, help="reply payload bytes")
    args = ap.parse_args()
    requests: dict[str, list[float]] = {m: [] for m in MODES}
    opens: dict[str, list[float]] = {m: [] for m in MODES}
    per_round: dict[str, list[float]] = {m: [] for m in MODES}
    with tempfile.TemporaryDirectory() as tmp:
        pki = Path(tmp) / "pki"
        init_pki(PkiSettings(swarm=SWARM, robots=ROBOTS, out=pki))
        for r in range(args.rounds):
            order = MODES[r % len(MODES) :] + MODES[: r % len(MODES)]
            for mode in order:
                got = measure(mode, pki, args.requests, args.warmup, args.opens, args.size)
                requests[mode] += got["request_s"]
                opens[mode] += got["open_s"]
                per_round[mode].append(summary(got["request_s"])["p50_us"])
                print(f"round {r} {mode:8} p50 {per_round[mode][-1]:7.1f} us", flush=True)
    modes: dict[str, dict[str, Any]] = {
        m: {
            "request_reply": summary(requests[m]),
            "p50_us_per_round": per_round[m],
            "session_open_ms_median": round(statistics.median(opens[m]) * 1e3, 2),
        }
        for m in MODES
    }
    base: dict[str, float] = modes["tcp"]["request_reply"]
    result: dict[str, Any] = {
        "machine": {
            "platform": platform.platform(),
            "python": platform.python_version(),
            "cpus": os.cpu_count(),
            "eclipse-zenoh": importlib.metadata.version("eclipse-zenoh"),
        },
        "setup": {
            "processes": "router, answering service and caller: three processes on loopback",
            "reply_bytes": args.size,
            "requests_per_mode": args.requests * args.rounds,
            "rounds": args.rounds,
            "acl": f"default deny, {ROBOTS} robots x 5 kinds + 1 client + 1 operator, "
            f"{len(access_control(SWARM, ROBOTS, clients=['cli'], operators=['job'])['rules'])} rules",
            "key_type": "EC P-256",
        },
        "modes": modes,
        "against_tcp": {
            m: {
                "p50": round(modes[m]["request_reply"]["p50_us"] / base["p50_us"], 3),
                "p99": round(modes[m]["request_reply"]["p99_us"] / base["p99_us"], 3),
            }
            for m in MODES
        },
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    for m in MODES:
        s = modes[m]["request_reply"]
        ratio = result["against_tcp"][m]["p50"]
        print(
            f"{m:8} p50 {s['p50_us']:7.1f} us  p99 {s['p99_us']:7.1f} us  "
            f"open {modes[m]['session_open_ms_median']:.2f} ms  ({ratio:.2f}x tcp p50)"
        )


if __name__ == "__main__":
    main()
