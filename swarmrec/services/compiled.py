"""Kinds served by the compiled host, ``swarmrec-dataplane`` (docs/dataplane.md).

A kind whose registry entry says ``compiled`` has a second implementation in Rust
(``dataplane/``), on the same keys, messages, error codes, metrics, logs and record
logs. The ``data_plane`` setting picks it: ``swarmrec serve`` and ``swarmrec host``
resolve every setting here, as for a Python service, and hand them to the binary
whole (``--spec-json``), so the two implementations never read settings differently;
the zenoh configuration travels as the Python binding prints it (TLS files, access
control, endpoints). Then:

* ``swarmrec serve <kind>``: the process becomes the compiled host (``exec``): no
  Python stays behind it.
* ``swarmrec host`` with only compiled kinds: the same.
* ``swarmrec host`` mixing both: the compiled kinds run in a child process on a
  session of their own (the same certificate), started first; its services are listed
  in the host's readiness line beside the Python ones, and it is stopped with the host.

The binary is found at ``$SWARMREC_DATAPLANE``, else in the checkout's
``target/release`` (``make dataplane`` builds it there), else on ``PATH``.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NoReturn

import swarmrec
from swarmrec.core.presets import get_preset
from swarmrec.errors import ConfigError
from swarmrec.runtime.hosting import ready_entries, ready_events, terminate
from swarmrec.runtime.runner import (
    Hosted,
    deepen_send_queue,
    service_logger,
    session_bus,
    session_identity,
    zenoh_config,
)
from swarmrec.runtime.settings import Config, StorageSettings
from swarmrec.services.settings import PlaceSettings

__all__ = [
    "BINARY",
    "ENV_VAR",
    "CompiledHost",
    "binary",
    "candidates",
    "exec_host",
    "host_spec",
    "is_compiled",
]

BINARY = "swarmrec-dataplane"
#: Names the binary explicitly (an image, a build elsewhere).
ENV_VAR = "SWARMREC_DATAPLANE"
#: How long a compiled child of a mixed host may take to say it is ready.
READY_TIMEOUT_S = 60.0


def is_compiled(config: Config, has_compiled: bool) -> bool:
    """Whether a kind (``has_compiled``: its registry entry's flag) is served compiled with ``config``."""
    return has_compiled and config.bus.data_plane == "compiled"


def candidates() -> list[Path]:
    """Where the compiled host may be, in the order it is looked for."""
    named = os.environ.get(ENV_VAR)
    out = [Path(named)] if named else []
    out.append(Path(swarmrec.__file__).resolve().parent.parent / "target" / "release" / BINARY)
    found = shutil.which(BINARY)
    if found:
        out.append(Path(found))
    return out


def binary() -> Path:
    """The compiled host's executable; ConfigError saying how to build it when absent."""
    for path in candidates():
        if path.is_file() and os.access(path, os.X_OK):
            return path
    named = os.environ.get(ENV_VAR)
    where = f"${ENV_VAR} ({named}), " if named else ""
    raise ConfigError(
        f"data_plane is compiled but {BINARY} is not built ({where}target/release, PATH): "
        "run `make dataplane` (cargo build --release), or set data_plane to python"
    )


def _service(h: Hosted) -> dict[str, Any]:
    """One service's resolved settings, as the binary reads them (dataplane/src/spec.rs)."""
    bus = h.config.bus
    places = h.config.get(PlaceSettings)
    preset = get_preset(places.preset)
    storage = h.config.get(StorageSettings) if h.config.has(StorageSettings) else None
    return {
        "kind": h.kind,
        "wire_kind": int(h.wire_kind),
        "swarm": bus.swarm,
        "robot": bus.robot,
        "n_robots": bus.n_robots,
        "max_message_bytes": bus.max_message_bytes,
        "data_dir": str(storage.data_dir) if storage is not None and storage.data_dir is not None else None,
        "fsync": bool(storage is not None and storage.fsync),
        "places": {
            "n_labels": places.n_labels,
            "d": float(preset.d),
            "min_common": preset.min_common,
            "same_label_only": preset.same_label_only,
            "max_objects_per_frame": places.max_objects_per_frame,
            "max_objects_per_label": places.max_objects_per_label,
            "verify_max_frames": places.verify_max_frames,
            "verify_max_object_pairs": places.verify_max_object_pairs,
        },
    }


def host_spec(hosted: Sequence[Hosted]) -> dict[str, Any]:
    """What ``swarmrec-dataplane host --spec-json`` takes for ``hosted`` (one session)."""
    if not hosted:
        raise ConfigError("a host runs at least one service")
    bus = session_bus(hosted)
    log = service_logger(hosted[0].kind, bus.robot, bus.log_level)
    conf = zenoh_config(bus, hosted[0].security, identity=session_identity(hosted), log=log)
    deepen_send_queue(conf)  # the compiled host always runs zenoh on one thread
    return {
        "zenoh": json.loads(str(conf)),
        "metrics_host": bus.metrics_host,
        "metrics_port": bus.metrics_port,
        "log_level": bus.log_level,
        "version": swarmrec.__version__,
        "services": [_service(h) for h in hosted],
    }


def _argv(hosted: Sequence[Hosted]) -> list[str]:
    exe = str(binary())
    return [exe, "host", "--spec-json", json.dumps(host_spec(hosted))]


def exec_host(hosted: Sequence[Hosted]) -> NoReturn:
    """Become the compiled host of ``hosted`` (this process is replaced)."""
    argv = _argv(hosted)
    sys.stdout.flush()
    sys.stderr.flush()
    os.execv(argv[0], argv)


class CompiledHost:
    """The compiled kinds of a mixed ``swarmrec host``, in a child process."""

    def __init__(self, hosted: Sequence[Hosted]) -> None:
        self.proc = subprocess.Popen(_argv(hosted), stdout=subprocess.PIPE, text=True)
        self.services: list[dict[str, Any]] = []
        ready = threading.Event()
        thread = threading.Thread(target=self._read, args=(ready,), name="compiled-host-stdout", daemon=True)
        thread.start()
        if not ready.wait(READY_TIMEOUT_S) or not self.services:
            self.stop()
            raise ConfigError(
                f"{BINARY} did not say it was ready in {READY_TIMEOUT_S:g} s "
                f"(exit code {self.proc.returncode}); its log lines are above"
            )

    def _read(self, ready: threading.Event) -> None:
        assert self.proc.stdout is not None
        for msg in ready_events(self.proc.stdout):
            if not ready.is_set():
                keep = ("service", "robot", "metrics_url")
                self.services = [{k: e[k] for k in keep if k in e} for e in ready_entries(msg)]
                ready.set()
        ready.set()  # the child ended before it was ready: the caller sees no services

    def stop(self, timeout_s: float = 10.0) -> int:
        """SIGTERM, wait, then SIGKILL; the exit code."""
        return terminate(self.proc, timeout_s)
