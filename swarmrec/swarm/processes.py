"""Start and stop a local swarm: one router and N robots' services, each a
separate process, on free loopback ports.

Each process prints one JSON ``ready`` line on stdout when it serves; its
JSON logs (stderr) go to ``<log_dir>/<kind>-<robot>.log``. Stopping sends
SIGTERM to the services, then the router, and escalates to SIGKILL for any
process that does not exit in time.
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

from swarmrec.errors import SwarmrecError
from swarmrec.services.config import ServiceSettings, settings_to_flags

__all__ = ["LocalSwarm", "ServiceProcess", "SwarmStartError", "free_port"]

ROBOT_SERVICES = ("index-shard", "verifier", "descriptor", "detector")

# Settings every robot's services share (the robot id is added per robot).
_SHARED = (
    "swarm",
    "n_robots",
    "connect",
    "preset",
    "n_labels",
    "label_bounds",
    "metrics_host",
    "workers",
    "request_timeout_s",
    "max_message_bytes",
    "lockstep",
    "loop_closure_min_score",
    "log_level",
    "fsync",
)


# Settings of the detectors only (their mode, model, camera); the replay mode ignores them.
_DETECTOR = (
    "detector_mode",
    "detector_model",
    "conf_threshold",
    "iou_threshold",
    "detector_threads",
    "camera_fx",
    "camera_fy",
    "camera_cx",
    "camera_cy",
    "depth_scale",
    "rgbd_max_dt",
    "classifier_model",
)


class SwarmStartError(SwarmrecError):
    """A service process exited or never became ready."""


def free_port() -> int:
    """A TCP port free on loopback right now (the OS picks it)."""
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

    def release(self) -> None:
        """After the process exited: let the stdout reader finish, close the pipe."""
        if self.reader is not None:
            self.reader.join(timeout=2.0)
        if self.proc.stdout is not None:
            self.proc.stdout.close()

    @property
    def name(self) -> str:
        return f"{self.kind}-{self.robot}"

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


def _python_cmd() -> list[str]:
    return [sys.executable, "-m", "swarmrec", "serve"]


class LocalSwarm:
    """A router and ``n_robots`` robots' services as local processes."""

    def __init__(
        self,
        base: ServiceSettings,
        *,
        data_dir: Path,
        log_dir: Path,
        dataset: str,
        labels_file: Path | None = None,
        services: Sequence[str] = ROBOT_SERVICES,
        router_port: int | None = None,
    ) -> None:
        self.router_port = router_port or free_port()
        endpoint = f"tcp/127.0.0.1:{self.router_port}"
        self.base = base.with_(connect=(endpoint,))
        self.data_dir, self.log_dir = data_dir, log_dir
        self.dataset, self.labels_file = dataset, labels_file
        self.services = tuple(services)
        self.router: ServiceProcess | None = None
        self.procs: list[ServiceProcess] = []
        self._logs: list[IO[str]] = []

    @property
    def endpoint(self) -> str:
        return self.base.connect[0]

    def _spawn(self, kind: str, robot: int, flags: list[str]) -> ServiceProcess:
        self.log_dir.mkdir(parents=True, exist_ok=True)
        log_path = self.log_dir / f"{kind}-{robot}.log"
        # Appended, so a restarted service's log follows its predecessor's.
        log = log_path.open("a", encoding="utf-8")
        self._logs.append(log)
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        proc = subprocess.Popen(
            [*_python_cmd(), kind, *flags],
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

    def start_router(self, timeout_s: float = 30.0) -> None:
        flags = ["--listen", self.endpoint, "--swarm", self.base.swarm, "--log-level", self.base.log_level]
        self.router = self._spawn("router", 0, flags)
        self._wait([self.router], timeout_s)

    def robot_flags(self, kind: str, robot: int) -> list[str]:
        settings = self.base.with_(robot=robot)
        flags = settings_to_flags(settings, (*_SHARED, "robot"))
        flags += ["--metrics-port", "0"]
        if kind in ("index-shard", "verifier", "descriptor", "detector"):
            # The detector keeps the constellations it made from RGB-D frames there.
            flags += ["--data-dir", str(self.data_dir / f"robot{robot}" / kind)]
        if kind == "detector":
            flags += settings_to_flags(settings, _DETECTOR)
            flags += ["--dataset", self.dataset]
            if self.labels_file is not None:
                flags += ["--labels-file", str(self.labels_file)]
        return flags

    def start_robot(self, robot: int, kinds: Sequence[str] | None = None) -> list[ServiceProcess]:
        started = [self._spawn(k, robot, self.robot_flags(k, robot)) for k in (kinds or self.services)]
        self.procs.extend(started)
        return started

    def start(self, timeout_s: float = 120.0, progress: bool = False) -> None:
        """Router first, then every robot's services; returns when all are ready."""
        self.start_router()
        started: list[ServiceProcess] = []
        for r in range(self.base.n_robots):
            started += self.start_robot(r)
        self._wait(started, timeout_s, progress=progress)

    def _wait(self, procs: Sequence[ServiceProcess], timeout_s: float, progress: bool = False) -> None:
        from tqdm import tqdm

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
        """``/metrics`` URL of every service still running, by (kind, robot): what
        :func:`swarmrec.swarm.scrape.scrape` reads."""
        return {
            (sp.kind, sp.robot): str(sp.info["metrics_url"])
            for sp in self.procs
            if sp.proc.poll() is None and sp.info.get("metrics_url")
        }

    def find(self, kind: str, robot: int) -> ServiceProcess:
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

    def __enter__(self) -> LocalSwarm:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
