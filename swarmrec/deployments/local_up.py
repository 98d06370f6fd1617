"""A local swarm left running: ``swarmrec up`` and ``swarmrec down``.

``swarmrec up --out DIR`` starts a :class:`~swarmrec.deployments.local.LocalDeployment`,
waits until every service serves and the index has settled, writes ``DIR/swarm.json``
(a :class:`LocalFile`: the router's endpoint, the gateway's address, the PKI folder, the
swarm's name, each service's ``/metrics`` URL and the process that keeps the swarm) and
keeps the swarm up until that process gets SIGINT or SIGTERM. Then it stops every
service and removes the file.

Clients find the swarm from the file, as they find a compose or Kubernetes swarm:
``swarmrec members --run DIR`` and the other client commands, and ``swarmrec run
--attach DIR`` (:class:`AttachedLocal`: it checks that the running swarm is the run's,
counts the run's traffic from a scrape taken when it attaches, and stops nothing).
``swarmrec down DIR`` signals the keeping process (:func:`stop_kept`).
"""

from __future__ import annotations

import json
import os
import signal
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from swarmrec.deployments.base import (
    AttachedSwarm,
    AttachFile,
    SwarmSpec,
    check_running,
    read_attach_json,
    shared_env,
)
from swarmrec.deployments.local import LocalDeployment
from swarmrec.deployments.metrics import Scrape, scrape
from swarmrec.errors import ConfigError

__all__ = [
    "AttachedLocal",
    "LocalFile",
    "keeper_alive",
    "read_local_file",
    "require_keeper",
    "stop_kept",
    "write_local_file",
]

#: The name of the attach file in the swarm's folder (the one compose and Kubernetes write).
SWARM_FILE = "swarm.json"


@dataclass(frozen=True, kw_only=True)
class LocalFile(AttachFile):
    """``swarm.json`` of a local swarm kept up by ``swarmrec up``."""

    #: The ``swarmrec up`` process that keeps the swarm (``swarmrec down`` signals it).
    pid: int = 0
    #: ``/metrics`` URL of every service, by ``kind/robot``.
    metrics_targets: dict[str, str] = field(default_factory=dict)
    #: How the services share processes (``service``, ``robot``, ``robots:K``).
    hosting: str = "service"
    #: Where the services keep their data and logs.
    data_dir: str = ""
    log_dir: str = ""

    def targets(self) -> dict[tuple[str, int], str]:
        """The metrics URLs by (kind, robot)."""
        out: dict[tuple[str, int], str] = {}
        for key, url in self.metrics_targets.items():
            kind, _, robot = key.rpartition("/")
            out[(kind, int(robot))] = url
        return out


def write_local_file(folder: Path, deployment: LocalDeployment, experiment: dict[str, Any]) -> LocalFile:
    """Write ``folder/swarm.json`` for the running ``deployment`` (this process keeps it)."""
    spec = deployment.spec
    if spec is None:
        raise ConfigError("the local swarm has not been started")
    info = LocalFile(
        deployment="local",
        swarm=spec.swarm,
        robots=spec.robots,
        workload=spec.workload,
        kinds=list(spec.kinds),
        router_endpoint=deployment.endpoint,
        prometheus_url="",
        gateway_address=deployment.gateway_address if "gateway" in spec.swarm_kinds else "",
        live_view_url=deployment.live_view_url,
        security=deployment.security,
        pki_dir=str(deployment.pki_dir.resolve()) if deployment.pki_dir is not None else "",
        experiment=experiment,
        shared_env=shared_env(spec),
        pid=os.getpid(),
        metrics_targets={f"{k}/{r}": url for (k, r), url in sorted(deployment.metrics_targets().items())},
        hosting=deployment.hosting,
        data_dir=str(deployment.data_dir.resolve()),
        log_dir=str(deployment.log_dir.resolve()),
    )
    folder.mkdir(parents=True, exist_ok=True)
    # Written whole, then renamed: a client never reads half a file.
    tmp = folder / f".{SWARM_FILE}.tmp"
    tmp.write_text(json.dumps(asdict(info), indent=2) + "\n")
    tmp.replace(folder / SWARM_FILE)
    return info


def read_local_file(folder: Path) -> LocalFile:
    """The ``swarm.json`` ``swarmrec up`` wrote in ``folder``."""
    data = read_attach_json(folder)
    path = folder / SWARM_FILE
    if data.get("deployment") != "local":
        kind = data.get("deployment", "compose")
        raise ConfigError(f"{path} describes a {kind} swarm, not one kept up by `swarmrec up`")
    try:
        return LocalFile(**data)
    except TypeError as e:
        raise ConfigError(f"{path} is not a swarm file written by this version of swarmrec: {e}") from None


def keeper_alive(pid: int) -> bool:
    """Whether ``pid`` is a running swarmrec process (not another one that reused the pid)."""
    if pid <= 0:
        return False
    try:
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return False
    return b"swarmrec" in cmdline


def require_keeper(folder: Path, pid: int) -> None:
    """ConfigError unless the ``swarmrec up`` process ``pid`` that kept ``folder``'s swarm runs."""
    if not keeper_alive(pid):
        raise ConfigError(
            f"the swarm of {folder / SWARM_FILE} is not running (its swarmrec up process {pid} is "
            f"gone): start it again with swarmrec up --out {folder}"
        )


def stop_kept(folder: Path, timeout_s: float = 60.0) -> str:
    """Stop the swarm ``swarmrec up`` keeps from ``folder``: SIGTERM to its process, then wait
    until it has stopped the services and removed the file. One line saying what happened."""
    info = read_local_file(folder)
    path = folder / SWARM_FILE
    if not keeper_alive(info.pid):
        path.unlink(missing_ok=True)
        return (
            f"no swarm was running from {folder} (process {info.pid} is gone); its stale {SWARM_FILE} removed"
        )
    os.kill(info.pid, signal.SIGTERM)
    deadline = time.monotonic() + timeout_s
    while keeper_alive(info.pid):
        if time.monotonic() > deadline:
            raise ConfigError(
                f"swarm {info.swarm!r} (process {info.pid}) did not stop within {timeout_s:.0f} s; "
                f"see {info.log_dir}"
            )
        time.sleep(0.1)
    return f"swarm {info.swarm!r} stopped ({info.robots} robots, process {info.pid})"


class AttachedLocal(AttachedSwarm):
    """A local swarm kept up by ``swarmrec up``, as a Deployment that starts and stops nothing."""

    info: LocalFile

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.info = read_local_file(folder)
        require_keeper(folder, self.info.pid)
        self.description = f"local processes kept up by swarmrec up ({self.info.hosting} hosting)"
        self._spec: SwarmSpec | None = None
        self._baseline: Scrape | None = None

    def start(self, spec: SwarmSpec, *, progress: bool = False) -> None:
        """Check that the running swarm is ``spec`` and take the counters' baseline."""
        check_running(self.info, spec, shared_env(spec), f"the swarm in {self.folder}")
        self._spec = spec
        self._baseline = scrape(self.info.targets())

    def wait_ready(self, timeout_s: float | None = None) -> None:
        if self._spec is None:
            raise ConfigError("start (check) the spec first")
        with self.client(5.0) as client:
            client.wait_for(self._spec.expected(), timeout_s if timeout_s is not None else 60.0)

    def metrics(self) -> Scrape:
        """The services' counters now, less those when the run attached."""
        after = scrape(self.info.targets())
        return after if self._baseline is None else after.minus(self._baseline)

    def stop(self) -> dict[str, int]:
        """Nothing: the swarm belongs to ``swarmrec up`` (``swarmrec down`` stops it)."""
        return {}
