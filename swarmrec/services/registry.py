"""The service registry: one entry per service kind, the one list every part reads.

The CLI (``swarmrec serve <kind>``: which kinds exist, which settings each
takes), the runner (wire enum, metrics, router mode), the client (kind names
from the wire enum), every deployment (which kinds run per robot, which keep
data on a volume) and the contract pages under ``services/`` all read
:data:`REGISTRY`. A new service is one class plus one entry here; a test
checks the entries against the protobuf ``ServiceKind`` enum.

Factories are named ``"module:Class"`` and imported on demand, so a shard's
process never loads the detector's onnxruntime or the verifier's numba kernels.

Another package adds a kind without touching this file: it declares an entry
point in the group ``swarmrec.services`` naming its :class:`ServiceSpec`
(``echo = my_package.echo:SPEC``), and every swarmrec process registers it at
start (:func:`load_plugins`). Its wire value may be any number the
``ServiceKind`` enum does not use (proto3 enums are open).
"""

from __future__ import annotations

import importlib
import importlib.metadata
import json
import os
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Literal, cast

from swarmrec.errors import ConfigError
from swarmrec.runtime.metrics import MetricSet
from swarmrec.runtime.runner import Hosted, ServiceBase, ServiceContext, install_signals, run_services
from swarmrec.runtime.settings import BusSettings, Component, Config, SecuritySettings, StorageSettings
from swarmrec.services import compiled
from swarmrec.services.metrics import (
    DescriptorMetrics,
    DetectorMetrics,
    FusionMetrics,
    GatewayMetrics,
    PlaceOwnerMetrics,
    RouterMetrics,
    ShardMetrics,
    SlamMetrics,
    VerifierMetrics,
)
from swarmrec.services.settings import (
    ClassifierSettings,
    DetectorSettings,
    ExplainSettings,
    FusionSettings,
    GatewaySettings,
    IndexSettings,
    LandmarkSettings,
    PlaceSettings,
    RgbdSettings,
    SlamServiceSettings,
    VprSettings,
)
from swarmrec.wire import messages as pb

__all__ = [
    "PLUGIN_GROUP",
    "REGISTRY",
    "WORKLOADS",
    "Call",
    "CompiledWhen",
    "ServiceSpec",
    "all_components",
    "hosted",
    "kind_of_wire",
    "kinds",
    "load_plugins",
    "register",
    "serve",
    "serve_many",
    "spec",
]

Scope = Literal["robot", "swarm"]


@dataclass(frozen=True)
class CompiledWhen:
    """The configurations of a kind its compiled implementation serves."""

    #: In words, for the contract page.
    doc: str
    test: Callable[[Config], bool]


def _replaying(config: Config) -> bool:
    # A detector's replay mode: its frames come recorded, ready to send (the rgbd and
    # classifier modes run models, in Python).
    return not config.has(DetectorSettings) or config.get(DetectorSettings).detector_mode == "replay"


@dataclass(frozen=True)
class Call:
    """An endpoint a kind queries: ``kind``'s ``endpoint`` on its own robot (``own``) or on
    any robot. The router's access control grants a kind exactly its calls."""

    kind: str
    endpoint: str
    own: bool = False


@dataclass(frozen=True)
class ServiceSpec:
    """One service kind."""

    #: The kind's name: ``swarmrec serve <kind>``, the key segment, the container name part.
    kind: str
    #: The ``swarmrec.v1.ServiceKind`` value it reports in MemberInfo.
    wire: int
    #: ``"module:Class"`` of its :class:`~swarmrec.runtime.runner.ServiceBase` subclass.
    factory: str
    #: One line for ``--help`` and the contract page.
    summary: str
    #: ``robot``: one per robot; ``swarm``: one for the whole swarm (the router, the gateway).
    scope: Scope = "robot"
    #: Keeps what it stores in record logs under its data_dir (a volume in containers).
    stateful: bool = False
    #: Settings components it reads besides the bus (and storage, for a stateful kind).
    components: tuple[type[Component], ...] = ()
    #: The metric families it exports besides every service's own.
    metrics: type[MetricSet] | None = None
    #: A zenoh mode forced on its session (the router's), else the settings' own.
    zenoh_mode: str | None = None
    #: Common name of its certificate (``swarmrec.security.identity``'s scheme), with
    #: ``{robot}``, ``{kind}`` and ``{swarm}`` filled in; the ``identity`` setting overrides it.
    identity: str = "r{robot}.{kind}.{swarm}"
    # What it may do on the bus beyond serving its own endpoints, declaring its liveliness
    # token and putting its events: the router's access control is computed from these
    # (swarmrec.security.acl), for a plugin's kind as for a built-in one.
    #: Endpoints of other kinds (or of its own kind) it queries.
    calls: tuple[Call, ...] = ()
    #: Endpoints any client of the swarm may call (read-only: a client never stores).
    client_endpoints: tuple[str, ...] = ()
    #: Endpoints the operator (the replay driver) may call besides the clients'.
    operator_endpoints: tuple[str, ...] = ()
    #: Kinds whose members' liveliness it follows (to route around one that goes).
    watches: tuple[str, ...] = ()
    #: Mailboxes between robots of this kind: robot r reads its own ``<box>/*`` and puts on
    #: every other robot's ``<box>/<r>`` only, so the key's last segment names the sender.
    mailboxes: tuple[str, ...] = ()
    #: It says it is stopping with a liveliness token of its own (``draining``), and
    #: follows its peers' (who stays to take over what it holds).
    drains: bool = False
    #: It checks its peers' signatures: its container or pod also gets the public certificates
    #: of its kind on every other robot (a relayed message's origin signature is checked
    #: against its origin's, docs/security.md).
    peer_certificates: bool = False
    #: Also implemented in the compiled host (swarmrec-dataplane, docs/dataplane.md), which
    #: serves it when the ``data_plane`` setting says ``compiled``.
    compiled: bool = False
    #: When only some configurations of the kind are compiled (the rest run in Python
    #: whatever ``data_plane`` says): which, in words and as a test.
    compiled_when: CompiledWhen | None = None

    def compiled_for(self, config: Config) -> bool:
        """Whether the compiled host can serve this kind with ``config`` (``data_plane`` aside)."""
        return self.compiled and (self.compiled_when is None or self.compiled_when.test(config))

    @property
    def all_components(self) -> tuple[type[Component], ...]:
        """Every component the kind reads, bus first (what its flags and variables cover)."""
        extra = (StorageSettings,) if self.stateful and StorageSettings not in self.components else ()
        return (BusSettings, SecuritySettings, *extra, *self.components)

    def common_name(self, swarm: str, robot: int) -> str:
        """The common name of this kind's certificate on ``robot`` of ``swarm``."""
        return self.identity.format(robot=robot, kind=self.kind, swarm=swarm)

    def load(self) -> type[ServiceBase]:
        """The service class (imported now)."""
        module, _, name = self.factory.partition(":")
        cls = getattr(importlib.import_module(module), name)
        if not (isinstance(cls, type) and issubclass(cls, ServiceBase)):
            raise TypeError(f"{self.factory} is not a ServiceBase subclass")
        return cls


_PLACES = (PlaceSettings,)
# The shards and the descriptors that route to them share the elastic index's settings.
_INDEXED = (PlaceSettings, IndexSettings)

REGISTRY: dict[str, ServiceSpec] = {}


def register(entry: ServiceSpec) -> ServiceSpec:
    """Add a kind (tests add their own); its name and wire value must be new."""
    if entry.kind in REGISTRY:
        raise ValueError(f"service kind {entry.kind!r} is already registered")
    if any(e.wire == entry.wire for e in REGISTRY.values()):
        raise ValueError(f"wire value {entry.wire} of {entry.kind!r} is already taken")
    REGISTRY[entry.kind] = entry
    return entry


for _entry in (
    ServiceSpec(
        "router",
        pb.ServiceKind.SERVICE_KIND_ROUTER,
        "swarmrec.services.router:Router",
        "a zenoh router: routes the swarm's traffic, holds nothing",
        scope="swarm",
        zenoh_mode="router",
        identity="router.{swarm}",
        metrics=RouterMetrics,
        compiled=True,
    ),
    ServiceSpec(
        "detector",
        pb.ServiceKind.SERVICE_KIND_DETECTOR,
        "swarmrec.services.detector:Detector",
        "its robot's frames to constellations (replay, rgbd) or views to landmark probabilities (classifier)",
        components=(
            StorageSettings,
            PlaceSettings,
            DetectorSettings,
            RgbdSettings,
            VprSettings,
            ClassifierSettings,
            LandmarkSettings,
        ),
        metrics=DetectorMetrics,
        # Its robot's stage: the constellation query, the full-image query, a landmark round.
        calls=(
            Call("descriptor", "process", own=True),
            Call("place-owner", "process", own=True),
            Call("fusion", "start_round", own=True),
        ),
        operator_endpoints=("step", "replay", "classify"),
        compiled=True,
        compiled_when=CompiledWhen("replay mode only: rgbd and classifier run in Python", _replaying),
    ),
    ServiceSpec(
        "descriptor",
        pb.ServiceKind.SERVICE_KIND_DESCRIPTOR,
        "swarmrec.services.descriptor:Descriptor",
        "the two-step query for each of its robot's frames; keeps the loop closures and explains them",
        stateful=True,
        components=(*_INDEXED, ExplainSettings),
        metrics=DescriptorMetrics,
        calls=(
            Call("index-shard", "query"),
            Call("index-shard", "store"),
            Call("index-shard", "placement"),
            Call("verifier", "verify"),
            Call("verifier", "store", own=True),
        ),
        client_endpoints=("loop_closures", "explain"),
        watches=("index-shard",),  # it routes around shards that are gone
        compiled=True,
    ),
    ServiceSpec(
        "index-shard",
        pb.ServiceKind.SERVICE_KIND_INDEX_SHARD,
        "swarmrec.services.index_shard:IndexShard",
        "label groups of the swarm's descriptor index (replicated, handed off as shards come and go): "
        "candidates for partial queries",
        stateful=True,
        components=_INDEXED,
        metrics=ShardMetrics,
        # The elastic index: shards read each other's placement, the coordinator sends
        # placements, a shard copying a group pages through an owner's copy.
        calls=(
            Call("index-shard", "placement"),
            Call("index-shard", "adopt"),
            Call("index-shard", "transfer"),
        ),
        # A client reads through `lookup` (swarmrec.security.acl.SHARD_READ_ENDPOINT), added there.
        client_endpoints=("placement",),
        watches=("index-shard",),
        drains=True,
        compiled=True,
    ),
    ServiceSpec(
        "verifier",
        pb.ServiceKind.SERVICE_KIND_VERIFIER,
        "swarmrec.services.verifier:Verifier",
        "holds its robot's constellations and verifies candidates geometrically",
        stateful=True,
        components=_PLACES,
        metrics=VerifierMetrics,
        client_endpoints=("verify",),
        compiled=True,
    ),
    ServiceSpec(
        "place-owner",
        pb.ServiceKind.SERVICE_KIND_PLACE_OWNER,
        "swarmrec.services.place_owner:PlaceOwner",
        "full-image place recognition: owns clusters of the descriptor space (answers and stores the "
        "queries routed to them) and queries, verifies and keeps the loop closures of its robot's frames",
        stateful=True,
        components=(PlaceSettings, VprSettings),
        metrics=PlaceOwnerMetrics,
        # The owner of a query's cluster, the verifier of its match; the copy holders; and the
        # re-balancing (docs/vpr.md): the coordinator reads loads and sends tables, holders
        # move entries, a robot behind reads the coordinator's table.
        calls=(
            Call("place-owner", "query"),
            Call("verifier", "verify"),
            Call("verifier", "store", own=True),
            Call("place-owner", "store_copy"),
            Call("place-owner", "cluster_load"),
            Call("place-owner", "adopt_table"),
            Call("place-owner", "store_entries"),
            Call("place-owner", "table"),
        ),
        # `lookup`: the owner's search without the store (the gateway's PlaceQuery).
        client_endpoints=("assignment", "loop_closures", "lookup", "table"),
        operator_endpoints=("rebalance",),
        watches=("place-owner",),  # the coordinator is the lowest live one
    ),
    ServiceSpec(
        "fusion",
        pb.ServiceKind.SERVICE_KIND_FUSION,
        "swarmrec.services.fusion:FusionService",
        "floods classifier outputs to its radio neighbours and fuses what it hears (weighted naive Bayes)",
        components=(LandmarkSettings, FusionSettings),
        metrics=FusionMetrics,
        client_endpoints=("posterior",),
        # Flooding: who is a neighbour changes with the radio graph, so every other robot.
        mailboxes=("inbox",),
        # A relayed output carries its origin's signature.
        peer_certificates=True,
    ),
    ServiceSpec(
        "slam",
        pb.ServiceKind.SERVICE_KIND_SLAM,
        "swarmrec.services.slam:SlamService",
        "its robot's part of the distributed two-stage Gauss-Seidel: takes turns, exchanges separator "
        "estimates only",
        components=(SlamServiceSettings,),
        metrics=SlamMetrics,
        client_endpoints=("status", "estimate", "sent"),
        operator_endpoints=("load", "solve"),
        mailboxes=("inbox", "control"),
        watches=("slam",),  # team members that vanish mid-solve
    ),
    ServiceSpec(
        "gateway",
        pb.ServiceKind.SERVICE_KIND_GATEWAY,
        "swarmrec.services.gateway:Gateway",
        "the swarm for gRPC clients in any language: every method's queries, loop closures, tables, "
        "SLAM estimates and landmark rounds; live events",
        scope="swarm",
        # VprSettings: the centres it routes full-image queries by, the model it describes images with.
        components=(GatewaySettings, VprSettings),
        metrics=GatewayMetrics,
        identity="client.gateway.{swarm}",
    ),
):
    register(_entry)

#: The entry-point group other packages declare their service kinds in.
PLUGIN_GROUP = "swarmrec.services"


def load_plugins() -> list[str]:
    """Register the kinds installed packages declare (entry points of :data:`PLUGIN_GROUP`);
    returns the kinds added. A kind already registered under that spec is left as is."""
    added = []
    for ep in importlib.metadata.entry_points(group=PLUGIN_GROUP):
        entry = ep.load()
        if not isinstance(entry, ServiceSpec):
            raise ConfigError(f"entry point {ep.name} = {ep.value} ({PLUGIN_GROUP}) is not a ServiceSpec")
        if entry.kind != ep.name:
            raise ConfigError(f"entry point {ep.name} = {ep.value} names the kind {entry.kind!r}")
        if REGISTRY.get(entry.kind) == entry:
            continue
        register(entry)
        added.append(entry.kind)
    return added


load_plugins()

#: Each robot's services for each experiment, in start order.
WORKLOADS: Mapping[str, tuple[str, ...]] = {
    "places": ("index-shard", "verifier", "descriptor", "detector"),
    # Full-image place recognition (docs/vpr.md): the verifiers check what the owners match.
    "dvpr": ("verifier", "place-owner", "detector"),
    "landmarks": ("fusion", "detector"),
    "slam": ("slam",),
}


def spec(kind: str) -> ServiceSpec:
    """The entry of ``kind``; ConfigError listing the known kinds."""
    try:
        return REGISTRY[kind]
    except KeyError:
        raise ConfigError(f"unknown service {kind!r}; services: {', '.join(REGISTRY)}") from None


def kinds(scope: Scope | None = None) -> tuple[str, ...]:
    """The registered kinds (of one scope), in registration order."""
    return tuple(k for k, e in REGISTRY.items() if scope is None or e.scope == scope)


def kind_of_wire(value: int) -> str:
    """The kind name of a ``ServiceKind`` wire value ("unknown" for one this version lacks)."""
    for entry in REGISTRY.values():
        if entry.wire == value:
            return entry.kind
    return "unknown"


def all_components() -> tuple[type[Component], ...]:
    """Every component any kind reads, each once (the settings a TOML file may name)."""
    seen: dict[type[Component], None] = {}
    for entry in REGISTRY.values():
        for comp in entry.all_components:
            seen.setdefault(comp)
    return tuple(seen)


def hosted(kind: str, config: Config) -> Hosted:
    """A service of ``kind`` with ``config``, ready for :func:`~swarmrec.runtime.runner.run_services`."""
    entry = spec(kind)
    if entry.zenoh_mode is not None and config.bus.mode != entry.zenoh_mode:
        config = config.replace(config.bus.with_(mode=entry.zenoh_mode))
    if compiled.is_compiled(config, entry.compiled_for(config)):
        # Served by the compiled host: the Python class (and its imports) is never loaded.
        factory = _not_in_python(entry.kind)
    else:
        factory = cast(Callable[[ServiceContext], ServiceBase], entry.load())
    cn = entry.common_name(config.bus.swarm, config.bus.robot)
    return Hosted(config, entry.kind, entry.wire, factory, entry.metrics, cn)


def _not_in_python(kind: str) -> Callable[[ServiceContext], ServiceBase]:
    def refuse(_ctx: ServiceContext) -> ServiceBase:
        raise ConfigError(f"{kind} is served by the compiled host (data_plane compiled), not in Python")

    return refuse


def serve(
    kind: str,
    config: Config,
    *,
    stop: threading.Event | None = None,
    on_ready: Callable[[pb.MemberInfo], None] | None = None,
) -> int:
    """Run one service of ``kind`` with ``config`` until stopped; returns an exit code."""
    return serve_many([(kind, config)], stop=stop, on_ready=on_ready)


def serve_many(
    services: Sequence[tuple[str, Config]],
    *,
    stop: threading.Event | None = None,
    on_ready: Callable[[pb.MemberInfo], None] | None = None,
) -> int:
    """Run several services (kinds, robots) in this process over one session (``swarmrec host``).

    Services whose kind is served compiled (the ``data_plane`` setting,
    :mod:`swarmrec.services.compiled`) run in the compiled host: this process becomes it
    when they are all there is (not when a caller waits on ``stop`` or ``on_ready``: tests
    running services in threads), else it starts it as a child beside the Python services."""
    native: list[Hosted] = []
    python: list[Hosted] = []
    for kind, config in services:
        h = hosted(kind, config)
        (native if compiled.is_compiled(h.config, spec(kind).compiled_for(h.config)) else python).append(h)
    if not native:
        return run_services(python, stop=stop, on_ready=on_ready)
    shards = compiled.index_shards(native)
    if os.environ.get(compiled.COORDINATORS_ONLY) == "1":
        # Started by a compiled host for its index shards: their coordinators, nothing else.
        from swarmrec.services.shard_coordinator import run_coordinators

        return run_coordinators(shards, stop=stop)
    if not python and stop is None and on_ready is None:
        compiled.exec_host(native)
    child = compiled.CompiledHost(native)
    coordinators = None
    try:
        # Compiled shards' coordinators run here, and outlive the compiled host's stop: a
        # shard drains then, and its groups move only while a coordinator acts.
        if shards:
            from swarmrec.services.shard_coordinator import (  # only with compiled shards
                CHECK_TIMEOUT_S,
                ShardCoordinators,
            )

            coordinators = ShardCoordinators(shards)
            # Ready once the shards' placements are checked (a caller would meet them unconfirmed).
            coordinators.wait_checked(CHECK_TIMEOUT_S, stop)
        if not python:
            wait = stop or threading.Event()
            install_signals(wait)
            # Said once the coordinators run: the compiled host's own readiness line.
            print(json.dumps(child.ready_line), flush=True)
            wait.wait()
            return 0
        return run_services(python, stop=stop, on_ready=on_ready, also_ready=child.services)
    finally:
        child.stop(compiled.stop_timeout_s(native))
        if coordinators is not None:
            coordinators.stop()


def missing_components(kind: str, parts: Sequence[Component]) -> list[str]:
    """Components ``kind`` reads that ``parts`` lacks (their defaults will be used)."""
    have = {type(p) for p in parts}
    return [c.__name__ for c in spec(kind).all_components if c not in have]
