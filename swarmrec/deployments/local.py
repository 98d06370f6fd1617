"""The local deployment: a router and every robot's services as separate processes
on this machine, on free loopback ports.

Each process is ``python -m swarmrec serve <kind>`` with the flags of its
configuration (:meth:`SwarmSpec.config_for`); it prints one JSON ``ready``
line on stdout when it serves, and its JSON logs (stderr) go to
``<log_dir>/<kind>-<robot>.log`` (appended, so a restarted service's log
follows its predecessor's). A stateful service keeps its data under
``<data_dir>/robot<r>/<kind>``. Stopping sends SIGTERM to the services, then
the router, and escalates to SIGKILL for any process that does not exit in time.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

from tqdm import tqdm

from swarmrec.client import SwarmClient
from swarmrec.deployments.base import SwarmSpec, SwarmStartError, config_flags
from swarmrec.deployments.metrics import Scrape, scrape
from swarmrec.errors import ConfigError

__all__ = ["LocalDeployment", "ServiceProcess", "free_port"]

#: A router that cannot listen on the port it was given (taken between choosing and
#: binding it) exits at once; it is started again on another port this many times.
ROUTER_ATTEMPTS = 5


def free_port() -> int:
    """A TCP port free on loopback right now (the OS picks it). Another process may take
    it before it is used: :meth:`LocalDeployment.start_router` retries on another."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


@dataclass
class ServiceProcess:
    """One running service process."""

    kind: str
    robot: int
    proc: subprocess.Popen[str]
    log_path: Path
    ready: threading.Event = field(default_factory=threading.Event)
    info: dict[str, object] = field(default_factory=dict)
    reader: threading.Thread | None = None

    @property
    def name(self) -> str:
        return f"{self.kind}-{self.robot}"

    @property
    def metrics_url(self) -> str:
        url = self.info.get("metrics_url")
        return url if isinstance(url, str) else ""

    def release(self) -> None:
        """After the process exited: let the stdout reader finish, close the pipe."""
        if self.reader is not None:
            self.reader.join(timeout=2.0)
        if self.proc.stdout is not None:
            self.proc.stdout.close()

    def _read_stdout(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            try:
                msg = json.loads(line)
            except json.JSONDecodeError:
                continue
            if isinstance(msg, dict) and msg.get("event") == "ready":
                self.info = msg
                self.ready.set()

    def tail(self, n: int = 15) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-n:])
        except OSError:
            return ""


class LocalDeployment:
    """A swarm as processes on this machine (see the module docstring)."""

    description = "local processes"

    def __init__(self, *, data_dir: Path, log_dir: Path, router_port: int | None = None) -> None:
        self.data_dir, self.log_dir = data_dir, log_dir
        self.router_port = router_port
        self.spec: SwarmSpec | None = None
        self.router: ServiceProcess | None = None
        self.procs: list[ServiceProcess] = []
        self._logs: list[IO[str]] = []

    # --- the Deployment interface ------------------------------------------------------

    @property
    def endpoint(self) -> str:
        if self.router_port is None:
            raise ConfigError("the router has not been started")
        return f"tcp/127.0.0.1:{self.router_port}"

    def start(self, spec: SwarmSpec, *, progress: bool = False, timeout_s: float = 120.0) -> None:
        """Router first, then every robot's services; returns when all are ready."""
        self.start_router(spec)
        started: list[ServiceProcess] = []
        for r in range(spec.robots):
            started += self.start_robot(r)
        self._wait(started, timeout_s, progress=progress)

    def wait_ready(self, timeout_s: float = 60.0) -> None:
        """Every started service printed its readiness line and has been routed to."""
        self._wait(self.procs, timeout_s)
        spec = self._spec()
        with SwarmClient([self.endpoint], spec.swarm, timeout_s=5.0) as client:
            client.wait_for({(sp.kind, sp.robot) for sp in self.procs if sp.proc.poll() is None}, timeout_s)

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
        if self.router is not None:
            codes["router"] = self.stop_process(self.router, timeout_s)
        for log in self._logs:
            log.close()
        self._logs.clear()
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

    def start_router(self, spec: SwarmSpec, timeout_s: float = 30.0) -> None:
        """The router on a free port (another one if that port was taken meanwhile)."""
        self.spec = spec
        fixed = self.router_port
        for attempt in range(1, ROUTER_ATTEMPTS + 1):
            self.router_port = fixed or free_port()
            config = spec.config_for("router", 0, listen=(self.endpoint,), metrics_port=0)
            self.router = self._spawn("router", 0, config_flags(config))
            try:
                self._wait([self.router], timeout_s)
                return
            except SwarmStartError:
                self.router.release()
                if fixed or attempt == ROUTER_ATTEMPTS:
                    raise

    def service_flags(self, kind: str, robot: int) -> list[str]:
        """The flags ``kind`` of ``robot`` is started with."""
        config = self._spec().config_for(
            kind,
            robot,
            connect=(self.endpoint,),
            data_dir=self.data_dir / f"robot{robot}" / kind,
            metrics_port=0,
        )
        return config_flags(config)

    def start_robot(self, robot: int, kinds: Sequence[str] | None = None) -> list[ServiceProcess]:
        """Start ``kinds`` (default: the spec's) of ``robot``; does not wait."""
        spec = self._spec()
        started = [self._spawn(k, robot, self.service_flags(k, robot)) for k in (kinds or spec.kinds)]
        self.procs.extend(started)
        return started

    def wait_started(self, procs: Sequence[ServiceProcess], timeout_s: float = 60.0) -> None:
        """Return when each of ``procs`` printed its readiness line."""
        self._wait(procs, timeout_s)

    def _spawn(self, kind: str, robot: int, flags: list[str]) -> ServiceProcess:
        self.log_dir.mkdir(parents=True, exist_ok=True)
        log_path = self.log_dir / f"{kind}-{robot}.log"
        log = log_path.open("a", encoding="utf-8")
        self._logs.append(log)
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        proc = subprocess.Popen(
            [sys.executable, "-m", "swarmrec", "serve", kind, *flags],
            stdout=subprocess.PIPE,
            stderr=log,
            text=True,
            env=env,
            start_new_session=True,  # a Ctrl-C in the terminal reaches the main job only
        )
        sp = ServiceProcess(kind, robot, proc, log_path)
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
        return {
            (sp.kind, sp.robot): sp.metrics_url
            for sp in self.procs
            if sp.proc.poll() is None and sp.metrics_url
        }

    def find(self, kind: str, robot: int) -> ServiceProcess:
        """The running process of ``kind`` on ``robot``."""
        for sp in self.procs:
            if sp.kind == kind and sp.robot == robot and sp.proc.poll() is None:
                return sp
        raise KeyError(f"no running {kind}-{robot}")

    def stop_process(self, sp: ServiceProcess, timeout_s: float = 10.0) -> int:
        """SIGTERM, wait, then SIGKILL; returns the exit code."""
        if sp.proc.poll() is None:
            sp.proc.send_signal(signal.SIGTERM)
            try:
                sp.proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                sp.proc.kill()
                sp.proc.wait()
        sp.release()
        return int(sp.proc.returncode)

    def __enter__(self) -> LocalDeployment:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
