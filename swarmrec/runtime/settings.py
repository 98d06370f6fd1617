"""Settings, one component at a time, each declared once.

A component is a frozen dataclass (:class:`Component`) whose fields are the
settings of one concern: the bus (:class:`BusSettings`), storage
(:class:`StorageSettings`), place recognition, the detector, fusion ... (those
live in :mod:`swarmrec.services.settings`). Each field is declared with
:func:`setting` (its default and its help), and everything else is generated
from that one declaration:

* a command-line flag ``--<name-with-dashes>`` in an argument group per component
  (:func:`add_flags`); a service's ``--help`` lists only its own components;
* an environment variable ``SWARMREC_<NAME>``;
* the key of a flat TOML file (one file can configure a whole robot)::

      # robot3.toml
      swarm = "lab"
      robot = 3
      n_robots = 10
      connect = ["tls/10.0.0.1:7447", "tls/10.0.0.2:7447"]
      pki_dir = "/etc/swarmrec/pki"
      data_dir = "/var/lib/swarmrec"

      SWARMREC_ROBOT=3 swarmrec serve index-shard --config robot3.toml --n-robots 10

Layers, lowest first: defaults < TOML file < environment < flags
(:func:`load_config`). Lists are comma-separated in the environment and in
flags. Setting names are unique across components (a test checks it), so the
flat namespace stays unambiguous. Each component validates itself on
construction; checks between components (``robot < n_robots`` is the bus's own,
``label_bounds`` against ``n_robots`` is place recognition's) run when a
:class:`Config` is built.
"""

from __future__ import annotations

import argparse
import math
import os
import tomllib
import types
import typing
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import MISSING, Field, dataclass, field, fields, replace
from pathlib import Path
from typing import Any, ClassVar, Literal, TypeVar

from swarmrec.errors import ConfigError
from swarmrec.runtime.keys import validate_swarm_name

__all__ = [
    "AUTO_QUEUE_ABOVE",
    "ENV_PREFIX",
    "MAX_STATS_KEYS",
    "BusSettings",
    "Component",
    "Config",
    "SecuritySettings",
    "SettingInfo",
    "StorageSettings",
    "add_flags",
    "describe",
    "load_config",
    "setting",
    "to_env",
    "to_flags",
]

ENV_PREFIX = "SWARMREC_"

T = TypeVar("T")
C = TypeVar("C", bound="Component")


def setting(default: T, help: str) -> T:
    """A settings field: its default and the one line of help every flag, variable and
    contract page shows."""
    out: T = field(default=default, metadata={"help": help})
    return out


#: Key expressions a router may count bytes of (each costs it a match per new resource).
MAX_STATS_KEYS = 64


@dataclass(frozen=True)
class Component:
    """Base of a settings component. Subclasses are ``@dataclass(frozen=True)`` with
    :func:`setting` fields, a ``title`` (the flag group) and, when values can be
    wrong, :meth:`problems` (and :meth:`problems_with` for checks against other
    components)."""

    title: ClassVar[str] = "settings"

    def problems(self) -> list[str]:
        """What is wrong with these values on their own (empty when valid)."""
        return []

    def problems_with(self, config: Config) -> list[str]:
        """What is wrong with these values given the other components of ``config``."""
        return []

    def max_robot_id(self, bus: BusSettings) -> int:
        """The highest robot id this component lets a service take (the bus allows
        ``n_robots - 1``; the elastic index lets index shards go beyond)."""
        return bus.n_robots - 1

    def __post_init__(self) -> None:
        found = self.problems()
        if found:
            raise ConfigError(f"invalid {self.title} settings: " + "; ".join(found))

    def with_(self: C, **changes: Any) -> C:
        """A copy with some settings changed (validated again)."""
        return replace(self, **changes)


@dataclass(frozen=True)
class SettingInfo:
    """One declared setting, as flags, variables and docs show it."""

    component: type[Component]
    name: str
    default: Any
    help: str

    @property
    def flag(self) -> str:
        return "--" + self.name.replace("_", "-")

    @property
    def env(self) -> str:
        return ENV_PREFIX + self.name.upper()

    @property
    def shown_default(self) -> str:
        d = self.default
        return ",".join(map(str, d)) if isinstance(d, tuple) else repr(d)


def describe(component: type[Component]) -> list[SettingInfo]:
    """Every setting of ``component``, in declaration order."""
    out = []
    for f in fields(component):
        default = f.default if f.default is not MISSING else None
        out.append(SettingInfo(component, f.name, default, str(f.metadata.get("help", ""))))
    return out


# --- the two components every service has -------------------------------------------

ZenohMode = Literal["client", "peer", "router"]
EndpointDispatch = Literal["auto", "channel", "queue"]
#: Which implementation serves a kind that has a compiled one (swarmrec.services.compiled).
DataPlane = Literal["python", "compiled"]
#: zenoh's runtime in a service process: one thread, or zenoh's own pools.
ZenohRuntime = Literal["single", "pools"]
#: zenoh on one thread (../shared/ZENOH.md): every pool handed over to one worker.
#: Sending stays on that thread too: with the sender on a thread of its own, zenoh's TLS
#: link reads and writes one TLS stream from two threads at once, which corrupts it
#: (upstream zenoh issue 2557; measured here: a compiled host crashed within seconds
#: under mutual TLS). One thread has its own hazard, answered by SINGLE_RUNTIME_TX_QUEUE.
SINGLE_THREAD_RUNTIME = (
    "(app:(worker_threads:1),rx:(handover:app),tx:(handover:app),net:(handover:app),acc:(handover:app))"
)
#: Batches (64 kB each) a link's send queue holds per priority in a process on the single
#: runtime: zenoh's most. With its default of 2, a message over 128 kB (a 400 kB request
#: is 7 batches) waits for room only the sender can make, and the sender runs on the one
#: thread that waits: after 5 s zenoh closes the link and the message is lost
#: (docs/dataplane.md, "No silent loss"). 16 batches hold one message up to ~1 MB.
SINGLE_RUNTIME_TX_QUEUE = 16
#: ``dispatch = "auto"`` uses queues in a process hosting more services than this: the two
#: were even for 20 services a process (5 robots), queues faster for 52 (13 robots) and
#: more (docs/swarm.md); a process of one service keeps zenoh's channels as it always had.
AUTO_QUEUE_ABOVE = 32


@dataclass(frozen=True)
class BusSettings(Component):
    """Who this service is on the bus and how it talks: every service has these."""

    title: ClassVar[str] = "bus"

    swarm: str = setting("default", "name of the swarm: a key segment, so swarms sharing a router never mix")
    robot: int = setting(0, "this robot's id (0 .. n_robots - 1)")
    n_robots: int = setting(1, "robots in the swarm")
    mode: ZenohMode = setting("client", "zenoh mode of the session: client, peer or router")
    connect: tuple[str, ...] = setting(
        ("tls/127.0.0.1:7447",), "router endpoints to connect to (several give failover)"
    )
    listen: tuple[str, ...] = setting((), "endpoints to listen on (a router)")
    peers: tuple[str, ...] = setting(
        (),
        "other routers a router dials (the mesh topology: its robot's radio neighbours, docs/mesh.md); "
        "it keeps redialling each one it loses",
    )
    stats_keys: tuple[str, ...] = setting(
        (),
        "key expressions a router counts payload bytes of, per link to another router (zenoh's "
        "per-key stats; the mesh: one per message type, docs/mesh.md)",
    )
    metrics_port: int = setting(0, "Prometheus endpoint port (0: a free one, -1: none)")
    metrics_host: str = setting("127.0.0.1", "Prometheus endpoint address")
    workers: int = setting(
        2, "worker threads per endpoint: they take its requests in turn and run the handler (see dispatch)"
    )
    dispatch: EndpointDispatch = setting(
        "auto",
        "how requests reach an endpoint's workers: channel (zenoh's channel; each waiting worker "
        "wakes every 100 ms), queue (zenoh's callback fills a queue; its receive thread takes the "
        "interpreter lock per request) or auto (queue in a process of more than "
        f"{AUTO_QUEUE_ABOVE} services, channel otherwise)",
    )
    data_plane: DataPlane = setting(
        "compiled",
        "which implementation serves a kind that has a compiled one (docs/dataplane.md): compiled "
        "(the Rust host, swarmrec-dataplane, built by `make dataplane`: same keys, messages, metrics "
        "and logs) or python (the reference); kinds without a compiled one are python either way",
    )
    zenoh_runtime: ZenohRuntime = setting(
        "single",
        "zenoh's runtime in a Python service process: single (one thread, with a deeper send "
        "queue: less CPU a message, docs/dataplane.md) or pools (zenoh's default thread pools); "
        "a router always runs pools, the compiled host single (but for a router); a ZENOH_RUNTIME "
        "environment variable overrides both",
    )
    request_timeout_s: float = setting(2.0, "how long a service waits for a peer's reply, seconds")
    max_message_bytes: int = setting(1 << 20, "largest request payload accepted, bytes")
    log_level: str = setting("INFO", "logging level")

    def problems(self) -> list[str]:
        problems: list[str] = []
        try:
            validate_swarm_name(self.swarm)
        except ConfigError as e:
            problems.append(str(e))
        if self.n_robots < 1:
            problems.append(f"n_robots must be >= 1, got {self.n_robots}")
        if self.mode not in ("client", "peer", "router"):
            problems.append(f"mode must be client, peer or router, got {self.mode!r}")
        if self.mode == "router" and not self.listen:
            problems.append("a router needs at least one --listen endpoint")
        if self.peers and self.mode != "router":
            problems.append("only a router dials peers (--peers); a client or peer uses --connect")
        if self.stats_keys and self.mode != "router":
            problems.append("only a router counts bytes per key (--stats-keys)")
        if len(self.stats_keys) > MAX_STATS_KEYS:
            problems.append(f"at most {MAX_STATS_KEYS} stats keys, got {len(self.stats_keys)}")
        if self.mode == "client" and not self.connect:
            problems.append("a client needs at least one --connect endpoint")
        if not -1 <= self.metrics_port <= 65535:
            problems.append(f"metrics_port must be -1 .. 65535, got {self.metrics_port}")
        if self.workers < 1:
            problems.append(f"workers must be >= 1, got {self.workers}")
        if self.dispatch not in ("auto", "channel", "queue"):
            problems.append(f"dispatch must be auto, channel or queue, got {self.dispatch!r}")
        if self.zenoh_runtime not in ("single", "pools"):
            problems.append(f"zenoh_runtime must be single or pools, got {self.zenoh_runtime!r}")
        if self.data_plane not in ("python", "compiled"):
            problems.append(f"data_plane must be python or compiled, got {self.data_plane!r}")
        if not (math.isfinite(self.request_timeout_s) and self.request_timeout_s > 0):
            problems.append(f"request_timeout_s must be > 0, got {self.request_timeout_s}")
        if not 1024 <= self.max_message_bytes <= 1 << 24:
            # Above 16 MiB a stored record would not fit the record log (runtime/storage.py).
            problems.append(f"max_message_bytes must be 1024 .. {1 << 24}, got {self.max_message_bytes}")
        if self.log_level.upper() not in ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL"):
            problems.append(
                f"log_level must be DEBUG, INFO, WARNING, ERROR or CRITICAL, got {self.log_level!r}"
            )
        if self.robot < 0:
            problems.append(f"robot must be >= 0, got {self.robot}")
        return problems

    def problems_with(self, config: Config) -> list[str]:
        # The highest id any component of this service allows (index shards may go beyond n_robots).
        highest = max(p.max_robot_id(self) for p in config.parts)
        if self.robot > highest:
            return [f"robot must be in [0, {highest + 1}) (n_robots={self.n_robots}), got {self.robot}"]
        return []


@dataclass(frozen=True)
class StorageSettings(Component):
    """Where a stateful service keeps what it stores (record logs, replayed on start)."""

    title: ClassVar[str] = "storage"

    data_dir: Path | None = setting(
        None, "folder of the service's stored data; unset: memory only (lost on restart)"
    )
    fsync: bool = setting(False, "fsync every stored record (survives power loss, costs ~1 ms a record)")


SecurityMode = Literal["mtls", "insecure"]


@dataclass(frozen=True)
class SecuritySettings(Component):
    """How this process's zenoh links are secured: mutual TLS (the default) or, for
    debugging only, plaintext (docs/security.md)."""

    title: ClassVar[str] = "security"

    security: SecurityMode = setting(
        "mtls",
        "mtls: every zenoh link is mutual TLS with this process's certificate (a router also "
        "enforces the swarm's access control); insecure: plaintext, unauthenticated, loudly logged",
    )
    pki_dir: Path | None = setting(
        None,
        "folder with the swarm CA (ca.pem), this process's <identity>.pem and .key, and for a "
        "router acl.json (`swarmrec pki init` writes them)",
    )
    identity: str = setting(
        "",
        "common name of this process's certificate; empty: its kind's own "
        "(r<robot>.<kind>.<swarm>, router.<swarm>, client.gateway.<swarm>)",
    )
    insecure_reason: str = setting(
        "", "why the links are plaintext (insecure mode; written in the warning it logs)"
    )

    def problems(self) -> list[str]:
        problems = []
        if self.security not in ("mtls", "insecure"):
            problems.append(f"security must be mtls or insecure, got {self.security!r}")
        if self.identity and not all(c.isalnum() or c in ".-_" for c in self.identity):
            problems.append(
                f"identity must be a certificate common name (a-z 0-9 . - _), got {self.identity!r}"
            )
        return problems


# --- a service's whole configuration ----------------------------------------------


@dataclass(frozen=True)
class Config:
    """The components one service reads, checked against each other on construction."""

    parts: tuple[Component, ...]

    def __post_init__(self) -> None:
        kinds = [type(p) for p in self.parts]
        if len(set(kinds)) != len(kinds):
            raise ValueError(f"a component appears twice: {[k.__name__ for k in kinds]}")
        problems = [msg for p in self.parts for msg in p.problems_with(self)]
        if problems:
            raise ConfigError("invalid settings: " + "; ".join(problems))

    @classmethod
    def of(cls, *parts: Component) -> Config:
        return cls(tuple(parts))

    def get(self, component: type[C]) -> C:
        """The component of type ``component``; ConfigError when this config has none."""
        for p in self.parts:
            if type(p) is component:
                return p
        raise ConfigError(f"no {component.title} settings here (this service does not read them)")

    def has(self, component: type[Component]) -> bool:
        return any(type(p) is component for p in self.parts)

    @property
    def bus(self) -> BusSettings:
        return self.get(BusSettings)

    def replace(self, *parts: Component) -> Config:
        """A copy with ``parts`` in place of the components of their types (added when absent)."""
        swapped = {type(p): p for p in parts}
        kept = tuple(swapped.pop(type(p), p) for p in self.parts)
        return Config(kept + tuple(swapped.values()))


# --- layering -------------------------------------------------------------------------


def _hints(component: type[Component]) -> dict[str, Any]:
    return typing.get_type_hints(component)


def _base_type(hint: Any) -> Any:
    if isinstance(hint, types.UnionType):  # X | None
        return next(a for a in typing.get_args(hint) if a is not type(None))
    return hint


def _convert(component: type[Component], name: str, value: Any) -> Any:
    """``value`` (from TOML, the environment or a flag) as setting ``name``'s type."""
    hint = _hints(component)[name]
    base = _base_type(hint)
    origin = typing.get_origin(base)
    optional = isinstance(hint, types.UnionType)
    try:
        if optional and isinstance(value, str) and value.strip() == "":
            return None
        if origin is tuple:
            item = typing.get_args(base)[0]
            items = [v.strip() for v in value.split(",") if v.strip()] if isinstance(value, str) else value
            return tuple(_scalar(item, v) for v in items)
        if base is bool:
            if isinstance(value, bool):
                return value
            text = str(value).strip().lower()
            if text in ("1", "true", "yes", "on"):
                return True
            if text in ("0", "false", "no", "off"):
                return False
            raise ValueError(f"not a boolean: {value!r}")
        if base is Path:
            return Path(value) if str(value) else None
        if origin is Literal:
            return str(value)
        return _scalar(base, value)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"setting {name}: cannot read {value!r} ({e})") from None


def _scalar(kind: Any, value: Any) -> Any:
    if kind is int and (isinstance(value, bool) or (isinstance(value, float) and not value.is_integer())):
        # TOML gives typed values: int(2.9) or int(True) would silently become 2 or 1.
        raise ValueError(f"not an integer: {value!r}")
    return kind(value)


def _owner(known: Iterable[type[Component]]) -> dict[str, type[Component]]:
    out: dict[str, type[Component]] = {}
    for comp in known:
        for f in fields(comp):
            if f.name in out and out[f.name] is not comp:
                raise ValueError(
                    f"setting {f.name} is declared by {out[f.name].__name__} and {comp.__name__}"
                )
            out[f.name] = comp
    return out


def _from_file(path: Path, owner: Mapping[str, type[Component]]) -> dict[str, Any]:
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as e:
        raise ConfigError(f"cannot read config file {path}: {e.strerror}") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"config file {path} is not valid TOML: {e}") from None
    unknown = sorted(set(data) - set(owner))
    if unknown:
        raise ConfigError(f"config file {path}: unknown settings {', '.join(unknown)}")
    return {k: _convert(owner[k], k, v) for k, v in data.items()}


def add_flags(parser: argparse.ArgumentParser, components: Sequence[type[Component]]) -> None:
    """``--config`` and one flag per setting of ``components``, grouped by component
    (default None, so a flag left out does not override a lower layer)."""
    parser.add_argument(
        "--config", type=Path, help=f"TOML file of settings (below env and flags; env {ENV_PREFIX}CONFIG)"
    )
    for comp in components:
        group = parser.add_argument_group(comp.title, (comp.__doc__ or "").strip().splitlines()[0])
        for info in describe(comp):
            group.add_argument(
                info.flag,
                dest=info.name,
                default=None,
                metavar=info.name.upper(),
                help=f"{info.help} (default {info.shown_default}; env {info.env})",
            )


def load_config(
    components: Sequence[type[Component]],
    args: argparse.Namespace | None = None,
    *,
    env: Mapping[str, str] | None = None,
    config_file: Path | None = None,
    known: Sequence[type[Component]] = (),
    overrides: Mapping[str, Any] | None = None,
) -> Config:
    """The :class:`Config` of ``components`` from the layers, lowest first: defaults,
    the TOML file (``config_file``, ``--config`` or ``SWARMREC_CONFIG``), ``SWARMREC_*``
    variables, flags, then ``overrides`` (what the caller fixes, such as a router's
    mode). The file may also name settings of the ``known`` components this service
    does not read (one file configures a whole robot); they are ignored."""
    environ = os.environ if env is None else env
    owner = _owner([*components, *known])
    own = {name for comp in components for name in (f.name for f in fields(comp))}
    values: dict[str, Any] = {}
    path = config_file if config_file is not None else getattr(args, "config", None)
    if path is None and environ.get(ENV_PREFIX + "CONFIG"):
        path = Path(environ[ENV_PREFIX + "CONFIG"])
    if path is not None:
        values.update({k: v for k, v in _from_file(Path(path), owner).items() if k in own})
    for name in own:
        key = ENV_PREFIX + name.upper()
        if key in environ:
            values[name] = _convert(owner[name], name, environ[key])
    if args is not None:
        for name in own:
            value = getattr(args, name, None)
            if value is not None:
                values[name] = _convert(owner[name], name, value)
    values.update(overrides or {})
    parts = []
    for comp in components:
        mine = {f.name: values[f.name] for f in fields(comp) if f.name in values}
        parts.append(comp(**mine))
    return Config(tuple(parts))


def _text(value: Any) -> str:
    if isinstance(value, tuple):
        return ",".join(map(str, value))
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)


def _changed(component: Component, only_changed: bool) -> list[tuple[str, Any]]:
    """(name, value) of ``component``'s settings that are not None (and differ from the
    default when ``only_changed``)."""
    out = []
    for f in fields(component):
        value = getattr(component, f.name)
        if value is None or (only_changed and value == f.default):
            continue
        out.append((f.name, value))
    return out


def to_flags(component: Component, *, only_changed: bool = False) -> list[str]:
    """Flags that reproduce ``component`` (settings left at None are left out, and those
    at their default too when ``only_changed``)."""
    out: list[str] = []
    for name, value in _changed(component, only_changed):
        out += ["--" + name.replace("_", "-"), _text(value)]
    return out


def to_env(component: Component, *, only_changed: bool = False) -> dict[str, str]:
    """``SWARMREC_*`` variables that reproduce ``component`` (None settings left out, and
    those at their default too when ``only_changed``)."""
    return {ENV_PREFIX + name.upper(): _text(value) for name, value in _changed(component, only_changed)}


def field_of(component: type[Component], name: str) -> Field[Any]:
    """The dataclass field ``name`` of ``component`` (for docs and tests)."""
    for f in fields(component):
        if f.name == name:
            return f
    raise KeyError(f"{component.__name__} has no setting {name!r}")
