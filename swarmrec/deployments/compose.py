"""The compose deployment: one container per service on this host, generated from a spec.

:func:`write_compose` turns a :class:`~swarmrec.deployments.base.SwarmSpec`
into files under ``settings.out``:

* ``compose.yml``: the router, each robot's services of the spec and
  Prometheus. Compose Specification, read alike by ``docker-compose`` 1.29 and
  ``docker compose`` v2. Each service's environment is its whole configuration
  (``SWARMREC_*``, generated from its settings components); a stateful kind (the
  registry says which) keeps its data in a named volume; a detector's dataset
  folder is mounted read-only at ``/data/dataset``, the files the settings name on
  the host (models, k-means centres, an assignment table) at ``/data/files`` and a
  SLAM team's robot folder at ``/data/slam``; a detector in rgbd mode writes what it
  detects and describes to ``data/robot<r>/detector`` on the host (a bind mount), where
  the run reads it back as from local processes. The router, the gRPC
  gateway (the one port a client needs) and Prometheus are published, on loopback.
* ``pki/``: the run's PKI (mutual TLS on every zenoh link, by default), and
  ``secrets/<service>/``: what each container mounts at ``/run/swarmrec/pki``:
  ``ca.pem`` and its own certificate and key only (the router also ``acl.json``;
  no container ever sees ``ca.key``), keys owned by the image's user.
* ``prometheus.yml``: a scrape target per service, labelled with its
  ``service`` and ``robot``.
* ``swarm.json``: what a client on the host needs to reach the swarm and to
  re-run its experiment (:class:`SwarmFile`).

:class:`ComposeDeployment` is the :class:`~swarmrec.deployments.base.Deployment`
of such a swarm: it checks the running swarm is the experiment's spec, reads
its counters from Prometheus (this run's only: a baseline is taken at start)
and leaves the containers running (:func:`up` and :func:`down` start and
remove them; deploy/engine.sh installs a compose tool when none is).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import swarmrec
from swarmrec.deployments.base import (
    AttachedSwarm,
    AttachFile,
    DeploymentError,
    SwarmSpec,
    check_running,
    config_env,
    numerics_env,
    shared_env,
)
from swarmrec.deployments.identities import Security, security_for, swarm_pki
from swarmrec.deployments.metrics import Scrape, scrape_prometheus
from swarmrec.errors import ConfigError
from swarmrec.runtime.settings import BusSettings
from swarmrec.runtime.tls import ACL_FILE, tls_endpoint
from swarmrec.services import registry
from swarmrec.services.settings import (
    DetectorSettings,
    GatewaySettings,
    RgbdSettings,
    SlamServiceSettings,
    VprSettings,
)

__all__ = [
    "MAX_ROBOTS",
    "ComposeDeployment",
    "ComposeError",
    "ComposeSettings",
    "SwarmFile",
    "compose_command",
    "compose_document",
    "down",
    "prometheus_document",
    "read_swarm_file",
    "render_yaml",
    "service_name",
    "up",
    "wait_healthy",
    "write_compose",
]

#: Largest swarm the generator writes (ten robots are 42 containers; more fit, but are untested).
MAX_ROBOTS = 16
METRICS_PORT = 9464  # every container serves its metrics here (its own network namespace)
ROUTER_PORT = 7447
GATEWAY_PORT = 50051
#: Where a container finds its certificate, its key and the CA (a read-only mount).
PKI_MOUNT = Path("/run/swarmrec/pki")
#: The image's user (deploy/Dockerfile): it must be able to read its key (mode 0600).
CONTAINER_UID = 10001
DATA_DIR = Path("/var/lib/swarmrec")
DATASET_MOUNT = "/data/dataset"
LABELS_MOUNT = "/data/labels.txt"
#: The host files the settings name (models, centres, an assignment), copied to ``out/files``.
FILES_MOUNT = "/data/files"
#: A SLAM team's robot folder (``<robot>.g2o`` each), copied to ``out/slam``.
SLAM_MOUNT = "/data/slam"
#: Where the rgbd detectors' data folders are on the host, under ``out``: as a local
#: deployment lays them out (``robot<r>/detector``), so a run reads them back alike.
DETECTIONS_DIR = "data"


class ComposeError(DeploymentError):
    """The compose tool failed, or the swarm did not become healthy."""


@dataclass(frozen=True)
class ComposeSettings:
    """Where and how a spec becomes containers; validated on construction."""

    #: Compose project name: prefixes every container, network and volume.
    project: str = "swarmrec"
    out: Path = Path("runs/compose")
    image: str = f"swarmrec:{swarmrec.__version__}"
    prometheus_image: str = f"swarmrec-prometheus:{swarmrec.__version__}"
    #: Host ports, published on 127.0.0.1 only.
    router_port: int = ROUTER_PORT
    prometheus_port: int = 9090
    gateway_port: int = GATEWAY_PORT
    scrape_interval_s: int = 2
    #: The zenoh links: mtls (default) or insecure (debugging, logged by every container).
    security: Security = "mtls"

    def __post_init__(self) -> None:
        problems = []
        if not self.project or not all(c.isalnum() or c in "-_" for c in self.project):
            problems.append(f"project must be letters, digits, - and _, got {self.project!r}")
        elif self.project != self.project.lower():
            problems.append(f"project must be lower case (compose lowers it), got {self.project!r}")
        for name in ("router_port", "prometheus_port", "gateway_port"):
            port = getattr(self, name)
            if not 1 <= port <= 65535:
                problems.append(f"{name} must be 1 .. 65535, got {port}")
        if len({self.router_port, self.prometheus_port, self.gateway_port}) != 3:
            problems.append("router_port, prometheus_port and gateway_port must differ")
        if self.security not in ("mtls", "insecure"):
            problems.append(f"security must be mtls or insecure, got {self.security!r}")
        if self.scrape_interval_s < 1:
            problems.append(f"scrape_interval_s must be >= 1, got {self.scrape_interval_s}")
        if problems:
            raise ConfigError("invalid compose settings: " + "; ".join(problems))


@dataclass(frozen=True, kw_only=True)
class SwarmFile(AttachFile):
    """``swarm.json`` of a compose swarm: the attach file, and the compose project."""

    deployment: str = "compose"
    project: str
    compose_file: str
    #: The rgbd detectors' data folders on this machine (``robot<r>/detector`` under it); "" when
    #: the detectors replay constellations (they write nothing a run reads back).
    detections_dir: str = ""


def service_name(kind: str, robot: int) -> str:
    """A robot's service in the compose file, and its host name on the swarm's network
    (compose prefixes container names with the project)."""
    return f"r{robot}-{kind}"


#: The settings that name one host file a service opens: (component, field).
_FILE_SETTINGS: tuple[tuple[type[Any], str], ...] = (
    (RgbdSettings, "detector_model"),
    (VprSettings, "descriptor_model"),
    (VprSettings, "vpr_centres"),
    (VprSettings, "vpr_assignment"),
)


def host_files(spec: SwarmSpec) -> dict[str, Path]:
    """The host files the spec's settings name, by the name each has under ``out/files``
    (``<setting><suffix>``): a container sees them at ``/data/files/<name>``."""
    files: dict[str, Path] = {}
    for comp, name in _FILE_SETTINGS:
        given = spec.component(comp)
        value = getattr(given, name) if given is not None else None
        if value:
            path = Path(value)
            files[f"{name}{path.suffix}"] = path
    return files


def _writes_detections(spec: SwarmSpec) -> bool:
    """Whether the spec's detectors detect in RGB-D frames (and write what they made)."""
    detector = spec.component(DetectorSettings)
    return (
        "detector" in spec.kinds
        and isinstance(detector, DetectorSettings)
        and detector.detector_mode == "rgbd"
    )


def _container_spec(spec: SwarmSpec) -> SwarmSpec:
    """``spec`` with host paths replaced by the mounts the containers see."""
    mounted: dict[type[Any], Any] = {}
    detector = spec.component(DetectorSettings)
    if isinstance(detector, DetectorSettings) and detector.dataset:
        mounted[DetectorSettings] = detector.with_(
            dataset=DATASET_MOUNT,
            labels_file=Path(LABELS_MOUNT) if detector.labels_file is not None else None,
        )
    for comp, name in _FILE_SETTINGS:
        given = mounted.get(comp) or spec.component(comp)
        value = getattr(given, name) if given is not None else None
        if given is not None and value:
            inside = f"{FILES_MOUNT}/{name}{Path(value).suffix}"
            mounted[comp] = given.with_(**{name: Path(inside) if isinstance(value, Path) else inside})
    slam = spec.component(SlamServiceSettings)
    if isinstance(slam, SlamServiceSettings) and slam.slam_folder is not None:
        mounted[SlamServiceSettings] = slam.with_(slam_folder=Path(SLAM_MOUNT))
    if not mounted:
        return spec
    parts = tuple(mounted.get(type(c), c) for c in spec.components)
    return SwarmSpec(spec.bus, spec.kinds, parts, spec.workload, dict(spec.overrides), spec.swarm_kinds)


def _reads(kind: str, comps: tuple[type[Any], ...]) -> bool:
    return any(c in registry.spec(kind).all_components for c in comps)


def _data_mounts(spec: SwarmSpec, kind: str) -> list[str]:
    """The read-only mounts of the host data ``kind`` reads (its files, a SLAM folder)."""
    mounts = []
    if host_files(spec) and _reads(kind, (RgbdSettings, VprSettings)):
        mounts.append(f"./files:{FILES_MOUNT}:ro")
    slam = spec.component(SlamServiceSettings)
    if (
        isinstance(slam, SlamServiceSettings)
        and slam.slam_folder is not None
        and _reads(kind, (SlamServiceSettings,))
    ):
        mounts.append(f"./slam:{SLAM_MOUNT}:ro")
    return mounts


def _environment(spec: SwarmSpec, kind: str, robot: int, security: Security = "mtls") -> dict[str, str]:
    entry = registry.spec(kind)
    # An rgbd detector keeps what it detects in its data folder, a bind mount the run reads back.
    keeps = entry.stateful or (kind == "detector" and _writes_detections(spec))
    scheme = "tcp" if security == "insecure" else "tls"
    config = spec.config_for(
        kind,
        robot,
        # The router's certificate names "router" (its host name on the swarm's network).
        connect=(f"{scheme}/router:{ROUTER_PORT}",),
        listen=(f"{scheme}/0.0.0.0:{ROUTER_PORT}",) if kind == "router" else (),
        data_dir=DATA_DIR if keeps else None,
        metrics_port=METRICS_PORT,
        metrics_host="0.0.0.0",
    )
    config = config.replace(security_for(security, PKI_MOUNT, service_name(kind, robot)))
    if config.has(GatewaySettings):
        config = config.replace(
            config.get(GatewaySettings).with_(grpc_host="0.0.0.0", grpc_port=GATEWAY_PORT)
        )
    return config_env(config) | numerics_env()


def _swarm_service_name(kind: str) -> str:
    """A per-swarm kind's compose service and host name: its kind (``gateway``)."""
    return kind


def _robot_service(spec: SwarmSpec, s: ComposeSettings, kind: str, robot: int) -> dict[str, Any]:
    name = service_name(kind, robot)
    svc: dict[str, Any] = {
        "image": s.image,
        "hostname": name,
        "command": [kind],
        "environment": _environment(spec, kind, robot, s.security),
        "depends_on": {"router": {"condition": "service_healthy"}},
        "restart": "unless-stopped",
        "stop_grace_period": "15s",
        "labels": {"org.swarmrec.service": kind, "org.swarmrec.robot": str(robot)},
    }
    volumes = [] if s.security == "insecure" else [f"./secrets/{name}:{PKI_MOUNT}:ro"]
    if registry.spec(kind).stateful:
        volumes.append(f"{name}-data:{DATA_DIR}")
    elif kind == "detector" and _writes_detections(spec):
        volumes.append(f"./{DETECTIONS_DIR}/robot{robot}/{kind}:{DATA_DIR}")
    detector = spec.component(DetectorSettings)
    if kind == "detector" and isinstance(detector, DetectorSettings) and detector.dataset:
        volumes.append(f"./dataset:{DATASET_MOUNT}:ro")
        if detector.labels_file is not None:
            volumes.append(f"./labels.txt:{LABELS_MOUNT}:ro")
    volumes += _data_mounts(spec, kind)
    if volumes:
        svc["volumes"] = volumes
    return svc


def compose_document(spec: SwarmSpec, s: ComposeSettings) -> dict[str, Any]:
    """The compose file as a dict (the Compose Specification: no ``version`` key)."""
    spec = _container_spec(spec)
    services: dict[str, Any] = {
        "router": {
            "image": s.image,
            "hostname": "router",
            "command": ["router"],
            "environment": _environment(spec, "router", 0, s.security),
            "ports": [f"127.0.0.1:{s.router_port}:{ROUTER_PORT}"],
            "restart": "unless-stopped",
            "stop_grace_period": "15s",
            "labels": {"org.swarmrec.service": "router", "org.swarmrec.robot": "0"},
        }
    }
    if s.security != "insecure":
        services["router"]["volumes"] = [f"./secrets/router:{PKI_MOUNT}:ro"]
    for kind in spec.swarm_kinds:
        name = _swarm_service_name(kind)
        services[name] = {
            "image": s.image,
            "hostname": name,
            "command": [kind],
            "environment": _environment(spec, kind, 0, s.security),
            "depends_on": {"router": {"condition": "service_healthy"}},
            "restart": "unless-stopped",
            "stop_grace_period": "15s",
            "labels": {"org.swarmrec.service": kind, "org.swarmrec.robot": "0"},
        }
        if kind == "gateway":
            services[name]["ports"] = [f"127.0.0.1:{s.gateway_port}:{GATEWAY_PORT}"]
        mounts = [] if s.security == "insecure" else [f"./secrets/{name}:{PKI_MOUNT}:ro"]
        mounts += _data_mounts(spec, kind)
        if mounts:
            services[name]["volumes"] = mounts
    volumes: dict[str, Any] = {}
    for robot in range(spec.robots):
        for kind in spec.kinds:
            name = service_name(kind, robot)
            services[name] = _robot_service(spec, s, kind, robot)
            if registry.spec(kind).stateful:
                volumes[f"{name}-data"] = {}
    services["prometheus"] = {
        "image": s.prometheus_image,
        "hostname": "prometheus",
        "volumes": ["./prometheus.yml:/etc/prometheus/prometheus.yml:ro", "prometheus-data:/prometheus"],
        "ports": [f"127.0.0.1:{s.prometheus_port}:9090"],
        "restart": "unless-stopped",
        "labels": {"org.swarmrec.service": "prometheus", "org.swarmrec.robot": "0"},
    }
    volumes["prometheus-data"] = {}
    return {"services": services, "volumes": volumes}


def prometheus_document(spec: SwarmSpec, s: ComposeSettings) -> dict[str, Any]:
    """Prometheus' configuration: every service of the swarm, labelled by service and robot."""
    groups: list[dict[str, Any]] = [
        {"targets": [f"router:{METRICS_PORT}"], "labels": {"service": "router", "robot": "0"}}
    ]
    for kind in spec.swarm_kinds:
        groups.append(
            {
                "targets": [f"{_swarm_service_name(kind)}:{METRICS_PORT}"],
                "labels": {"service": kind, "robot": "0"},
            }
        )
    for robot in range(spec.robots):
        for kind in spec.kinds:
            groups.append(
                {
                    "targets": [f"{service_name(kind, robot)}:{METRICS_PORT}"],
                    "labels": {"service": kind, "robot": str(robot)},
                }
            )
    return {
        "global": {"scrape_interval": f"{s.scrape_interval_s}s", "scrape_timeout": "1s"},
        "scrape_configs": [
            # honor_labels: the services' own info series carry the same service and robot labels.
            {"job_name": "swarmrec", "honor_labels": True, "static_configs": groups}
        ],
    }


def render_yaml(doc: Any, indent: int = 0) -> str:
    """``doc`` (dicts, lists, strings, numbers, booleans) as block-style YAML.

    Every string is written double-quoted with JSON escapes, which YAML reads
    back unchanged: no value ("on", "0755", "1.10") is ever re-typed.
    """
    pad = "  " * indent
    if isinstance(doc, dict):
        if not doc:
            return "{}"
        lines = []
        for key, value in doc.items():
            k = str(key)
            if isinstance(value, dict | list) and value:
                lines.append(f"{pad}{k}:\n{render_yaml(value, indent + 1)}")
            else:
                lines.append(f"{pad}{k}: {render_yaml(value, 0)}")
        return "\n".join(lines)
    if isinstance(doc, list):
        if not doc:
            return "[]"
        lines = []
        for item in doc:
            if isinstance(item, dict) and item:
                body = render_yaml(item, indent + 1)
                lines.append(f"{pad}- {body.lstrip()}")
            else:
                lines.append(f"{pad}- {render_yaml(item, 0)}")
        return "\n".join(lines)
    if isinstance(doc, bool):
        return "true" if doc else "false"
    if isinstance(doc, int | float):
        return json.dumps(doc)
    if doc is None:
        return "null"
    return json.dumps(str(doc))


def write_compose(
    spec: SwarmSpec, s: ComposeSettings, *, experiment: dict[str, Any] | None = None
) -> SwarmFile:
    """Write compose.yml, prometheus.yml and swarm.json for ``spec`` under ``s.out``.

    A detector's dataset (a folder or a zip on the host) is copied to ``s.out/dataset``,
    the folder the compose file mounts, unless it is that folder already.
    """
    if not 1 <= spec.robots <= MAX_ROBOTS:
        raise ConfigError(f"a compose swarm has 1 .. {MAX_ROBOTS} robots, got {spec.robots}")
    out = s.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    detector = spec.component(DetectorSettings)
    if isinstance(detector, DetectorSettings) and detector.dataset:
        _copy_dataset(Path(detector.dataset), out / "dataset")
        if detector.labels_file is not None:
            shutil.copy2(detector.labels_file, out / "labels.txt")
    _copy_files(host_files(spec), out / "files")
    slam = spec.component(SlamServiceSettings)
    if isinstance(slam, SlamServiceSettings) and slam.slam_folder is not None:
        _copy_dataset(slam.slam_folder, out / "slam")
    detections = _detections_folders(spec, out) if _writes_detections(spec) else ""
    pki = ""
    if s.security == "mtls":
        pki = str(_write_secrets(spec, out))
    compose_file = out / "compose.yml"
    header = (
        f"# Generated by `swarmrec compose` (swarmrec {swarmrec.__version__}): {spec.robots} robots, "
        f"{spec.workload or 'custom'} workload, swarm {spec.swarm!r}.\n"
        "# Edit the generator (swarmrec/deployments/compose.py), not this file.\n"
    )
    compose_file.write_text(header + render_yaml(compose_document(spec, s)) + "\n")
    (out / "prometheus.yml").write_text(header + render_yaml(prometheus_document(spec, s)) + "\n")
    info = SwarmFile(
        project=s.project,
        swarm=spec.swarm,
        robots=spec.robots,
        workload=spec.workload,
        kinds=list(spec.kinds),
        router_endpoint=(
            f"tcp/127.0.0.1:{s.router_port}"
            if s.security == "insecure"
            else tls_endpoint("127.0.0.1", s.router_port)
        ),
        prometheus_url=f"http://127.0.0.1:{s.prometheus_port}",
        compose_file=str(compose_file),
        experiment=dict(experiment or {}),
        shared_env=shared_env(_container_spec(spec)),
        gateway_address=f"grpc://127.0.0.1:{s.gateway_port}" if "gateway" in spec.swarm_kinds else "",
        security=s.security,
        pki_dir=pki,
        detections_dir=detections,
    )
    (out / "swarm.json").write_text(json.dumps(asdict(info), indent=2) + "\n")
    return info


def _write_secrets(spec: SwarmSpec, out: Path) -> Path:
    """The run's PKI in ``out/pki`` and, per container, ``out/secrets/<service>/`` with the CA
    certificate and that container's own pair only (the router: and the access control; a kind
    that checks its peers' signatures, fusion: and the other robots' certificates of its kind,
    public, to check origins)."""
    pki = swarm_pki(out / "pki", spec.swarm, spec.robots, router_names=("router",))
    secrets = out / "secrets"
    shutil.rmtree(secrets, ignore_errors=True)
    who = [("router", "router", 0)] + [(_swarm_service_name(k), k, 0) for k in spec.swarm_kinds]
    who += [(service_name(k, r), k, r) for r in range(spec.robots) for k in spec.kinds]
    for name, kind, robot in who:
        folder = secrets / name
        folder.mkdir(parents=True, mode=0o755)
        cn = registry.spec(kind).common_name(spec.swarm, robot)
        files = [("ca.pem", "ca.pem"), (f"{cn}.pem", f"{cn}.pem"), (f"{cn}.key", f"{cn}.key")]
        if kind == "router":
            files.append((ACL_FILE, ACL_FILE))
        if registry.spec(kind).peer_certificates:
            # The other robots' certificates of its kind (public): a relayed message's origin
            # signature is checked against its origin's (docs/security.md).
            peers = (registry.spec(kind).common_name(spec.swarm, r) for r in range(spec.robots) if r != robot)
            files += [(f"{peer}.pem", f"{peer}.pem") for peer in peers]
        for src, dst in files:
            shutil.copy2(pki / src, folder / dst)
        key = folder / f"{cn}.key"
        os.chmod(key, 0o600)
        if os.geteuid() == 0:  # the container's user must read its key; only root can give it
            os.chown(key, CONTAINER_UID, CONTAINER_UID)
    return pki


def _copy_files(files: dict[str, Path], target: Path) -> None:
    """The host files the services open, under the names the containers see them by."""
    shutil.rmtree(target, ignore_errors=True)
    if not files:
        return
    target.mkdir(parents=True)
    for name, path in files.items():
        if not path.is_file():
            raise ConfigError(f"{path} (a file the swarm's settings name) is not a file")
        shutil.copy2(path, target / name)


def _detections_folders(spec: SwarmSpec, out: Path) -> str:
    """Empty ``out/data/robot<r>/detector`` folders, writable by the containers' user: the
    rgbd detectors' data folders (an earlier swarm's detections removed)."""
    root = out / DETECTIONS_DIR
    shutil.rmtree(root, ignore_errors=True)
    for robot in range(spec.robots):
        folder = root / f"robot{robot}" / "detector"
        folder.mkdir(parents=True)
        if os.geteuid() == 0:
            os.chown(folder, CONTAINER_UID, CONTAINER_UID)
        else:  # only root can give the folder away; let the container's user write it instead
            os.chmod(folder, 0o777)
    return str(root)


def _copy_dataset(source: Path, target: Path) -> None:
    if source.resolve() == target.resolve():
        return
    if target.exists():
        shutil.rmtree(target)
    if source.is_dir():
        shutil.copytree(source, target)
    else:
        target.mkdir(parents=True)
        shutil.copy2(source, target / source.name)


def read_swarm_file(folder: Path) -> SwarmFile:
    """The ``swarm.json`` written by :func:`write_compose` in ``folder``."""
    path = folder / "swarm.json"
    try:
        data = json.loads(path.read_text())
        if isinstance(data, dict) and data.get("deployment", "compose") != "compose":
            raise ConfigError(f"{path} describes a {data['deployment']} swarm, not a compose project")
        info = SwarmFile(**data)
    except FileNotFoundError:
        hint = f"swarmrec compose up --out {folder}"
        raise ConfigError(f"{path} not found: write it first with `{hint}`") from None
    except (json.JSONDecodeError, TypeError) as e:
        raise ConfigError(f"{path} is not a swarm file written by this version of swarmrec: {e}") from None
    unknown = [k for k in info.kinds if k not in registry.REGISTRY]
    if unknown:
        raise ConfigError(f"{path}: unknown service kinds {unknown}; kinds: {', '.join(registry.REGISTRY)}")
    return info


class ComposeDeployment(AttachedSwarm):
    """A compose swarm that already runs (``swarmrec compose up``), as a Deployment."""

    info: SwarmFile

    def __init__(self, folder: Path, *, wait_s: float = 120.0) -> None:
        self.folder = folder
        self.info = read_swarm_file(folder)
        self.description = f"compose project {self.info.project}"
        self.wait_s = wait_s
        self._baseline: Scrape | None = None
        self._spec: SwarmSpec | None = None

    def start(self, spec: SwarmSpec, *, progress: bool = False) -> None:
        """Check that the running swarm is ``spec`` and take the counters' baseline."""
        check_running(self.info, spec, shared_env(_container_spec(spec)), f"the swarm in {self.folder}")
        self._spec = spec
        self._baseline = scrape_prometheus(self.info.prometheus_url, fresh_after=time.time())

    def wait_ready(self, timeout_s: float | None = None) -> None:
        spec = self._spec
        if spec is None:
            raise ConfigError("start (check) the spec first")
        with self.client(5.0) as client:
            client.wait_for(spec.expected(), timeout_s if timeout_s is not None else self.wait_s)

    def metrics(self) -> Scrape:
        """The counters Prometheus holds now, less those at :meth:`start`."""
        after = scrape_prometheus(self.info.prometheus_url, fresh_after=time.time())
        return after if self._baseline is None else after.minus(self._baseline)

    @property
    # (AttachedSwarm says None: a swarm started elsewhere keeps its data elsewhere; a compose
    # swarm's rgbd detectors write theirs to bind mounts on this machine.)
    def local_data_dir(self) -> Path | None:  # type: ignore[override]
        """The rgbd detectors' data folders (bind mounts on this machine), when the swarm has them."""
        return Path(self.info.detections_dir) if self.info.detections_dir else None

    def stop(self) -> dict[str, int]:
        """Nothing: the containers belong to ``swarmrec compose``; no process was started here."""
        return {}


def compose_command() -> list[str]:
    """``docker compose`` (v2) when the CLI has it, else ``docker-compose`` (v1.29)."""
    if shutil.which("docker") is not None:
        probe = subprocess.run(["docker", "compose", "version"], capture_output=True, check=False)
        if probe.returncode == 0:
            return ["docker", "compose"]
    if shutil.which("docker-compose") is not None:
        return ["docker-compose"]
    raise ComposeError("no compose tool found: run deploy/engine.sh (installs docker-compose)")


def _compose(info: SwarmFile, *args: str, timeout_s: float = 600.0) -> subprocess.CompletedProcess[str]:
    cmd = [*compose_command(), "-p", info.project, "-f", info.compose_file, *args]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, check=False)
    except subprocess.TimeoutExpired:
        raise ComposeError(f"{' '.join(cmd)} did not finish in {timeout_s:g} s") from None
    if proc.returncode != 0:
        raise ComposeError(f"{' '.join(cmd)} failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    return proc


def up(info: SwarmFile, timeout_s: float = 300.0) -> float:
    """Start every container and wait until all are healthy; returns the seconds it took."""
    t0 = time.monotonic()
    _compose(info, "up", "-d", "--no-build", timeout_s=timeout_s)
    wait_healthy(info.project, timeout_s - (time.monotonic() - t0))
    return time.monotonic() - t0


def down(info: SwarmFile, *, volumes: bool = True, timeout_s: float = 300.0) -> None:
    """Stop and remove the containers and the network (and the named volumes)."""
    args = ["down", "--remove-orphans", "--timeout", "15"]
    if volumes:
        args.append("--volumes")
    _compose(info, *args, timeout_s=timeout_s)


def _states(project: str) -> dict[str, str]:
    """Health (or state, for containers without a health check) of the project's containers."""
    ids = subprocess.run(
        ["docker", "ps", "-aq", "--filter", f"label=com.docker.compose.project={project}"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split()
    if not ids:
        return {}
    fmt = "{{.Name}} {{if .State.Health}}{{.State.Health.Status}}{{else}}{{.State.Status}}{{end}}"
    out = subprocess.run(["docker", "inspect", "-f", fmt, *ids], capture_output=True, text=True, check=True)
    states = {}
    for line in out.stdout.splitlines():
        name, _, state = line.strip().partition(" ")
        states[name.lstrip("/")] = state
    return states


def wait_healthy(project: str, timeout_s: float = 300.0) -> None:
    """Return when every container of ``project`` is healthy; raise when one fails or time is up."""
    deadline = time.monotonic() + timeout_s
    states: dict[str, str] = {}
    while time.monotonic() < deadline:
        states = _states(project)
        bad = {n: st for n, st in states.items() if st in ("unhealthy", "exited", "dead")}
        if bad:
            raise ComposeError(f"containers failed: {bad}; see `docker logs <name>`")
        if states and all(st == "healthy" for st in states.values()):
            return
        time.sleep(1.0)
    waiting = sorted(n for n, st in states.items() if st != "healthy")
    raise ComposeError(f"not healthy after {timeout_s:g} s: {', '.join(waiting) or 'no containers'}")


def bus_for(robots: int, swarm: str = "compose", request_timeout_s: float = 5.0) -> BusSettings:
    """The bus settings of a compose swarm of ``robots`` (the CLI's defaults)."""
    return BusSettings(swarm=swarm, n_robots=robots, request_timeout_s=request_timeout_s)
