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
import itertools
import json
import math
import os
import random
import shutil
import socket
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
    """Robot ``robot`` out of range (``link`` None) or on ``link`` during ``[start, end)``;
    with ``peer``, only the link between ``robot`` and ``peer`` (a pair row, ``robot < peer``:
    the mesh topology, docs/mesh.md)."""

    start: float
    end: float
    robot: int
    link: LinkSpec | None = None
    peer: int | None = None

    @property
    def subject(self) -> tuple[int, ...]:
        """The robot, or the pair, the row is about."""
        return (self.robot,) if self.peer is None else (self.robot, self.peer)


@dataclass(frozen=True)
class Schedule:
    """When robots' links change, in ``unit`` (seconds from the replay's start, or steps)."""

    intervals: tuple[Outage, ...]
    unit: TimeUnit = "s"

    @property
    def has_pairs(self) -> bool:
        """Whether a row is about a pair of robots (only a mesh has links between robots)."""
        return any(o.peer is not None for o in self.intervals)

    def check(self, robots: int) -> None:
        """ConfigError, in one line, for a row naming a robot outside ``0..robots-1`` or two
        rows about the same robot (or pair) whose intervals overlap."""
        for o in self.intervals:
            unknown = [r for r in o.subject if r >= robots]
            if unknown:
                raise ConfigError(
                    f"the link schedule names robot {unknown[0]}, but the swarm has robots 0..{robots - 1}"
                )
        by_subject: dict[tuple[int, ...], list[Outage]] = {}
        for o in self.intervals:
            by_subject.setdefault(o.subject, []).append(o)
        for subject, rows in by_subject.items():
            rows.sort(key=lambda o: o.start)
            for a, b in itertools.pairwise(rows):
                if b.start < a.end:
                    who = f"robot {subject[0]}" if len(subject) == 1 else f"robots {subject[0]}-{subject[1]}"
                    raise ConfigError(
                        f"the link schedule has overlapping rows for {who}: "
                        f"[{a.start:g}, {a.end:g}) and [{b.start:g}, {b.end:g})"
                    )

    def pairs_at(self, t: float) -> dict[tuple[int, int], LinkSpec | None]:
        """Pairs whose link is changed at ``t`` by a pair row: cut (None) or on another link."""
        return {
            (o.robot, o.peer): o.link for o in self.intervals if o.peer is not None and o.start <= t < o.end
        }

    def state_at(self, t: float) -> dict[int, LinkSpec | None]:
        """Robots whose link is changed at ``t``: out of range (None) or on another link
        (rows about one robot; pair rows: :meth:`pairs_at`)."""
        out: dict[int, LinkSpec | None] = {}
        for o in self.intervals:
            if o.peer is None and o.start <= t < o.end:
                # An outage wins over a changed link in the same instant.
                out[o.robot] = None if (o.link is None or out.get(o.robot, o.link) is None) else o.link
        return out

    def changes(self) -> list[float]:
        """Every instant the state changes, in order."""
        return sorted({t for o in self.intervals for t in (o.start, o.end)})


def read_schedule(path: Path, *, unit: TimeUnit = "s") -> Schedule:
    """A schedule CSV: a header naming ``start, end`` and ``robot`` or ``robot_a, robot_b``
    (or all three: a row fills one or the other), and optionally ``rate_kbps``,
    ``latency_ms``; a row with neither is an outage. A ``robot_a, robot_b`` row is about the
    link between two robots (the mesh topology). Errors name the file and line."""
    if unit not in ("s", "step"):
        raise ConfigError(f"schedule unit must be s or step, got {unit!r}")
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as e:
        raise DatasetError(path, f"cannot read the schedule: {e.strerror}") from None
    rows = csv.DictReader(line for line in text.splitlines() if line.strip() and not line.startswith("#"))
    header = {f.strip() for f in rows.fieldnames or ()}
    if not ({"start", "end"} <= header and ("robot" in header or {"robot_a", "robot_b"} <= header)):
        raise DatasetError(
            path, f"the header must name start, end and robot or robot_a, robot_b (got {rows.fieldnames})", 1
        )
    intervals = []
    for number, row in enumerate(rows, start=2):
        clean = {k.strip(): (v or "").strip() for k, v in row.items() if k}
        try:
            start, end = float(clean["start"]), float(clean["end"])
            robot, peer = _row_subject(clean)
            rate = float(clean["rate_kbps"]) if clean.get("rate_kbps") else None
            latency = float(clean["latency_ms"]) if clean.get("latency_ms") else None
            link = LinkSpec(rate, latency) if rate is not None or latency is not None else None
        except (ValueError, ConfigError) as e:
            raise MalformedLineError(path, f"not a schedule row: {e}", number) from None
        if not (math.isfinite(start) and math.isfinite(end) and 0 <= start < end) or robot < 0:
            raise MalformedLineError(path, f"need 0 <= start < end and a robot id >= 0, got {clean}", number)
        intervals.append(Outage(start, end, robot, link, peer))
    return Schedule(tuple(intervals), unit)


def _row_subject(row: Mapping[str, str]) -> tuple[int, int | None]:
    """A row's robot, or its pair (lower id first); ValueError for neither, both, or a robot
    paired with itself."""
    one = row.get("robot", "")
    a, b = row.get("robot_a", ""), row.get("robot_b", "")
    if one and not (a or b):
        return int(one), None
    if a and b and not one:
        lo, hi = sorted((int(a), int(b)))
        if lo == hi:
            raise ValueError(f"robot_a and robot_b are both {lo}")
        return lo, hi
    raise ValueError("a row names either robot or both robot_a and robot_b")


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


def reserved_port(taken: set[int] | None = None) -> int:
    """A loopback port free now, below the range the OS gives out for port 0 and for outgoing
    connections (``ip_local_port_range``): a proxy that closes and opens again (a mesh's link,
    cut and healed) finds it still free, since only an explicit bind could take it. A port
    from the OS's range was seen taken by an outgoing connection while its proxy was closed."""
    try:
        low = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        low = 32768
    taken = taken if taken is not None else set()
    start = max(1024, low - 16384)
    for port in random.Random().sample(range(start, low), k=min(4096, low - start)):
        if port in taken:
            continue
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
            try:
                sock.bind(("127.0.0.1", port))
            except OSError:
                continue
        taken.add(port)
        return port
    raise DeploymentError(f"no free loopback port in {start}..{low - 1} for a link's proxy")


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

    def add_proxy(self, name: str, upstream_port: int, listen_port: int = 0) -> int:
        """A proxy ``name`` to ``upstream_port`` on loopback, listening on ``listen_port``, by
        default a port the OS gives it (Toxiproxy binds port 0 and names the port it got);
        returns that port."""
        made = self._call(
            "POST",
            "/proxies",
            {
                "name": name,
                "listen": f"127.0.0.1:{listen_port}",
                "upstream": f"127.0.0.1:{upstream_port}",
                "enabled": True,
            },
        )
        listen = made.get("listen", "") if isinstance(made, dict) else ""
        port = str(listen).rpartition(":")[2]
        if not port.isdigit() or int(port) == 0:
            raise DeploymentError(f"Toxiproxy did not say where proxy {name} listens: {made!r}")
        return int(port)

    def set_upstream(self, name: str, upstream_port: int) -> None:
        """Point proxy ``name`` at ``upstream_port`` (a router that started after its proxy)."""
        self._call("POST", f"/proxies/{name}", {"upstream": f"127.0.0.1:{upstream_port}"})

    def set_enabled(self, name: str, enabled: bool) -> None:
        """Open proxy ``name``, or close it and every connection through it."""
        self._call("POST", f"/proxies/{name}", {"enabled": enabled})

    def add_robot(self, robot: int, router_port: int, link: LinkSpec) -> str:
        """A proxy for ``robot`` to the router; returns the endpoint its services use."""
        port = self.add_proxy(f"robot-{robot}", router_port)
        self.ports[robot] = port
        self.set_link(robot, link)
        return f"tcp/127.0.0.1:{port}"

    def set_link(self, robot: int, link: LinkSpec) -> None:
        """Replace ``robot``'s toxics by those of ``link`` (both directions)."""
        self.set_toxics(f"robot-{robot}", link)
        self.links[robot] = link

    def set_toxics(self, name: str, link: LinkSpec) -> None:
        """Replace proxy ``name``'s toxics by those of ``link`` (both directions)."""
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

    def _toxic(self, proxy: str, name: str, kind: str, stream: str, attributes: Mapping[str, int]) -> None:
        body = {"name": name, "type": kind, "stream": stream, "toxicity": 1.0, "attributes": dict(attributes)}
        self._call("POST", f"/proxies/{proxy}/toxics", body)

    def set_connected(self, robot: int, connected: bool) -> None:
        """Cut ``robot``'s link (its connections close) or restore it."""
        self.set_enabled(f"robot-{robot}", connected)
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
