"""Kinds served by the compiled host, ``swarmrec-dataplane`` (docs/dataplane.md).

A kind whose registry entry says ``compiled`` has a second implementation in Rust
(``dataplane/``), on the same keys, messages, error codes, metrics, logs and record
logs. The ``data_plane`` setting picks it: ``swarmrec serve`` and ``swarmrec host``
resolve every setting here, as for a Python service, and hand them to the binary
whole (``--spec-file``, a JSON file the binary removes once read), so the two
implementations never read settings differently; the zenoh configuration travels as
the Python binding prints it (TLS files, access control, endpoints). Then:

* ``swarmrec serve <kind>``: the process becomes the compiled host (``exec``): no
  Python stays behind it. An index shard's coordinator, which computes placements, is
  Python: the compiled host runs it in a child process of its own, this same command
  line with :data:`COORDINATORS_ONLY` set (:mod:`swarmrec.services.shard_coordinator`).
* ``swarmrec host`` with only compiled kinds: the same.
* ``swarmrec host`` mixing both: the compiled kinds run in a child process on a
  session of their own (the same certificate), started first; its services are listed
  in the host's readiness line beside the Python ones, and it is stopped with the host
  (and dies with it: ``PR_SET_PDEATHSIG``). Compiled index shards' coordinators then run
  in the Python host.

The binary is found at ``$SWARMREC_DATAPLANE``, else in the checkout's
``target/release`` (``make dataplane`` builds it there), else on ``PATH``.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NoReturn

import swarmrec
from swarmrec.core.placement import groups_from_bounds, ring
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
from swarmrec.services.settings import DetectorSettings, ExplainSettings, IndexSettings, PlaceSettings
from swarmrec.wire.placement import placement_to_proto

__all__ = [
    "BINARY",
    "COORDINATORS_ONLY",
    "ENV_VAR",
    "CompiledHost",
    "binary",
    "candidates",
    "coordinator_command",
    "exec_host",
    "host_spec",
    "index_shards",
    "is_compiled",
    "stop_timeout_s",
]

BINARY = "swarmrec-dataplane"
#: Names the binary explicitly (an image, a build elsewhere).
ENV_VAR = "SWARMREC_DATAPLANE"
#: Set in the environment of the process a compiled host starts for its index shards'
#: coordinators: the same command line then runs only those.
COORDINATORS_ONLY = "SWARMREC_SHARD_COORDINATORS_ONLY"
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


def _index_settings(h: Hosted) -> IndexSettings:
    return h.config.get(IndexSettings) if h.config.has(IndexSettings) else IndexSettings()


def _index(h: Hosted) -> dict[str, Any]:
    """An index shard's settings beyond the place settings (dataplane/src/spec.rs,
    IndexSpec), with the placement a shard with nothing on disk starts from: computed by
    the Python core, the one implementation of the placement rules."""
    bus = h.config.bus
    places = h.config.get(PlaceSettings)
    index = _index_settings(h)
    groups = groups_from_bounds(places.bounds(bus).tolist())
    first = ring(groups, range(bus.n_robots), replicas=index.replicas)
    return {
        "groups": [list(g) for g in groups],
        "n_ret": get_preset(places.preset).n_ret,
        "lockstep": places.lockstep,
        "transfer_page": index.transfer_page,
        "drain_timeout_s": index.drain_timeout_s,
        "initial_placement": list(placement_to_proto(first).SerializeToString()),
    }


def _descriptor(h: Hosted) -> dict[str, Any]:
    """A descriptor's settings beyond the place settings (dataplane/src/spec.rs,
    DescriptorSpec), with the placement it routes with until it learns better (version 0,
    as the Python descriptor starts from)."""
    bus = h.config.bus
    places = h.config.get(PlaceSettings)
    preset = get_preset(places.preset)
    index = _index_settings(h)
    explain = h.config.get(ExplainSettings) if h.config.has(ExplainSettings) else ExplainSettings()
    groups = groups_from_bounds(places.bounds(bus).tolist())
    first = ring(groups, range(bus.n_robots), replicas=index.replicas)
    return {
        "n_ret": preset.n_ret,
        "n_fq": preset.n_fq,
        "min_objects": preset.min_objects,
        "exclusion": preset.exclusion,
        "loop_closure_min_score": float(places.loop_closure_min_score),
        "suspect_s": index.suspect_s,
        "pending_capacity": index.pending_capacity,
        "retry_interval_s": index.retry_interval_s,
        "explain_reports": explain.explain_reports,
        "request_timeout_s": bus.request_timeout_s,
        "initial_placement": list(placement_to_proto(first).SerializeToString()),
    }


def _detector(h: Hosted) -> dict[str, Any]:
    """A replaying detector's frames, read and put on the wire by the Python reader and
    codec (the same bytes the Python detector sends), and its outbox's settings
    (dataplane/src/spec.rs, DetectorSpec)."""
    # Imported here: only a host of detectors reads datasets.
    from swarmrec.services.detector.replay import wire_frames

    detector = h.config.get(DetectorSettings)
    _ids, frames = wire_frames(h.config)
    return {
        "frames": [{"wire": f.hex()} if isinstance(f, bytes) else {"unsendable": f} for f in frames],
        "dataset": detector.dataset,
        "outbox_capacity": detector.outbox_capacity,
        "outbox_retry_s": detector.outbox_retry_s,
        # A frame's query holds several nested requests: the reference gives it their time and some.
        "process_timeout_s": 4 * h.config.bus.request_timeout_s,
    }


def _service(h: Hosted) -> dict[str, Any]:
    """One service's resolved settings, as the binary reads them (dataplane/src/spec.rs)."""
    bus = h.config.bus
    storage = h.config.get(StorageSettings) if h.config.has(StorageSettings) else None
    return {
        "index": _index(h) if h.kind == "index-shard" else None,
        "descriptor": _descriptor(h) if h.kind == "descriptor" else None,
        "detector": _detector(h) if h.kind == "detector" else None,
        "kind": h.kind,
        "wire_kind": int(h.wire_kind),
        "swarm": bus.swarm,
        "robot": bus.robot,
        "n_robots": bus.n_robots,
        "max_message_bytes": bus.max_message_bytes,
        "data_dir": str(storage.data_dir) if storage is not None and storage.data_dir is not None else None,
        "fsync": bool(storage is not None and storage.fsync),
        # A router has no place settings (the binary then reads defaults it never uses).
        **({"places": _places(h.config.get(PlaceSettings))} if h.config.has(PlaceSettings) else {}),
    }


def _places(places: PlaceSettings) -> dict[str, Any]:
    """The place-recognition settings a verifier reads (dataplane/src/spec.rs, PlaceSpec)."""
    preset = get_preset(places.preset)
    return {
        "n_labels": places.n_labels,
        "d": float(preset.d),
        "min_common": preset.min_common,
        "same_label_only": preset.same_label_only,
        "max_objects_per_frame": places.max_objects_per_frame,
        "max_objects_per_label": places.max_objects_per_label,
        "verify_max_frames": places.verify_max_frames,
        "verify_max_object_pairs": places.verify_max_object_pairs,
    }


def host_spec(
    hosted: Sequence[Hosted], *, coordinator: Sequence[str] = (), die_with_parent: bool = False
) -> dict[str, Any]:
    """What ``swarmrec-dataplane host --spec-file`` reads for ``hosted`` (one session);
    ``coordinator``: the command of the Python process the host runs beside it for its
    index shards' coordinators; ``die_with_parent``: the host is a Python host's child."""
    if not hosted:
        raise ConfigError("a host runs at least one service")
    bus = session_bus(hosted)
    log = service_logger(hosted[0].kind, bus.robot, bus.log_level)
    conf = zenoh_config(bus, hosted[0].security, identity=session_identity(hosted), log=log)
    if bus.mode != "router":
        deepen_send_queue(conf)  # the compiled host runs zenoh on one thread, but for a router
    return {
        "zenoh": json.loads(str(conf)),
        "metrics_host": bus.metrics_host,
        "metrics_port": bus.metrics_port,
        "log_level": bus.log_level,
        "version": swarmrec.__version__,
        "services": [_service(h) for h in hosted],
        "coordinator": list(coordinator),
        "die_with_parent": die_with_parent,
    }


def _argv(
    hosted: Sequence[Hosted], *, coordinator: Sequence[str] = (), die_with_parent: bool = False
) -> list[str]:
    exe = str(binary())
    spec = host_spec(hosted, coordinator=coordinator, die_with_parent=die_with_parent)
    # In a file, not in an argument: Linux takes at most 128 kB an argument, and a host of
    # fifty shards says more. The host removes the file once it has read it.
    fd, path = tempfile.mkstemp(prefix="swarmrec-host-", suffix=".json")
    with os.fdopen(fd, "w") as f:
        json.dump(spec, f)
    return [exe, "host", "--spec-file", path]


def coordinator_command(argv: Sequence[str] | None = None) -> list[str]:
    """This command line again (``argv``: ``sys.argv``), run with :data:`COORDINATORS_ONLY`
    set: it resolves the same settings and runs only the coordinators of the compiled index
    shards it names (:func:`swarmrec.services.registry.serve_many`)."""
    args = list(sys.argv if argv is None else argv)
    return ["env", f"{COORDINATORS_ONLY}=1", sys.executable, "-m", "swarmrec", *args[1:]]


def index_shards(hosted: Sequence[Hosted]) -> list[Hosted]:
    """The index shards among compiled ``hosted``: each needs a Python process beside it for
    its coordinator (:mod:`swarmrec.services.shard_coordinator`), and drains on stop."""
    return [h for h in hosted if h.kind == "index-shard"]


def stop_timeout_s(hosted: Sequence[Hosted]) -> float:
    """How long the compiled host may take to stop: an index shard drains first."""
    drains = [_index_settings(h).drain_timeout_s for h in index_shards(hosted)]
    return 10.0 + max(drains, default=0.0)


def exec_host(hosted: Sequence[Hosted]) -> NoReturn:
    """Become the compiled host of ``hosted`` (this process is replaced); with index
    shards, the host runs their coordinators beside it (:func:`coordinator_command`)."""
    argv = _argv(hosted, coordinator=coordinator_command() if index_shards(hosted) else ())
    sys.stdout.flush()
    sys.stderr.flush()
    os.execv(argv[0], argv)


class CompiledHost:
    """The compiled kinds of a mixed ``swarmrec host``, in a child process."""

    def __init__(self, hosted: Sequence[Hosted]) -> None:
        argv = _argv(hosted, die_with_parent=True)
        self.proc = subprocess.Popen(argv, stdout=subprocess.PIPE, text=True)
        self.services: list[dict[str, Any]] = []
        #: The host's readiness line as it printed it.
        self.ready_line: dict[str, Any] = {}
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
                self.ready_line = msg
                keep = ("service", "robot", "metrics_url")
                self.services = [{k: e[k] for k in keep if k in e} for e in ready_entries(msg)]
                ready.set()
        ready.set()  # the child ended before it was ready: the caller sees no services

    def stop(self, timeout_s: float = 10.0) -> int:
        """SIGTERM, wait, then SIGKILL; the exit code."""
        return terminate(self.proc, timeout_s)
