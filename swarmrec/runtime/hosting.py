"""How a deployment puts services in processes (``--hosting``).

* ``service``: one process per service (the default; a service's crash is its own);
* ``robot``: one process per robot, its services sharing one zenoh session;
* ``robots:K``: one process for every K consecutive robots (simulating many robots
  on one machine; each robot keeps its own services, endpoints and metrics).

The runner does not need this (it hosts whatever it is given); deployments and the
PKI do, to start the processes and to give each its certificate.
"""

from __future__ import annotations

import signal
import subprocess
from typing import Any

from swarmrec.errors import ConfigError

__all__ = ["host_ranges", "robots_per_process", "terminate"]


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
