"""Realistic links between robots: bandwidth, latency and outages, by a real link emulator.

Every robot's services reach the router through a TCP proxy of their own, run by
Toxiproxy (built from its Go module, ``github.com/Shopify/toxiproxy/v2``, into the
project's cache: :func:`toxiproxy_binary`). A robot's link is then what its proxy
makes of it:

* ``rate_kbps``: a bandwidth toxic in each direction (kilobytes per second);
* ``latency_ms``: a latency toxic in each direction (so a request/reply between two
  robots crosses four: up and down through each robot's link);
* an outage: the proxy is disabled, its connections close, and zenoh reconnects
  when it is enabled again.

A **schedule** (:func:`read_schedule`) says when robots are out of range, as
multi-robot datasets publish their communication graphs: a CSV of ``start, end,
robot`` rows (times in seconds from the start of the replay, or in lock-step steps),
with optional ``rate_kbps`` and ``latency_ms`` columns that change a robot's link for
that interval instead of cutting it. Linux ``netem`` is not available on these
machines' kernels and ``tc`` token buckets shape bandwidth only; a proxy gives both
rate and delay on loopback, per robot.
"""

from __future__ import annotations

import csv
import json
import math
import os
import shutil
import subprocess
import time
import urllib.error
import urllib.request
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from swarmrec.deployments.errors import DeploymentError
from swarmrec.errors import ConfigError, DatasetError, MalformedLineError

__all__ = [
    "TOXIPROXY_MODULE",
    "TOXIPROXY_VERSION",
    "LinkEmulator",
    "LinkSpec",
    "Outage",
    "Schedule",
    "read_schedule",
    "toxiproxy_binary",
]

TOXIPROXY_MODULE = "github.com/Shopify/toxiproxy/v2/cmd/server"
TOXIPROXY_VERSION = "v2.5.0"
TimeUnit = Literal["s", "step"]


@dataclass(frozen=True)
class LinkSpec:
    """One robot's link to the rest of the swarm (None: not limited)."""

    rate_kbps: float | None = None
    latency_ms: float | None = None

    def __post_init__(self) -> None:
        for name in ("rate_kbps", "latency_ms"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value >= 0):
                raise ConfigError(f"{name} must be a number >= 0, got {value}")
        if self.rate_kbps == 0:
            raise ConfigError("rate_kbps 0 is an outage: write it as a schedule interval")

    @property
    def limited(self) -> bool:
        return self.rate_kbps is not None or self.latency_ms is not None


@dataclass(frozen=True)
class Outage:
    """Robot ``robot`` out of range (``link`` None) or on ``link`` during ``[start, end)``."""

    start: float
    end: float
    robot: int
    link: LinkSpec | None = None


@dataclass(frozen=True)
class Schedule:
    """When robots' links change, in ``unit`` (seconds from the replay's start, or steps)."""

    intervals: tuple[Outage, ...]
    unit: TimeUnit = "s"

    def state_at(self, t: float) -> dict[int, LinkSpec | None]:
        """Robots whose link is changed at ``t``: out of range (None) or on another link."""
        out: dict[int, LinkSpec | None] = {}
        for o in self.intervals:
            if o.start <= t < o.end:
                # An outage wins over a changed link in the same instant.
                out[o.robot] = None if (o.link is None or out.get(o.robot, o.link) is None) else o.link
        return out

    def changes(self) -> list[float]:
        """Every instant the state changes, in order."""
        return sorted({t for o in self.intervals for t in (o.start, o.end)})


def read_schedule(path: Path, *, unit: TimeUnit = "s") -> Schedule:
    """A schedule CSV: a header naming ``start, end, robot`` and optionally ``rate_kbps``,
    ``latency_ms``; a row with neither is an outage. Errors name the file and line."""
    if unit not in ("s", "step"):
        raise ConfigError(f"schedule unit must be s or step, got {unit!r}")
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as e:
        raise DatasetError(path, f"cannot read the schedule: {e.strerror}") from None
    rows = csv.DictReader(line for line in text.splitlines() if line.strip() and not line.startswith("#"))
    need = {"start", "end", "robot"}
    if rows.fieldnames is None or not need <= {f.strip() for f in rows.fieldnames}:
        raise DatasetError(path, f"the header must name {', '.join(sorted(need))} (got {rows.fieldnames})", 1)
    intervals = []
    for number, row in enumerate(rows, start=2):
        clean = {k.strip(): (v or "").strip() for k, v in row.items() if k}
        try:
            start, end, robot = float(clean["start"]), float(clean["end"]), int(clean["robot"])
            rate = float(clean["rate_kbps"]) if clean.get("rate_kbps") else None
            latency = float(clean["latency_ms"]) if clean.get("latency_ms") else None
            link = LinkSpec(rate, latency) if rate is not None or latency is not None else None
        except (ValueError, ConfigError) as e:
            raise MalformedLineError(path, f"not a schedule row: {e}", number) from None
        if not (math.isfinite(start) and math.isfinite(end) and 0 <= start < end) or robot < 0:
            raise MalformedLineError(path, f"need 0 <= start < end and a robot id >= 0, got {clean}", number)
        intervals.append(Outage(start, end, robot, link))
    return Schedule(tuple(intervals), unit)


def toxiproxy_binary(cache: Path | None = None) -> Path:
    """The Toxiproxy server, built from its Go module into the project's cache on first use."""
    root = cache or Path(os.environ.get("SWARMREC_CACHE", Path.home() / ".cache" / "swarmrec"))
    target = root / "toxiproxy" / TOXIPROXY_VERSION
    binary = target / "server"
    if binary.is_file():
        return binary
    go = shutil.which("go")
    if go is None:
        raise DeploymentError("building Toxiproxy needs Go (https://go.dev); none is on the PATH")
    target.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, GOBIN=str(target), GOFLAGS="-mod=mod")
    proc = subprocess.run(
        [go, "install", f"{TOXIPROXY_MODULE}@{TOXIPROXY_VERSION}"],
        capture_output=True,
        text=True,
        env=env,
        timeout=900,
        check=False,
    )
    if proc.returncode != 0 or not binary.is_file():
        raise DeploymentError(
            f"go install {TOXIPROXY_MODULE}@{TOXIPROXY_VERSION} failed:\n{proc.stderr[-2000:]}"
        )
    return binary


def listening_ports(pid: int) -> set[int]:
    """The TCP ports process ``pid`` listens on (IPv4 and IPv6), from /proc: its sockets'
    inodes matched against the kernel's socket tables. Empty where /proc does not say
    (not Linux, or the process gone)."""
    try:
        fds = os.listdir(f"/proc/{pid}/fd")
    except OSError:
        return set()
    inodes = set()
    for fd in fds:
        try:
            link = os.readlink(f"/proc/{pid}/fd/{fd}")
        except OSError:
            continue  # closed meanwhile (the listing's own descriptor, for one)
        if link.startswith("socket:["):
            inodes.add(link[len("socket:[") : -1])
    ports: set[int] = set()
    for table in ("tcp", "tcp6"):
        try:
            lines = Path(f"/proc/{pid}/net/{table}").read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            fields = line.split()
            # local address (hex ip:port), state 0A = LISTEN, inode
            if len(fields) > 9 and fields[3] == "0A" and fields[9] in inodes:
                ports.add(int(fields[1].rsplit(":", 1)[1], 16))
    return ports


class LinkEmulator:
    """A Toxiproxy server and one proxy per robot in front of the router."""

    def __init__(self, *, log_dir: Path, binary: Path | None = None) -> None:
        self.binary = binary or toxiproxy_binary()
        self.log_dir = log_dir
        self.proc: subprocess.Popen[bytes] | None = None
        self.api = ""
        self.ports: dict[int, int] = {}
        self.links: dict[int, LinkSpec] = {}
        self.cut: set[int] = set()

    def start(self, api_port: int = 0, timeout_s: float = 20.0) -> None:
        """The server, its API on ``api_port``; 0 (the default): a port the OS gives it, read
        back from the kernel's table of the process's listening sockets (Toxiproxy logs the
        port it was given, not the one it got), so no port is chosen here and lost."""
        self.log_dir.mkdir(parents=True, exist_ok=True)
        log = (self.log_dir / "toxiproxy.log").open("ab")
        self.proc = subprocess.Popen(
            [str(self.binary), "-host", "127.0.0.1", "-port", str(api_port)],
            stdout=log,
            stderr=log,
            start_new_session=True,
        )
        log.close()
        deadline = time.monotonic() + timeout_s
        while True:
            port = api_port or next(iter(sorted(listening_ports(self.proc.pid))), 0)
            if port:
                self.api = f"http://127.0.0.1:{port}"
                try:
                    self._call("GET", "/version")
                    return
                except DeploymentError:
                    pass
            if self.proc.poll() is not None or time.monotonic() > deadline:
                raise DeploymentError(f"Toxiproxy did not start; see {self.log_dir / 'toxiproxy.log'}")
            time.sleep(0.05)

    def _call(self, method: str, path: str, body: Mapping[str, Any] | None = None) -> Any:
        data = json.dumps(body).encode() if body is not None else None
        request = urllib.request.Request(self.api + path, data=data, method=method)
        request.add_header("Content-Type", "application/json")
        try:
            with urllib.request.urlopen(request, timeout=5.0) as resp:
                text = resp.read().decode() or "null"
        except (urllib.error.URLError, OSError) as e:
            raise DeploymentError(f"Toxiproxy {method} {path}: {e}") from None
        try:
            return json.loads(text)
        except json.JSONDecodeError:
            return text  # /version answers plain text

    def add_robot(self, robot: int, router_port: int, link: LinkSpec) -> str:
        """A proxy for ``robot`` to the router, on a port the OS gives it (Toxiproxy binds port
        0 and names the port it got); returns the endpoint its services use."""
        name = f"robot-{robot}"
        made = self._call(
            "POST",
            "/proxies",
            {
                "name": name,
                "listen": "127.0.0.1:0",
                "upstream": f"127.0.0.1:{router_port}",
                "enabled": True,
            },
        )
        listen = made.get("listen", "") if isinstance(made, dict) else ""
        port = str(listen).rpartition(":")[2]
        if not port.isdigit() or int(port) == 0:
            raise DeploymentError(f"Toxiproxy did not say where robot {robot}'s proxy listens: {made!r}")
        self.ports[robot] = int(port)
        self.set_link(robot, link)
        return f"tcp/127.0.0.1:{port}"

    def set_link(self, robot: int, link: LinkSpec) -> None:
        """Replace ``robot``'s toxics by those of ``link`` (both directions)."""
        name = f"robot-{robot}"
        for toxic in self._call("GET", f"/proxies/{name}/toxics"):
            self._call("DELETE", f"/proxies/{name}/toxics/{toxic['name']}")
        for stream in ("upstream", "downstream"):
            if link.latency_ms is not None:
                attrs = {"latency": round(link.latency_ms), "jitter": 0}
                self._toxic(name, f"latency-{stream}", "latency", stream, attrs)
            if link.rate_kbps is not None:
                self._toxic(
                    name, f"rate-{stream}", "bandwidth", stream, {"rate": max(1, round(link.rate_kbps))}
                )
        self.links[robot] = link

    def _toxic(self, proxy: str, name: str, kind: str, stream: str, attributes: Mapping[str, int]) -> None:
        body = {"name": name, "type": kind, "stream": stream, "toxicity": 1.0, "attributes": dict(attributes)}
        self._call("POST", f"/proxies/{proxy}/toxics", body)

    def set_connected(self, robot: int, connected: bool) -> None:
        """Cut ``robot``'s link (its connections close) or restore it."""
        self._call("POST", f"/proxies/robot-{robot}", {"enabled": connected})
        if connected:
            self.cut.discard(robot)
        else:
            self.cut.add(robot)

    def apply(self, state: Mapping[int, LinkSpec | None], default: Mapping[int, LinkSpec]) -> list[str]:
        """Make every robot's link what ``state`` says (robots absent from it: their default);
        returns what changed, for the report."""
        events = []
        for robot in sorted(self.ports):
            want = state.get(robot, default.get(robot, LinkSpec()))
            if want is None:
                if robot not in self.cut:
                    self.set_connected(robot, False)
                    events.append(f"robot {robot} out of range")
                continue
            if robot in self.cut:
                self.set_connected(robot, True)
                events.append(f"robot {robot} back in range")
            if self.links.get(robot) != want:
                self.set_link(robot, want)
                events.append(f"robot {robot} link {want}")
        return events

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.proc = None


def robots_of(schedule: Schedule) -> Iterable[int]:
    return sorted({o.robot for o in schedule.intervals})
