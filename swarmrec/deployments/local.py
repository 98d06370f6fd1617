"""The local deployment: a router and every robot's services as processes on this
machine, on free loopback ports.

``hosting`` says how services share processes:

* ``service`` (default): one process per service, ``python -m swarmrec serve <kind>``
  with the flags of its configuration (:meth:`SwarmSpec.config_for`);
* ``robot``: one process per robot hosting all its services over one zenoh session
  (``swarmrec host``): calls between a robot's own services stay in the process;
* ``robots:K``: K robots per process, the simulation mode for swarms of many robots.

A process prints one JSON ``ready`` line on stdout when it serves, and its JSON logs
(stderr) go to ``<log_dir>/<name>.log`` (appended, so a restarted process's log
follows its predecessor's). A stateful service keeps its data under
``<data_dir>/robot<r>/<kind>`` whatever the hosting. Stopping sends SIGTERM to the
services, then the router, and escalates to SIGKILL for any process that does not
exit in time.

Every link is mutual TLS by default: the deployment creates the run's PKI in
``<data_dir>/pki`` (:mod:`swarmrec.deployments.identities`), each process presents
its own kind's certificate, the router enforces the access control, and
:meth:`LocalDeployment.client` connects as the operator. ``security="insecure"``
is the explicit, logged debugging mode. The per-swarm kinds (the gRPC gateway)
start after the router, on free ports: :attr:`LocalDeployment.gateway_address`.
"""

from __future__ import annotations

import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import IO, Literal

from tqdm import tqdm

from swarmrec.client import GatewayClient, ZenohClient
from swarmrec.core.association import warm_up
from swarmrec.deployments.base import SwarmSpec, SwarmStartError, config_flags
from swarmrec.deployments.identities import Security, client_tls, retire_ca_key, run_pki, security_for
from swarmrec.deployments.links import LinkEmulator, LinkSpec, Schedule, TimeUnit, read_schedule
from swarmrec.deployments.mesh import (
    KEYS_PAGE,
    MESH_PAGE,
    MeshLinks,
    MeshOperator,
    RouterView,
    key_bytes,
    link_bytes,
    message_types,
    router_views,
)
from swarmrec.deployments.metrics import Scrape, scrape
from swarmrec.deployments.radio import FloatArray, RadioGraph
from swarmrec.errors import ConfigError
from swarmrec.runtime.hosting import host_ranges, ready_entries, ready_events, robots_per_process, terminate
from swarmrec.runtime.settings import BusSettings, Component, Config, to_flags
from swarmrec.runtime.tls import tls_endpoint
from swarmrec.security.identity import SERVICE_KINDS, Identity
from swarmrec.services.settings import GatewaySettings, IndexSettings

__all__ = ["LocalDeployment", "LocalSettings", "ServiceProcess", "Topology", "free_port"]

#: How the robots' routers are laid out: one router for the swarm (star) or one per robot,
#: linked by radio range (mesh, docs/mesh.md).
Topology = Literal["star", "mesh"]


def free_port() -> int:
    """A TCP port free on loopback right now (the OS picks it). Another process may take
    it before it is used: servers that can bind port 0 and say their port should (the
    router does, :meth:`LocalDeployment.start_router`)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


@dataclass
class ServiceProcess:
    """One running process and the services it hosts: (kind, robot) pairs, the first one
    named by ``kind`` and ``robot``."""

    kind: str
    robot: int
    proc: subprocess.Popen[str]
    log_path: Path
    services: list[tuple[str, int]] = field(default_factory=list)
    ready: threading.Event = field(default_factory=threading.Event)
    info: dict[str, object] = field(default_factory=dict)
    urls: dict[tuple[str, int], str] = field(default_factory=dict)
    reader: threading.Thread | None = None

    def __post_init__(self) -> None:
        if not self.services:
            self.services = [(self.kind, self.robot)]

    @property
    def name(self) -> str:
        return f"{self.kind}-{self.robot}" if len(self.services) == 1 else self.log_path.stem

    @property
    def metrics_url(self) -> str:
        """The metrics URL of the process's first service (its only one, in ``service`` hosting)."""
        return self.urls.get((self.kind, self.robot), "")

    def release(self) -> None:
        """After the process exited: let the stdout reader finish, close the pipe."""
        if self.reader is not None:
            self.reader.join(timeout=2.0)
        if self.proc.stdout is not None:
            self.proc.stdout.close()

    def _read_stdout(self) -> None:
        assert self.proc.stdout is not None
        for msg in ready_events(self.proc.stdout):
            self.info = msg
            for e in ready_entries(msg):
                if isinstance(e.get("metrics_url"), str):
                    self.urls[(str(e.get("service")), int(e.get("robot", 0)))] = e["metrics_url"]
            self.ready.set()

    def tail(self, n: int = 15) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-n:])
        except OSError:
            return ""


def on_mesh(spec: SwarmSpec) -> SwarmSpec:
    """``spec`` for a router per robot: its index takes a member out of sight for away (in
    another part of a split team), not gone, and holds its placement (docs/mesh.md, "Partitions")."""
    index = spec.component(IndexSettings)
    if not isinstance(index, IndexSettings) or index.hold_when_away:
        return spec
    parts = tuple(c.with_(hold_when_away=True) if c is index else c for c in spec.components)
    return replace(spec, components=parts)


def _listening_port(ready: dict[str, object]) -> int:
    """The port a router's readiness line says it listens on (its first endpoint)."""
    listen = ready.get("listen")
    if isinstance(listen, list) and listen and isinstance(listen[0], str):
        port = listen[0].rsplit(":", 1)[-1].split("#", 1)[0]
        if port.isdigit() and int(port) > 0:
            return int(port)
    raise SwarmStartError(f"the router did not say which port it listens on (its readiness line: {ready})")


def _for_robots(timeout_s: float, robots: int) -> float:
    """A start-up wait grown by 3 s a robot beyond 40: on two cores a 100-robot swarm
    (50 robots a process) once took over 120 s to start."""
    return timeout_s + 3.0 * max(0, robots - 40)


@dataclass(frozen=True)
class LocalSettings:
    """How a run's swarm runs as processes on this machine (``swarmrec run``'s local flags);
    validated on construction. A run's own settings say what it replays; these say where."""

    #: How services share processes: service, robot or robots:K.
    hosting: str = "service"
    #: Every robot's emulated link (bandwidth, latency; docs/links.md); unlimited by default.
    link: LinkSpec = field(default_factory=LinkSpec)
    #: When robots go out of range (a CSV, :func:`swarmrec.deployments.links.read_schedule`).
    schedule: Path | None = None
    #: The schedule's time unit: lock-step steps or seconds from the replay's start.
    schedule_unit: TimeUnit = "step"
    #: mtls (mutual TLS and access control) or insecure (debugging).
    security: Security = "mtls"
    #: One router for the swarm (star) or one per robot, linked by radio range (mesh).
    topology: Topology = "star"
    #: The mesh's radio range in metres over the robots' positions (None: all hear all).
    radio_range_m: float | None = None

    def __post_init__(self) -> None:
        if self.security not in ("mtls", "insecure"):
            raise ConfigError(f"security must be mtls or insecure, got {self.security!r}")
        if self.topology not in ("star", "mesh"):
            raise ConfigError(f"topology must be star or mesh, got {self.topology!r}")
        if self.radio_range_m is not None and self.topology != "mesh":
            raise ConfigError("a radio range links robots to each other: it needs --topology mesh")
        if self.radio_range_m is not None and not (
            math.isfinite(self.radio_range_m) and self.radio_range_m > 0
        ):
            raise ConfigError(f"the radio range must be a distance > 0 in metres, got {self.radio_range_m}")
        if self.topology == "mesh" and (robots_per_process(self.hosting) or 1) > 1:
            raise ConfigError(
                "a mesh gives every robot its own router: use service or robot hosting, "
                "not several robots a process"
            )
        if self.topology == "mesh" and self.schedule is not None and self.schedule_unit != "step":
            raise ConfigError("a mesh's link schedule is in lock-step steps (--schedule-unit step)")
        if self.schedule_unit not in ("s", "step"):
            raise ConfigError(f"schedule_unit must be s or step, got {self.schedule_unit!r}")
        if (self.link.limited or self.schedule is not None) and (robots_per_process(self.hosting) or 1) > 1:
            raise ConfigError(
                "emulated links are per robot: use service or robot hosting, not several robots a process"
            )


class LocalDeployment:
    """A swarm as processes on this machine (see the module docstring)."""

    #: Every robot of the spec runs each of its kinds for the whole run (nobody scales them).
    fixed_size = True

    def __init__(
        self,
        *,
        data_dir: Path,
        log_dir: Path,
        router_port: int | None = None,
        hosting: str = "service",
        link: LinkSpec | None = None,
        schedule: Schedule | None = None,
        security: Security = "mtls",
        topology: Topology = "star",
        radio_range_m: float | None = None,
    ) -> None:
        self.data_dir, self.log_dir = data_dir, log_dir
        self.topology: Topology = topology
        self.radio_range_m = radio_range_m
        #: The mesh's routers (robot r's at index r), its links and the radio graph they follow.
        self.routers: list[ServiceProcess] = []
        self.router_ports: list[int] = []
        self.mesh_links: MeshLinks | None = None
        self.radio: RadioGraph | None = None
        #: How long the mesh took to start: its links (the emulator and a proxy per pair), its
        #: routers (started at once, to the last one ready), its first convergence (with the
        #: services up), in seconds.
        self.mesh_start: dict[str, float] = {}
        self.router_port = router_port
        self.security: Security = security
        self.pki_dir: Path | None = None
        self.swarm_procs: list[ServiceProcess] = []
        self.robots_per_process = robots_per_process(hosting)
        self.link = link or LinkSpec()
        self.schedule = schedule
        self.links: LinkEmulator | None = None
        if (self.link.limited or schedule is not None or topology == "mesh") and (
            self.robots_per_process or 1
        ) > 1:
            raise ConfigError(
                "emulated links and a mesh's routers are per robot: use service or robot hosting, "
                "not several robots a process"
            )
        if schedule is not None and schedule.has_pairs and topology != "mesh":
            raise ConfigError(
                "the link schedule has robot_a,robot_b rows: links between robots need --topology mesh"
            )
        self.hosting = hosting
        self.description = (
            "local processes" if hosting == "service" else f"local processes ({hosting} hosting)"
        )
        if topology == "mesh":
            self.description += ", a router per robot (mesh)"
        self.spec: SwarmSpec | None = None
        self.router: ServiceProcess | None = None
        self.procs: list[ServiceProcess] = []
        self._logs: list[IO[str]] = []
        #: Remove an earlier run's logs, placement and detections from ``data_dir`` at the start.
        self.fresh = False

    @classmethod
    def for_run(cls, out: Path, settings: LocalSettings | None = None) -> LocalDeployment:
        """The swarm of one run whose folder is ``out``: its services' data in ``out/data``,
        their logs in ``out/logs``; what an earlier run there left of its logs, placement
        and detections is removed when the swarm starts (its stores are refused then,
        :func:`~swarmrec.deployments.base.running`). Reads the link schedule now, so a bad
        one is refused before anything starts."""
        settings = settings or LocalSettings()
        schedule = (
            read_schedule(settings.schedule, unit=settings.schedule_unit) if settings.schedule else None
        )
        deployment = cls(
            data_dir=out / "data",
            log_dir=out / "logs",
            hosting=settings.hosting,
            link=settings.link,
            schedule=schedule,
            security=settings.security,
            topology=settings.topology,
            radio_range_m=settings.radio_range_m,
        )
        deployment.fresh = True
        return deployment

    @property
    def local_data_dir(self) -> Path:
        """Where the services keep their data, on this machine."""
        return self.data_dir

    @property
    def emulated_links(self) -> LocalDeployment | None:
        """This deployment when it emulates links to the star's router (a rate, a latency or a
        schedule), else None (a mesh's links between robots: :attr:`mesh`)."""
        if self.topology == "mesh":
            return None
        return self if self.link.limited or self.schedule is not None else None

    def plan_radio(self, robots: int, steps: int, positions: FloatArray | None) -> RadioGraph:
        """A mesh's radio graph for a run of ``steps`` lock-step steps, from the robots'
        positions at each step (``(steps, robots, 3)``, :func:`~swarmrec.deployments.radio.robot_positions`),
        the radio range and the link schedule; call it before :meth:`start`. ConfigError
        (one line) for a schedule naming robots the swarm lacks or with overlapping rows."""
        if self.topology != "mesh":
            raise ConfigError("only a mesh has a radio graph (--topology mesh)")
        self.radio = RadioGraph.build(
            robots,
            steps,
            positions=positions if self.radio_range_m is not None else None,
            range_m=self.radio_range_m,
            schedule=self.schedule,
            default=self.link,
        )
        return self.radio

    def services_of(self, robots: set[int]) -> set[tuple[str, int]]:
        """The (kind, robot) services this deployment runs for ``robots``."""
        return {s for sp in self.procs for s in sp.services if s[1] in robots}

    def _clear_earlier_run(self) -> None:
        """What an earlier run's services left that is not stored data: logs, the index's
        placement, the place owners' snapshots, the detectors' constellations and descriptors."""
        patterns = (
            "robot*/*/*.log",
            "robot*/*/placement.state",
            "robot*/*/owner-index.npz",
            "robot*/detector/constellations/*.txt",
            "robot*/detector/descriptors/*.npy",
        )
        for pattern in patterns:
            for old in self.data_dir.glob(pattern):
                old.unlink()

    # --- the Deployment interface ------------------------------------------------------

    @property
    def endpoint(self) -> str:
        """The router's endpoint (a mesh: robot 0's router)."""
        if self.router_port is None:
            raise ConfigError("the router has not been started")
        return self._loopback(self.router_port)

    def _loopback(self, port: int) -> str:
        if self.security == "insecure":
            return f"tcp/127.0.0.1:{port}"
        return tls_endpoint("127.0.0.1", port)

    def _gateway_says(self, field: str) -> str | None:
        """A field of the gateway's readiness line (None: no gateway ready, or no such field)."""
        for sp in self.swarm_procs:
            value = sp.info.get(field)
            if sp.kind == "gateway" and isinstance(value, str):
                return value
        return None

    @property
    def gateway_address(self) -> str:
        """The gateway's address from its readiness line (it listens on a port the OS chose)."""
        address = self._gateway_says("grpc")
        if address is None:
            raise ConfigError("the gateway has not been started, or is not ready yet")
        return address

    @property
    def live_view_url(self) -> str:
        """The gateway's live view, with its token ("" when it serves none)."""
        return self._gateway_says("web") or ""

    def client(self, timeout_s: float = 5.0, *, role: str = "operator") -> ZenohClient:
        """A client of the swarm through its router (a mesh: robot 0's; the operator of a
        mesh has a session on every robot's router, :class:`~swarmrec.deployments.mesh.MeshOperator`)."""
        if self.topology == "mesh" and role == "operator" and self.router_ports:
            return self.operator(timeout_s)  # type: ignore[return-value]  # a ZenohClient's interface
        return self._client_at(self.endpoint, timeout_s, role=role)

    def _client_at(self, endpoint: str, timeout_s: float, *, role: str = "operator") -> ZenohClient:
        spec = self._spec()
        if self.pki_dir is None:
            return ZenohClient(
                [endpoint], spec.swarm, timeout_s=timeout_s, insecure_reason="insecure deployment"
            )
        tls = client_tls(self.pki_dir, spec.swarm, "client" if role == "client" else "operator")
        return ZenohClient([endpoint], spec.swarm, timeout_s=timeout_s, tls=tls)

    def operator(self, timeout_s: float = 5.0) -> MeshOperator:
        """The mesh's operator: a session on each robot's own router (not yet opened)."""
        clients = [self._client_at(self._loopback(port), timeout_s) for port in self.router_ports]
        return MeshOperator(clients, lambda r: self.services_of({r}))

    def gateway_client(self, timeout_s: float = 5.0) -> GatewayClient:
        spec = self._spec()
        tls = client_tls(self.pki_dir, spec.swarm, "client") if self.pki_dir is not None else None
        return GatewayClient(self.gateway_address, spec.swarm, timeout_s=timeout_s, tls=tls)

    def start(self, spec: SwarmSpec, *, progress: bool = False, timeout_s: float | None = None) -> None:
        """Router first, the per-swarm kinds, then every robot's services; returns when all are ready.

        ``timeout_s`` defaults to 120 s, longer for big swarms (:func:`_for_robots`)."""
        if timeout_s is None:
            timeout_s = _for_robots(120.0, spec.robots)
        if self.fresh:
            self._clear_earlier_run()
        if self.topology == "mesh":
            spec = on_mesh(spec)
        if "verifier" in spec.kinds:
            # Compiled once here, the verifier processes load the kernels from numba's cache
            # instead of each compiling them at once.
            warm_up()
        self.start_router(spec)
        started: list[ServiceProcess] = self.start_swarm_kinds()
        if self.robots_per_process is None:
            for r in range(spec.robots):
                started += self.start_robot(r)
        else:
            for first, last in host_ranges(self.hosting, spec.robots):
                started.append(self.start_host(list(range(first, last + 1))))
        self._wait(started, timeout_s, progress=progress)

    def wait_ready(self, timeout_s: float | None = None) -> None:
        """Every started service printed its readiness line and has been routed to
        (``timeout_s``: 60 s, longer for big swarms, :func:`_for_robots`); a mesh: every
        robot's router sees exactly its component of step 0 and every service in it."""
        if timeout_s is None:
            timeout_s = _for_robots(60.0, self.spec.robots if self.spec else 0)
        self._wait(self.procs, timeout_s)
        if self.mesh_links is not None:
            with self.operator(5.0) as operator:
                waited = self.mesh_links.wait_converged(0, operator, self._router_views, timeout_s)
            self.mesh_start["converge_s"] = waited
            return
        with self.client(5.0) as client:
            running = {s for sp in self.procs if sp.proc.poll() is None for s in sp.services}
            client.wait_for(running, timeout_s)

    def metrics(self) -> Scrape:
        """Every running service's ``/metrics``, read now (the processes started with this run)."""
        return scrape(self.metrics_targets())

    def stop(self, timeout_s: float = 10.0) -> dict[str, int]:
        """Stop every service, then the router; the exit code of each."""
        codes: dict[str, int] = {}
        for sp in self.procs:
            if sp.proc.poll() is None:
                sp.proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + timeout_s
        for sp in self.procs:
            try:
                sp.proc.wait(timeout=max(deadline - time.monotonic(), 0.1))
            except subprocess.TimeoutExpired:
                sp.proc.kill()
                sp.proc.wait()
            sp.release()
            codes[sp.name] = int(sp.proc.returncode)
        if self.routers:  # a mesh: a router per robot
            for r, sp in enumerate(self.routers):
                codes[f"router-{r}"] = self.stop_process(sp, timeout_s)
        elif self.router is not None:
            codes["router"] = self.stop_process(self.router, timeout_s)
        if self.mesh_links is not None:
            self.mesh_links.emulator.stop()
            self.mesh_links = None
        if self.links is not None:
            self.links.stop()
            self.links = None
        for log in self._logs:
            log.close()
        self._logs.clear()
        if self.pki_dir is not None:
            # The run is over: its CA key leaves with it (its folder keeps the certificates).
            retire_ca_key(self.pki_dir)
        return codes

    # --- finer control (tests and fault injection) -----------------------------------

    @property
    def spec_swarm(self) -> str:
        """The name of the swarm this deployment runs."""
        return self._spec().swarm

    def _spec(self) -> SwarmSpec:
        if self.spec is None:
            raise ConfigError("start the router first (it takes the swarm spec)")
        return self.spec

    def _secured(
        self, config: Config, who: str, *, host: tuple[int, int] | None = None, router_of: int | None = None
    ) -> Config:
        """``config`` with the process's security: its kind's own certificate, for a process
        hosting robots ``host`` (first, last) the host certificate of those robots, for a
        mesh's router ``router_of`` that robot's router certificate."""
        security = security_for(self.security, self.pki_dir, who)
        if host is not None and security.security == "mtls":
            identity = Identity.host(self._spec().swarm, *host).common_name
            security = security.with_(identity=identity)
        if router_of is not None and security.security == "mtls":
            security = security.with_(identity=Identity.router(self._spec().swarm, router_of).common_name)
        return config.replace(security)

    def start_router(self, spec: SwarmSpec, timeout_s: float = 30.0) -> None:
        """The run's PKI (mutual TLS), then the router: on the port it had (a restart, or
        ``router_port`` given), else on the one the OS gives it (port 0), read from its
        readiness line: no port is chosen here and then lost to another program."""
        self.spec = spec
        if self.security == "mtls":
            # A hosting process presents a host certificate covering its robots; a robot
            # restarted alone (start_robot) presents its own robot's.
            hosts: set[tuple[int, int]] = set()
            if self.robots_per_process is not None:
                hosts = {*host_ranges(self.hosting, spec.robots), *((r, r) for r in range(spec.robots))}
            # Every kind this swarm runs gets certificates (a plugin's too), the built-in ones always.
            kinds = (*SERVICE_KINDS, *(k for k in spec.kinds if k not in SERVICE_KINDS))
            # Index shards may have ids beyond the robots (IndexSettings.max_shards): certificates too.
            index = spec.component(IndexSettings)
            ids = max(spec.robots, index.max_shards if isinstance(index, IndexSettings) else 0)
            self.pki_dir = run_pki(
                self.data_dir / "pki",
                spec.swarm,
                ids,
                hosts=sorted(hosts),
                kinds=kinds,
                robot_routers=self.topology == "mesh",
            )
        if self.topology == "mesh":
            self._start_mesh(spec, timeout_s)
            return
        fixed = self.router_port
        self.router_port = fixed or 0
        config = spec.config_for("router", 0, listen=(self.endpoint,), metrics_port=0)
        self.router = self._spawn("router", 0, config_flags(self._secured(config, "router")))
        try:
            self._wait([self.router], timeout_s)
        except SwarmStartError:
            self.router.release()
            raise
        if not fixed:
            self.router_port = _listening_port(self.router.info)
        if self.link.limited or self.schedule is not None:
            self._start_links(spec)

    def _start_links(self, spec: SwarmSpec) -> None:
        """A proxy per robot in front of the router, with the default link, then the
        schedule's state at time 0."""
        assert self.router_port is not None
        self.links = LinkEmulator(log_dir=self.log_dir)
        self.links.start()  # its API on a port the OS gives it
        for robot in range(spec.robots):
            self.links.add_robot(robot, self.router_port, self.link)
        self.apply_links(0.0)

    def _start_mesh(self, spec: SwarmSpec, timeout_s: float) -> None:
        """A router per robot, each dialling the proxies of its links to higher robots; the
        proxies pointed at the routers once they listen; the links of step 0."""
        radio = self.radio or self.plan_radio(spec.robots, 1, None)
        if radio.robots != spec.robots:
            raise ConfigError(f"the radio graph is of {radio.robots} robots, the swarm has {spec.robots}")
        t0 = time.perf_counter()
        emulator = LinkEmulator(log_dir=self.log_dir)
        emulator.start()
        self.mesh_links = MeshLinks(radio, emulator)
        self.mesh_links.create()
        self.mesh_start["links_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        self.routers = []
        for r in range(spec.robots):
            config = spec.config_for("router", r, listen=(self._loopback(0),), metrics_port=0)
            bus = config.get(BusSettings).with_(
                peers=tuple(self._loopback(p) for p in self.mesh_links.dials(r)),
                stats_keys=tuple(message_types(spec.swarm).values()),
            )
            config = self._secured(config.replace(bus), f"router-{r}", router_of=r)
            self.routers.append(self._spawn("router", r, config_flags(config)))
        try:
            self._wait(self.routers, timeout_s)
        except SwarmStartError:
            for sp in self.routers:
                sp.release()
            raise
        self.mesh_start["routers_s"] = time.perf_counter() - t0
        self.router_ports = [_listening_port(sp.info) for sp in self.routers]
        self.router, self.router_port = self.routers[0], self.router_ports[0]
        self.mesh_links.connect_to(self.router_ports)
        self.mesh_links.apply(0)

    @property
    def mesh(self) -> LocalDeployment | None:
        """This deployment when it runs a router per robot (the mesh), else None."""
        return self if self.topology == "mesh" else None

    def step_links(self, t: int, operator: MeshOperator) -> tuple[list[str], float | None]:
        """Put the mesh's links in step ``t``'s state and, when any changed, wait until every
        robot's router sees exactly its component; what changed, and the seconds waited
        (None: nothing changed)."""
        if self.mesh_links is None:
            raise ConfigError("the mesh has not been started")
        events = self.mesh_links.apply(t)
        if not events:
            return [], None
        return events, self.mesh_links.wait_converged(t, operator, self._router_views)

    def _router_scrape(self, page: str = "") -> Scrape:
        """Every router's metrics page, or (``page`` "/mesh") its cheap page of links alone,
        or ("/keys") its page with the bytes by message type."""
        targets = {("router", sp.robot): sp.metrics_url + page for sp in self.routers if sp.metrics_url}
        return scrape(targets, parallel=8)

    def _router_views(self) -> dict[int, RouterView]:
        return router_views(self._router_scrape(MESH_PAGE))

    def link_bytes(self) -> dict[tuple[int, int], tuple[float, float]]:
        """Bytes on each link between two robots' routers so far
        (:func:`~swarmrec.deployments.mesh.link_bytes`)."""
        return link_bytes(self._router_scrape(), self._spec().swarm)

    def type_bytes(self) -> dict[tuple[str, str], float]:
        """Payload bytes by message type summed over the links so far, from every router's
        ``/keys`` page (:func:`~swarmrec.deployments.mesh.key_bytes`); read it while the
        links do not change (before and after a replay)."""
        return key_bytes(self._router_scrape(KEYS_PAGE), self._spec().swarm)

    def robot_endpoint(self, robot: int) -> str:
        """Where ``robot``'s services connect: its own router (a mesh), its link's proxy, or
        the router itself."""
        if self.router_ports:
            return self._loopback(self.router_ports[robot])
        if self.links is not None and robot in self.links.ports:
            port = self.links.ports[robot]
            # The proxy forwards bytes: TLS goes through it end to end, to the router.
            return f"tcp/127.0.0.1:{port}" if self.security == "insecure" else tls_endpoint("127.0.0.1", port)
        return self.endpoint

    def apply_links(self, t: float) -> list[str]:
        """Put every robot's link in the schedule's state at ``t`` (its unit); what changed."""
        if self.links is None or self.schedule is None:
            return []
        default = dict.fromkeys(self.links.ports, self.link)
        return self.links.apply(self.schedule.state_at(t), default)

    def start_swarm_kinds(self) -> list[ServiceProcess]:
        """The spec's per-swarm kinds (the gateway, on a free gRPC port); does not wait."""
        spec = self._spec()
        started = []
        for kind in spec.swarm_kinds:
            config = spec.config_for(kind, 0, connect=(self.endpoint,), metrics_port=0)
            if config.has(GatewaySettings):
                # Port 0: the OS picks it while binding; the readiness line says which.
                config = config.replace(config.get(GatewaySettings).with_(grpc_port=0))
            sp = self._spawn(kind, 0, config_flags(self._secured(config, kind)))
            self.procs.append(sp)
            self.swarm_procs.append(sp)
            started.append(sp)
        return started

    def service_flags(self, kind: str, robot: int) -> list[str]:
        """The flags ``kind`` of ``robot`` is started with."""
        config = self._spec().config_for(
            kind,
            robot,
            connect=(self.robot_endpoint(robot),),
            data_dir=self.data_dir / f"robot{robot}" / kind,
            metrics_port=0,
        )
        return config_flags(self._secured(config, f"{kind}-{robot}"))

    def start_robot(self, robot: int, kinds: Sequence[str] | None = None) -> list[ServiceProcess]:
        """Start ``kinds`` (default: the spec's) of ``robot``, a process each or (``robot``
        hosting) one process for them all; does not wait."""
        spec = self._spec()
        if self.robots_per_process is not None:
            return [self.start_host([robot], kinds)]
        started = [self._spawn(k, robot, self.service_flags(k, robot)) for k in (kinds or spec.kinds)]
        self.procs.extend(started)
        return started

    def start_host(self, robots: Sequence[int], kinds: Sequence[str] | None = None) -> ServiceProcess:
        """One ``swarmrec host`` process for ``kinds`` of ``robots``; does not wait."""
        spec = self._spec()
        kinds = list(kinds or spec.kinds)
        parts: dict[type, Component] = {}
        for kind in kinds:
            config = spec.config_for(
                kind,
                robots[0],
                connect=(self.robot_endpoint(robots[0]),),
                data_dir=self.data_dir,
                metrics_port=0,
            )
            config = self._secured(config, f"host of robots {robots}", host=(robots[0], robots[-1]))
            for part in config.parts:
                parts.setdefault(type(part), part)
        flags = [flag for part in parts.values() for flag in to_flags(part, only_changed=True)]
        ids = ",".join(map(str, robots))
        name = f"host-r{robots[0]}" if len(robots) == 1 else f"host-r{robots[0]}-{robots[-1]}"
        sp = self._spawn_command(
            ["host", "--kinds", ",".join(kinds), "--robots", ids, *flags],
            name,
            kinds[0],
            robots[0],
            [(k, r) for r in robots for k in kinds],
        )
        self.procs.append(sp)
        return sp

    def wait_started(self, procs: Sequence[ServiceProcess], timeout_s: float = 60.0) -> None:
        """Return when each of ``procs`` printed its readiness line."""
        self._wait(procs, timeout_s)

    def _spawn(self, kind: str, robot: int, flags: list[str]) -> ServiceProcess:
        return self._spawn_command(["serve", kind, *flags], f"{kind}-{robot}", kind, robot, [(kind, robot)])

    def _spawn_command(
        self, args: list[str], name: str, kind: str, robot: int, services: list[tuple[str, int]]
    ) -> ServiceProcess:
        self.log_dir.mkdir(parents=True, exist_ok=True)
        log_path = self.log_dir / f"{name}.log"
        log = log_path.open("a", encoding="utf-8")
        self._logs.append(log)
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        proc = subprocess.Popen(
            [sys.executable, "-m", "swarmrec", *args],
            stdout=subprocess.PIPE,
            stderr=log,
            text=True,
            env=env,
            start_new_session=True,  # a Ctrl-C in the terminal reaches the main job only
        )
        sp = ServiceProcess(kind, robot, proc, log_path, services)
        sp.reader = threading.Thread(target=sp._read_stdout, daemon=True, name=f"stdout-{sp.name}")
        sp.reader.start()
        return sp

    def _wait(self, procs: Sequence[ServiceProcess], timeout_s: float, progress: bool = False) -> None:
        deadline = time.monotonic() + timeout_s
        with tqdm(total=len(procs), desc="starting services", disable=not progress, leave=False) as bar:
            pending = list(procs)
            while pending:
                for sp in list(pending):
                    if sp.ready.is_set():
                        pending.remove(sp)
                        bar.update(1)
                    elif sp.proc.poll() is not None:
                        raise SwarmStartError(
                            f"{sp.name} exited with code {sp.proc.returncode} before it was ready; "
                            f"its log ({sp.log_path}) ends:\n{sp.tail()}"
                        )
                if pending and time.monotonic() > deadline:
                    names = ", ".join(sp.name for sp in pending)
                    raise SwarmStartError(f"not ready after {timeout_s:g} s: {names}")
                if pending:
                    time.sleep(0.05)

    def metrics_targets(self) -> dict[tuple[str, int], str]:
        """``/metrics`` URL of every service still running, by (kind, robot)."""
        return {key: url for sp in self.procs if sp.proc.poll() is None for key, url in sp.urls.items()}

    def find(self, kind: str, robot: int) -> ServiceProcess:
        """The running process that hosts ``kind`` of ``robot``."""
        for sp in self.procs:
            if (kind, robot) in sp.services and sp.proc.poll() is None:
                return sp
        raise KeyError(f"no running {kind}-{robot}")

    def stop_process(self, sp: ServiceProcess, timeout_s: float = 10.0) -> int:
        """SIGTERM, wait, then SIGKILL; returns the exit code."""
        code = terminate(sp.proc, timeout_s)
        sp.release()
        return code

    def __enter__(self) -> LocalDeployment:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
