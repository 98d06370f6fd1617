"""How a deployment puts services in processes (``--hosting``).

* ``service``: one process per service (the default; a service's crash is its own);
* ``robot``: one process per robot, its services sharing one zenoh session;
* ``robots:K``: one process for every K consecutive robots (simulating many robots
  on one machine; each robot keeps its own services, endpoints and metrics).

The runner does not need this (it hosts whatever it is given); deployments and the
PKI do, to start the processes and to give each its certificate.
"""

from __future__ import annotations

import json
import signal
import subprocess
from collections.abc import Iterable, Iterator
from typing import Any

from swarmrec.errors import ConfigError

__all__ = ["host_ranges", "ready_entries", "ready_events", "robots_per_process", "terminate"]


def ready_events(lines: Iterable[str]) -> Iterator[dict[str, Any]]:
    """The readiness lines (``{"event": "ready", ...}``) among a service process's stdout
    lines, as the runner and the compiled host print them; other lines are skipped."""
    for line in lines:
        try:
            msg = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(msg, dict) and msg.get("event") == "ready":
            yield msg


def ready_entries(msg: dict[str, Any]) -> list[dict[str, Any]]:
    """The services a readiness line lists (one service's line is its own entry)."""
    entries = msg.get("services", [msg])
    return [e for e in entries if isinstance(e, dict)] if isinstance(entries, list) else []


def terminate(proc: subprocess.Popen[Any], timeout_s: float = 10.0) -> int:
    """Stop a service process as its owner does: SIGTERM (it drops its liveliness token,
    finishes what it serves and exits), then SIGKILL after ``timeout_s``; its exit code."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return int(proc.returncode)


def robots_per_process(hosting: str) -> int | None:
    """None for ``service`` hosting, else how many robots one process hosts."""
    if hosting == "service":
        return None
    if hosting == "robot":
        return 1
    name, _, count = hosting.partition(":")
    if name == "robots" and count.isdigit() and int(count) >= 1:
        return int(count)
    raise ConfigError(f"hosting must be service, robot or robots:K (K >= 1), got {hosting!r}")


def host_ranges(hosting: str, robots: int) -> list[tuple[int, int]]:
    """The (first, last) robots of each hosting process of a swarm of ``robots``; none
    for ``service`` hosting."""
    k = robots_per_process(hosting)
    if k is None:
        return []
    return [(first, min(first + k, robots) - 1) for first in range(0, robots, k)]
