"""What every deployment does, and what it is asked to run.

A :class:`SwarmSpec` says what a swarm is: its bus settings (name, robot count,
timeouts), the service kinds each robot runs (a workload of the registry) and
the settings components they share (place recognition, the detector's dataset,
fusion ...). A :class:`Deployment` runs a spec somewhere (local processes, a
compose project, a Kubernetes namespace) behind five calls::

    deployment.start(spec)        # or check that the swarm already running is this spec
    deployment.wait_ready()       # every service's liveliness token is up
    deployment.endpoint           # the router endpoint a client connects to
    deployment.client()           # a zenoh client of the swarm, as the operator (drives replays)
    deployment.gateway_address    # grpc://host:port of the swarm's gRPC gateway
    deployment.metrics()          # the services' counters of this run
    deployment.stop()             # exit codes of what it started

and says what it can do beyond that: whether every robot runs the whole spec for the
whole run (``fixed_size``), where the services' data is readable on this machine
(``local_data_dir``, local processes only) and whether it emulates links
(``emulated_links``). Experiments (:mod:`swarmrec.experiments`) take a deployment and
never ask which kind it is.
"""

from __future__ import annotations

import json
import os
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from swarmrec.client import GatewayClient, ZenohClient
from swarmrec.deployments.errors import DeploymentError, SwarmStartError
from swarmrec.deployments.identities import client_tls
from swarmrec.deployments.links import LinkSpec, Schedule
from swarmrec.deployments.mesh import MeshOperator
from swarmrec.deployments.metrics import Scrape
from swarmrec.deployments.radio import FloatArray, RadioGraph
from swarmrec.errors import ConfigError
from swarmrec.runtime.settings import BusSettings, Component, Config, StorageSettings, to_env, to_flags
from swarmrec.runtime.tls import TlsFiles
from swarmrec.services import registry

__all__ = [
    "AttachFile",
    "AttachedSwarm",
    "Deployment",
    "DeploymentError",
    "EmulatedLinks",
    "SwarmSession",
    "SwarmSpec",
    "SwarmStartError",
    "announce_live_view",
    "check_running",
    "config_env",
    "config_flags",
    "numerics_env",
    "read_attach_json",
    "running",
    "shared_env",
]


@dataclass(frozen=True)
class SwarmSpec:
    """A swarm to deploy: a router, the per-swarm ``swarm_kinds`` (the gRPC gateway), and on
    each of ``bus.n_robots`` robots the ``kinds``."""

    bus: BusSettings
    kinds: tuple[str, ...]
    #: Settings shared by the robots' services; a kind takes the components it reads
    #: (the registry says which) and the defaults of any not given.
    components: tuple[Component, ...] = ()
    #: The workload's name (``places``, ``landmarks``): compose files and reports show it.
    workload: str = ""
    #: Per-service overrides: ``{(kind, robot): (components...)}`` (a test's one odd robot).
    overrides: dict[tuple[str, int], tuple[Component, ...]] = field(default_factory=dict)
    #: Kinds that run once for the swarm beside the router.
    swarm_kinds: tuple[str, ...] = ("gateway",)

    def __post_init__(self) -> None:
        for kind in self.kinds:
            if registry.spec(kind).scope != "robot":
                raise ConfigError(f"{kind} runs once per swarm, not on each robot")
        for kind in self.swarm_kinds:
            if registry.spec(kind).scope != "swarm" or kind == "router":
                raise ConfigError(f"{kind} is not a per-swarm kind besides the router")
        kinds = [type(c) for c in self.components]
        if len(set(kinds)) != len(kinds):
            raise ConfigError("a settings component appears twice in the swarm spec")

    @property
    def robots(self) -> int:
        return self.bus.n_robots

    @property
    def swarm(self) -> str:
        return self.bus.swarm

    def expected(self) -> set[tuple[str, int]]:
        """Every (kind, robot) the swarm runs besides the router (a per-swarm kind on robot 0)."""
        return {(k, r) for r in range(self.robots) for k in self.kinds} | {(k, 0) for k in self.swarm_kinds}

    def component(self, kind: type[Component]) -> Component | None:
        return next((c for c in self.components if type(c) is kind), None)

    def config_for(
        self,
        kind: str,
        robot: int,
        *,
        connect: tuple[str, ...] = (),
        listen: tuple[str, ...] = (),
        data_dir: Path | None = None,
        metrics_port: int | None = None,
        metrics_host: str | None = None,
    ) -> Config:
        """The whole configuration of ``kind`` on ``robot`` (the router: robot 0)."""
        entry = registry.spec(kind)
        bus_changes: dict[str, object] = {"robot": robot}
        for name, value in (("connect", connect), ("listen", listen)):
            if value:
                bus_changes[name] = value
        if metrics_port is not None:
            bus_changes["metrics_port"] = metrics_port
        if metrics_host is not None:
            bus_changes["metrics_host"] = metrics_host
        if entry.zenoh_mode is not None:
            bus_changes["mode"] = entry.zenoh_mode
        parts: list[Component] = [self.bus.with_(**bus_changes)]
        special = {type(c): c for c in self.overrides.get((kind, robot), ())}
        for comp in entry.all_components[1:]:
            given = special.get(comp) or self.component(comp) or comp()
            if isinstance(given, StorageSettings) and data_dir is not None:
                given = given.with_(data_dir=data_dir)
            parts.append(given)
        return Config(tuple(parts))


def config_flags(config: Config) -> list[str]:
    """Command-line flags that reproduce ``config`` for ``swarmrec serve`` (settings at
    their defaults left out: the command line shows what this service has of its own)."""
    return [flag for part in config.parts for flag in to_flags(part, only_changed=True)]


def config_env(config: Config) -> dict[str, str]:
    """``SWARMREC_*`` variables that reproduce ``config`` (a container's environment; settings
    at their defaults left out)."""
    out: dict[str, str] = {}
    for part in config.parts:
        out.update(to_env(part, only_changed=True))
    return out


def numerics_env() -> dict[str, str]:
    """This machine's OpenBLAS settings (``OPENBLAS_CORETYPE`` ...), for every container and pod:
    OpenBLAS picks its kernels by them, and with them the last bits of a solve or a decomposition
    (a SLAM team's estimates differed from run_dgs's by 1e-14 without them), so the services
    compute as the run's offline check on this machine does (lock-step identity is bit for bit).
    None set: each container or pod detects its CPU, as this machine does."""
    return {k: v for k, v in sorted(os.environ.items()) if k.startswith("OPENBLAS_")}


@dataclass(frozen=True, kw_only=True)
class AttachFile:
    """``swarm.json``: what a client on this machine needs to attach to a swarm that runs
    (``swarmrec run --attach DIR``), whatever runs it. Each deployment that leaves a swarm
    running writes one, adding where the swarm runs (a compose project, a Kubernetes
    namespace); ``deployment`` says which, so one reader opens any of them
    (:func:`swarmrec.deployments.attach.attach`)."""

    #: Which deployment wrote it: ``compose`` or ``kubernetes``.
    deployment: str
    swarm: str
    robots: int
    workload: str
    kinds: list[str]
    #: The router, from this machine (``tls/host:port``).
    router_endpoint: str
    #: The Prometheus server that scrapes every service, from this machine.
    prometheus_url: str
    #: ``grpc://host:port`` of the swarm's gRPC gateway, from this machine.
    gateway_address: str = ""
    #: The gateway's live view (a web page of the swarm), with its token; "" when none.
    live_view_url: str = ""
    #: mtls or insecure; with mtls, the PKI on this machine (the client's and operator's identities).
    security: str = "mtls"
    pki_dir: str = ""
    #: The experiment's own record (its dataset on this machine, preset, ...), to re-run it.
    experiment: dict[str, Any] = field(default_factory=dict)
    #: The settings every robot's services share (what the spec said), to check a run against.
    shared_env: dict[str, str] = field(default_factory=dict)


def read_attach_json(folder: Path) -> dict[str, Any]:
    """``folder/swarm.json`` as JSON (whichever deployment wrote it); ConfigError, saying how
    to start one, when there is none or it is not a swarm file."""
    path = folder / "swarm.json"
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(
            f"{path} not found: no swarm is kept there (start one: swarmrec up --out {folder}, "
            f"swarmrec compose up --out {folder} or swarmrec k8s up --out {folder})"
        ) from None
    except json.JSONDecodeError as e:
        raise ConfigError(f"{path} is not a swarm file: {e}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path} is not a swarm file: not a JSON object")
    return data


class AttachedSwarm:
    """A client's side of a swarm left running, from its attach file (``folder/swarm.json``):
    what the deployments that attach to one (compose, a local swarm kept up) share."""

    folder: Path
    info: AttachFile
    #: Started elsewhere: its services may have been scaled or restarted since.
    fixed_size = False
    local_data_dir = None
    emulated_links = None
    mesh = None

    @property
    def endpoint(self) -> str:
        return self.info.router_endpoint

    @property
    def gateway_address(self) -> str:
        if not self.info.gateway_address:
            raise ConfigError(f"the swarm in {self.folder} runs no gateway")
        return self.info.gateway_address

    def _tls(self, role: str) -> TlsFiles | None:
        if self.info.security == "insecure" or not self.info.pki_dir:
            return None
        return client_tls(
            Path(self.info.pki_dir), self.info.swarm, "client" if role == "client" else "operator"
        )

    def client(self, timeout_s: float = 5.0, *, role: str = "operator") -> ZenohClient:
        tls = self._tls(role)
        reason = "" if tls is not None else f"{self.folder / 'swarm.json'} says security insecure"
        return ZenohClient(
            [self.endpoint], self.info.swarm, timeout_s=timeout_s, tls=tls, insecure_reason=reason
        )

    def gateway_client(self, timeout_s: float = 5.0) -> GatewayClient:
        tls = self._tls("client")
        return GatewayClient(self.gateway_address, self.info.swarm, timeout_s=timeout_s, tls=tls)


class EmulatedLinks(Protocol):
    """A deployment's emulated links between the robots and the router (docs/links.md)."""

    #: Every robot's link when the schedule says nothing else.
    link: LinkSpec
    #: When robots go out of range; None: the links never change.
    schedule: Schedule | None

    def apply_links(self, t: float) -> list[str]:
        """Put every link in the schedule's state at ``t`` (its unit); what changed."""
        ...

    def services_of(self, robots: set[int]) -> set[tuple[str, int]]:
        """The (kind, robot) services run for ``robots`` (those to wait for when they are back)."""
        ...


class RadioMesh(Protocol):
    """A deployment's router per robot, linked by radio range (docs/mesh.md)."""

    #: The radio graph its links follow (None until planned or started).
    radio: RadioGraph | None
    #: Seconds its start took, by part (links, routers, converge).
    mesh_start: dict[str, float]

    def plan_radio(self, robots: int, steps: int, positions: FloatArray | None) -> RadioGraph:
        """The radio graph of a run of ``steps`` lock-step steps; before the swarm starts."""
        ...

    def step_links(self, t: int, operator: MeshOperator) -> tuple[list[str], float | None]:
        """Step ``t``'s links, converged; what changed and the seconds waited (None: nothing)."""
        ...

    def link_bytes(self) -> dict[tuple[int, int], tuple[float, float]]:
        """Bytes on each link so far, ``{(a, b): (a to b, b to a)}``."""
        ...

    def type_bytes(self) -> dict[tuple[str, str], float]:
        """The payload bytes of each (message type, zenoh message) summed over every link so
        far; read while the links do not change."""
        ...


class Deployment(Protocol):
    """Where a swarm runs; see the module docstring."""

    #: One line for reports: "local processes", "compose project swarmrec", ...
    description: str

    @property
    def fixed_size(self) -> bool:
        """Every robot of the spec runs each of its kinds for the whole run (False where an
        operator may scale a kind, or the swarm was started elsewhere)."""
        ...

    @property
    def local_data_dir(self) -> Path | None:
        """Where the services keep their data, when that is on this machine; else None."""
        ...

    @property
    def emulated_links(self) -> EmulatedLinks | None:
        """The links it emulates; None when the robots reach the router as the network lets them."""
        ...

    @property
    def mesh(self) -> RadioMesh | None:
        """Its router per robot, linked by radio range; None for one router (the star)."""
        ...

    def start(self, spec: SwarmSpec, *, progress: bool = False) -> None:
        """Start ``spec`` (or check that the swarm already running is ``spec``)."""
        ...

    @property
    def endpoint(self) -> str:
        """The router endpoint a client on this machine connects to."""
        ...

    @property
    def gateway_address(self) -> str:
        """``grpc://host:port`` of the swarm's gRPC gateway, from this machine."""
        ...

    def client(self, timeout_s: float = 5.0, *, role: str = "operator") -> ZenohClient:
        """A zenoh client of the swarm with the identity of ``role`` (operator: may drive replays;
        client: reads only), not yet opened."""
        ...

    def gateway_client(self, timeout_s: float = 5.0) -> GatewayClient:
        """A client of the swarm's gRPC gateway with a client identity, not yet opened."""
        ...

    def wait_ready(self, timeout_s: float = 60.0) -> None:
        """Return when every service of the spec serves; DeploymentError when time is up."""
        ...

    def metrics(self) -> Scrape:
        """The services' counters of this run (since ``start``)."""
        ...

    def stop(self) -> dict[str, int]:
        """Stop what this deployment started; the exit code of each process it ran."""
        ...


@dataclass
class SwarmSession:
    """A swarm between its start and its stop (:func:`running`): how long each took, and
    the exit code of every process once it stopped."""

    deployment: Deployment
    timings: dict[str, float]
    exit_codes: dict[str, int] = field(default_factory=dict)


@contextmanager
def running(
    deployment: Deployment,
    spec: SwarmSpec,
    *,
    progress: bool = False,
    timings: dict[str, float] | None = None,
    held_data: str = "",
    request_timeout_s: float = 5.0,
) -> Iterator[SwarmSession]:
    """The one life of a run's swarm, wherever it runs: start ``spec`` on ``deployment``,
    wait until every service serves (``start_s``), say where its live view is, and stop it
    on the way out, whatever happened (``stop_s``, the exit codes). ``held_data``: refuse
    a swarm that already holds an earlier run's data (stored items), with this advice;
    empty: a workload whose services hold nothing across runs. ``timings`` collects the
    figures (a new dict when None)."""
    session = SwarmSession(deployment, timings if timings is not None else {})
    try:
        t0 = time.perf_counter()
        deployment.start(spec, progress=progress)
        deployment.wait_ready()
        session.timings["start_s"] = time.perf_counter() - t0
        announce_live_view(deployment, progress)
        if held_data:
            with deployment.client(request_timeout_s, role="client") as client:
                holding = {f"{m.kind}-{m.robot}": m.stored_items for m in client.members() if m.stored_items}
            if holding:
                # An earlier replay's frames would be found as loop closures of this one.
                raise ConfigError(
                    f"the swarm already holds data from an earlier run ({holding}); {held_data}"
                )
        yield session
    finally:
        t0 = time.perf_counter()
        session.exit_codes = deployment.stop()
        session.timings["stop_s"] = time.perf_counter() - t0


def announce_live_view(deployment: Deployment, progress: bool) -> None:
    """Say where the swarm's live view is (stderr, beside the progress bars), when the
    deployment serves one on this machine and the run shows its progress."""
    url = getattr(deployment, "live_view_url", "")
    if progress and isinstance(url, str) and url:
        print(f"live view of the swarm: {url}", file=sys.stderr, flush=True)


def shared_env(spec: SwarmSpec) -> dict[str, str]:
    """The settings every robot's services share: the environment of each robot-0 service,
    less what differs per robot or per process (robot id, addresses, storage). A swarm
    left running records it, so a run attached to it can check it is the one it wants."""
    out: dict[str, str] = {}
    per_service = {"SWARMREC_ROBOT", "SWARMREC_DATA_DIR", "SWARMREC_FSYNC", "SWARMREC_MODE"}
    for kind in spec.kinds:
        env = config_env(spec.config_for(kind, 0))
        out.update({k: v for k, v in env.items() if k not in per_service})
    return out


def check_running(info: AttachFile, spec: SwarmSpec, wanted_env: dict[str, str], where: str) -> None:
    """ConfigError unless the swarm ``info`` describes runs ``spec`` (its workload, kinds,
    robots, name and shared settings ``wanted_env``); ``where`` names it in the message."""
    problems = []
    if spec.workload and spec.workload != info.workload:
        problems.append(f"it runs the {info.workload} workload, not {spec.workload}")
    if tuple(info.kinds) != spec.kinds:
        problems.append(f"its robots run {info.kinds}, not {list(spec.kinds)}")
    if info.robots != spec.robots:
        problems.append(f"it has {info.robots} robots, not {spec.robots}")
    if info.swarm != spec.swarm:
        problems.append(f"its swarm is {info.swarm!r}, not {spec.swarm!r}")
    if not problems:
        have = info.shared_env
        differ = sorted(k for k in wanted_env.keys() | have.keys() if wanted_env.get(k) != have.get(k))
        if differ:
            shown = ", ".join(f"{k}={have.get(k)!r} (wanted {wanted_env.get(k)!r})" for k in differ[:5])
            problems.append(f"its settings differ: {shown}")
    if problems:
        raise ConfigError(f"{where} is not this run's: " + "; ".join(problems))
