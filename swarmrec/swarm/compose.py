"""The swarm as containers: a generated compose file, one container per service.

``write_compose(settings)`` prepares the dataset the detectors replay and
writes, under ``settings.out``:

* ``compose.yml``: the router, each robot's services and Prometheus. The
  ``places`` workload (place recognition, the default) gives each robot a
  detector, descriptor, index-shard and verifier; the ``landmarks`` workload
  (cooperative landmark recognition, docs/landmarks.md) a detector in
  classifier mode and a fusion service. Compose Specification, read alike by
  ``docker-compose`` 1.29 and ``docker compose`` v2. Stateful services keep
  their data in a named volume each; only the router and Prometheus are
  published, on loopback.
* ``prometheus.yml``: a scrape target per service, labelled with its
  ``service`` and ``robot``.
* ``swarm.json``: what a client on the host needs to drive and report on the
  swarm (``swarmrec run --attach DIR``, ``swarmrec landmarks --attach DIR``):
  endpoints, settings, dataset.

:func:`compose_command`, :func:`up` and :func:`down` run the compose tool
that is installed (deploy/engine.sh installs one when none is).
"""

from __future__ import annotations

import json
import shutil
import subprocess
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import swarmrec
from swarmrec.errors import ConfigError, SwarmrecError
from swarmrec.services.keys import validate_swarm_name

__all__ = [
    "MAX_ROBOTS",
    "ComposeError",
    "ComposeSettings",
    "SwarmFile",
    "compose_command",
    "down",
    "read_swarm_file",
    "render_yaml",
    "service_name",
    "up",
    "wait_healthy",
    "write_compose",
]

#: Largest swarm the generator writes (ten robots are 42 containers; more fit, but are untested).
MAX_ROBOTS = 16
ROBOT_SERVICES = ("index-shard", "verifier", "descriptor", "detector")
#: Each robot's services per workload.
WORKLOADS: dict[str, tuple[str, ...]] = {"places": ROBOT_SERVICES, "landmarks": ("fusion", "detector")}
STATEFUL = ("index-shard", "verifier", "descriptor")
METRICS_PORT = 9464  # every container serves its metrics here (its own network namespace)
ROUTER_PORT = 7447


class ComposeError(SwarmrecError):
    """The compose tool failed, or the swarm did not become healthy."""


@dataclass(frozen=True)
class ComposeSettings:
    """One containerised swarm; validated on construction."""

    robots: int = 4
    #: ``places`` (place recognition) or ``landmarks`` (cooperative landmark recognition).
    workload: str = "places"
    dataset: str = "synthetic"
    seed: int = 0
    frames: int | None = None
    labels: Path | None = None
    groundtruth: Path | None = None
    preset: str = "paper"
    swarm: str = "compose"
    #: Compose project name: prefixes every container, network and volume.
    project: str = "swarmrec"
    out: Path = Path("runs/compose")
    image: str = f"swarmrec:{swarmrec.__version__}"
    prometheus_image: str = f"swarmrec-prometheus:{swarmrec.__version__}"
    #: Host ports, published on 127.0.0.1 only.
    router_port: int = ROUTER_PORT
    prometheus_port: int = 9090
    scrape_interval_s: int = 2
    #: Shards answer from frames stored before the query's step (lock-step replay).
    lockstep: bool = True
    request_timeout_s: float = 5.0
    log_level: str = "INFO"

    def __post_init__(self) -> None:
        problems = []
        if not 1 <= self.robots <= MAX_ROBOTS:
            problems.append(f"robots must be 1 .. {MAX_ROBOTS}, got {self.robots}")
        if self.workload not in WORKLOADS:
            problems.append(f"workload must be {' or '.join(WORKLOADS)}, got {self.workload!r}")
        elif self.workload == "landmarks" and self.robots < 2:
            problems.append("a landmarks swarm needs at least 2 robots")
        if not self.project or not all(c.isalnum() or c in "-_" for c in self.project):
            problems.append(f"project must be letters, digits, - and _, got {self.project!r}")
        elif self.project != self.project.lower():
            problems.append(f"project must be lower case (compose lowers it), got {self.project!r}")
        for name in ("router_port", "prometheus_port"):
            port = getattr(self, name)
            if not 1 <= port <= 65535:
                problems.append(f"{name} must be 1 .. 65535, got {port}")
        if self.router_port == self.prometheus_port:
            problems.append("router_port and prometheus_port must differ")
        if self.scrape_interval_s < 1:
            problems.append(f"scrape_interval_s must be >= 1, got {self.scrape_interval_s}")
        try:
            validate_swarm_name(self.swarm)
        except ConfigError as e:
            problems.append(str(e))
        if problems:
            raise ConfigError("invalid compose settings: " + "; ".join(problems))


@dataclass(frozen=True)
class SwarmFile:
    """``swarm.json``: how the host reaches a containerised swarm."""

    project: str
    swarm: str
    robots: int
    preset: str
    n_labels: int
    label_bounds: list[int]
    lockstep: bool
    request_timeout_s: float
    router_endpoint: str
    prometheus_url: str
    #: Host paths: the dataset the detectors replay (mounted read-only), its labels, its poses.
    dataset: str
    labels: str | None
    groundtruth: str | None
    compose_file: str
    #: ``places`` or ``landmarks`` (files written before the landmarks workload have none).
    workload: str = "places"

    @property
    def services(self) -> tuple[str, ...]:
        """Each robot's service kinds."""
        return WORKLOADS[self.workload]


def service_name(kind: str, robot: int) -> str:
    """A robot's service in the compose file, and its host name on the swarm's network
    (compose prefixes container names with the project)."""
    return f"r{robot}-{kind}"


def _robot_service(s: ComposeSettings, kind: str, robot: int, env: dict[str, str]) -> dict[str, Any]:
    name = service_name(kind, robot)
    svc: dict[str, Any] = {
        "image": s.image,
        "hostname": name,
        "command": [kind],
        "environment": {**env, "SWARMREC_ROBOT": str(robot)},
        "depends_on": {"router": {"condition": "service_healthy"}},
        "restart": "unless-stopped",
        "stop_grace_period": "15s",
        "labels": {"org.swarmrec.service": kind, "org.swarmrec.robot": str(robot)},
    }
    if kind in STATEFUL:
        svc["volumes"] = [f"{name}-data:/var/lib/swarmrec"]
    if kind == "detector" and s.workload == "landmarks":
        # Its views come with each request; the shipped classifier is in the image.
        svc["environment"]["SWARMREC_DETECTOR_MODE"] = "classifier"
    elif kind == "detector":
        svc["volumes"] = ["./dataset:/data/dataset:ro"]
        svc["environment"]["SWARMREC_DATASET"] = "/data/dataset"
        if s.labels is not None:
            svc["volumes"].append("./labels.txt:/data/labels.txt:ro")
            svc["environment"]["SWARMREC_LABELS_FILE"] = "/data/labels.txt"
    return svc


def compose_document(s: ComposeSettings, n_labels: int, bounds: Sequence[int]) -> dict[str, Any]:
    """The compose file as a dict (the Compose Specification: no ``version`` key)."""
    env = {
        "SWARMREC_SWARM": s.swarm,
        "SWARMREC_N_ROBOTS": str(s.robots),
        "SWARMREC_CONNECT": f"tcp/router:{ROUTER_PORT}",
        "SWARMREC_REQUEST_TIMEOUT_S": str(s.request_timeout_s),
        "SWARMREC_LOG_LEVEL": s.log_level,
    }
    if s.workload == "places":
        env |= {
            "SWARMREC_PRESET": s.preset,
            "SWARMREC_N_LABELS": str(n_labels),
            "SWARMREC_LABEL_BOUNDS": ",".join(str(int(b)) for b in bounds),
            "SWARMREC_LOCKSTEP": "true" if s.lockstep else "false",
        }
    services: dict[str, Any] = {
        "router": {
            "image": s.image,
            "hostname": "router",
            "command": ["router", "--listen", f"tcp/0.0.0.0:{ROUTER_PORT}"],
            "environment": {"SWARMREC_SWARM": s.swarm, "SWARMREC_LOG_LEVEL": s.log_level},
            "ports": [f"127.0.0.1:{s.router_port}:{ROUTER_PORT}"],
            "restart": "unless-stopped",
            "stop_grace_period": "15s",
            "labels": {"org.swarmrec.service": "router", "org.swarmrec.robot": "0"},
        }
    }
    volumes: dict[str, Any] = {}
    for robot in range(s.robots):
        for kind in WORKLOADS[s.workload]:
            name = service_name(kind, robot)
            services[name] = _robot_service(s, kind, robot, env)
            if kind in STATEFUL:
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


def prometheus_document(s: ComposeSettings) -> dict[str, Any]:
    """Prometheus' configuration: every service of the swarm, labelled by service and robot."""
    groups: list[dict[str, Any]] = [
        {"targets": [f"router:{METRICS_PORT}"], "labels": {"service": "router", "robot": "0"}}
    ]
    for robot in range(s.robots):
        for kind in WORKLOADS[s.workload]:
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


def write_compose(s: ComposeSettings) -> SwarmFile:
    """Prepare the dataset (places) and write compose.yml, prometheus.yml and swarm.json."""
    out = s.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    if s.workload == "landmarks":
        return _write_files(s, out, n_labels=0, bounds=[], dataset="", labels=None, groundtruth=None)
    from swarmrec.swarm.job import SwarmSettings, prepare_dataset, swarm_label_bounds

    job = SwarmSettings(
        dataset=s.dataset,
        seed=s.seed,
        frames=s.frames,
        labels=s.labels,
        groundtruth=s.groundtruth,
        robots=s.robots,
        preset=s.preset,
        out=out,
    )
    source, labels_file, seq, _trajectory = prepare_dataset(job)
    dataset = out / "dataset"
    if Path(source).resolve() != dataset:
        # The compose file mounts ./dataset: a user's dataset (folder or zip) is copied beside it.
        if dataset.exists():
            shutil.rmtree(dataset)
        if Path(source).is_dir():
            shutil.copytree(source, dataset)
        else:
            dataset.mkdir()
            shutil.copy2(source, dataset / Path(source).name)
    if labels_file is not None:
        shutil.copy2(labels_file, out / "labels.txt")
    groundtruth = s.groundtruth
    if groundtruth is None and (dataset / "groundtruth.txt").is_file():
        groundtruth = dataset / "groundtruth.txt"
    bounds = [int(b) for b in swarm_label_bounds(job, seq)]
    return _write_files(
        s,
        out,
        n_labels=seq.n_labels,
        bounds=bounds,
        dataset=str(dataset),
        labels=str(out / "labels.txt") if labels_file is not None else None,
        groundtruth=str(groundtruth) if groundtruth is not None else None,
    )


def _write_files(
    s: ComposeSettings,
    out: Path,
    *,
    n_labels: int,
    bounds: list[int],
    dataset: str,
    labels: str | None,
    groundtruth: str | None,
) -> SwarmFile:
    compose_file = out / "compose.yml"
    header = (
        f"# Generated by `swarmrec compose` (swarmrec {swarmrec.__version__}): {s.robots} robots, "
        f"{s.workload} workload, swarm {s.swarm!r}.\n"
        "# Edit the generator (swarmrec/swarm/compose.py), not this file.\n"
    )
    compose_file.write_text(header + render_yaml(compose_document(s, n_labels, bounds)) + "\n")
    (out / "prometheus.yml").write_text(header + render_yaml(prometheus_document(s)) + "\n")
    info = SwarmFile(
        project=s.project,
        swarm=s.swarm,
        robots=s.robots,
        preset=s.preset,
        n_labels=n_labels,
        label_bounds=bounds,
        lockstep=s.lockstep,
        request_timeout_s=s.request_timeout_s,
        router_endpoint=f"tcp/127.0.0.1:{s.router_port}",
        prometheus_url=f"http://127.0.0.1:{s.prometheus_port}",
        dataset=dataset,
        labels=labels,
        groundtruth=groundtruth,
        compose_file=str(compose_file),
        workload=s.workload,
    )
    (out / "swarm.json").write_text(json.dumps(asdict(info), indent=2) + "\n")
    return info


def read_swarm_file(folder: Path) -> SwarmFile:
    """The ``swarm.json`` written by :func:`write_compose` in ``folder``."""
    path = folder / "swarm.json"
    try:
        data = json.loads(path.read_text())
        info = SwarmFile(**data)
    except FileNotFoundError:
        hint = f"swarmrec compose up --out {folder}"
        raise ConfigError(f"{path} not found: write it first with `{hint}`") from None
    except (json.JSONDecodeError, TypeError) as e:
        raise ConfigError(f"{path} is not a swarm file written by this version of swarmrec: {e}") from None
    if info.workload not in WORKLOADS:
        raise ConfigError(f"{path}: unknown workload {info.workload!r}; workloads: {', '.join(WORKLOADS)}")
    return info


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
