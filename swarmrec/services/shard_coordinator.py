"""The elastic index's coordinator beside a compiled index shard.

A compiled shard (``swarmrec-dataplane``, docs/dataplane.md) serves every per-message
endpoint; what is not per-message, deciding placements, stays in Python with the one
implementation of the placement rules (:mod:`swarmrec.core.placement`): the
:class:`~swarmrec.services.coordinator.Coordinator` every shard runs, here driving its
shard through the shard's own endpoints instead of in-process calls:

* its view of the shard (placement, confirmed, groups held) is the shard's
  ``placement`` answer, read again at every tick (the placement itself only when the
  shard follows another one than the view's);
* following a placement is an ``adopt`` to the shard, which accepts it from its own
  robot as from the lowest live shard (``publish`` set when the coordinator computed
  it, so the shard counts it as published).

The coordinators of one process's compiled shards share a zenoh session of their own,
with the shards' certificate (:class:`ShardCoordinators`); the process that starts the
compiled host runs them (:func:`swarmrec.services.registry.serve_many`) and stops the
host first, so a draining shard still has its coordinator while it hands its groups on.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Sequence

import zenoh

from swarmrec.core.placement import Placement, ring
from swarmrec.errors import CallError, ErrorCode, RemoteError
from swarmrec.runtime import ServiceContext, keys
from swarmrec.runtime.metrics import ServiceMetrics
from swarmrec.runtime.rpc import Caller
from swarmrec.runtime.runner import (
    Hosted,
    install_signals,
    open_session,
    service_logger,
    session_bus,
    session_identity,
    zenoh_config,
)
from swarmrec.services.coordinator import Coordinator, ShardSettings
from swarmrec.services.metrics import ShardMetrics
from swarmrec.wire import messages as pb
from swarmrec.wire.placement import placement_from_proto, placement_to_proto

__all__ = ["CompiledShard", "CompiledShardCoordinator", "ShardCoordinators", "run_coordinators"]


class CompiledShard(ShardSettings):
    """The coordinator's :class:`~swarmrec.services.coordinator.Shard`, over a compiled
    shard's ``placement`` and ``adopt`` endpoints."""

    def __init__(self, ctx: ServiceContext) -> None:
        self.read_settings(ctx)
        # What the shard starts from with nothing on disk, until it has answered.
        self.placement: Placement = ring(
            self.groups, range(self.bus.n_robots), replicas=self.index_settings.replicas
        )
        self.confirmed = False
        self.ready: set[int] = set()

    def _key(self, endpoint: str) -> str:
        return keys.endpoint(self.bus.swarm, "index-shard", self.shard, endpoint)

    def _take(self, state: pb.ShardState) -> None:
        if state.HasField("placement"):
            placement = placement_from_proto(state.placement, self.places.n_labels)
            if placement.groups == self.groups:
                self.placement = placement
        self.confirmed = state.confirmed
        self.ready = set(state.ready_groups)

    def state(self, known_version: int | None = None) -> pb.ShardState:
        """The shard's state (its placement left out when it is ``known_version``); the
        view kept here follows it."""
        st = self.ctx.caller.call(
            self._key("placement"),
            pb.PlacementRequest(known_version=known_version),
            pb.ShardState,
            target_robot=self.shard,
            endpoint="placement",
        )
        self._take(st)
        return st

    def _adopt(self, placement: Placement, *, publish: bool, reason: int = 0) -> bool:
        try:
            st = self.ctx.caller.call(
                self._key("adopt"),
                pb.AdoptRequest(
                    placement=placement_to_proto(placement),
                    publish=publish,
                    reason=pb.PlacementReason.ValueType(reason),
                ),
                pb.ShardState,
                target_robot=self.shard,
                endpoint="adopt",
            )
        except RemoteError as e:
            if e.code == ErrorCode.FAILED_PRECONDITION:
                return False  # older than the one the shard follows
            raise
        self.placement = placement
        self._take(st)
        return True

    def follow(self, placement: Placement, *, confirm: bool = True) -> bool:
        """The shard follows ``placement`` (a compiled shard always confirms what it adopts)."""
        del confirm
        return self._adopt(placement, publish=False)

    def follow_own(self, placement: Placement, reason: int) -> None:
        self._adopt(placement, publish=True, reason=reason)


class CompiledShardCoordinator(Coordinator):
    """The coordinator loop for a :class:`CompiledShard`: its view is refreshed first.

    ``checked`` is set once the start-up check is done (the shard confirmed, or the swarm
    found further along and the coordinator's adoption awaited): the process running the
    shard declares it ready then, so that no caller meets a shard still unconfirmed."""

    def __init__(self, shard: CompiledShard) -> None:
        super().__init__(shard)
        self.compiled = shard
        self.checked = threading.Event()
        self._viewed = -float("inf")

    def confirm_on_start(self) -> None:
        try:
            while not self._stop.is_set():
                try:
                    # The shard may have loaded a newer placement from its disk than assumed.
                    self.compiled.state()
                    super().confirm_on_start()
                    return
                except CallError as e:  # the shard not answering yet, or a call lost: again
                    self.log.info(f"confirming the compiled shard's placement: {e}")
                    self._stop.wait(self.settings.placement_tick_s)
        finally:
            self.checked.set()

    def tick(self) -> None:
        # The view is what the coordinator acts on: fresh at every tick where it acts or may
        # take over (its shard the lowest alive); otherwise it serves only to tell who is
        # present, and a hundred coordinators each asking their shard every second is a
        # hundred requests a second for nothing.
        now = time.monotonic()
        if (
            self.acting
            or self.lowest_live() == self.shard.shard
            or now - self._viewed >= self.settings.state_interval_s
        ):
            try:
                # The placement only when it changed: a hundred shards' placements a second
                # were most of a large swarm's index traffic.
                known = self.compiled.placement.version if self.compiled.confirmed else None
                self.compiled.state(known)
            except CallError as e:
                self.log.info(f"the compiled shard did not answer: {e}")
                return
            self._viewed = now
        super().tick()


class ShardCoordinators:
    """The coordinators of a process's compiled index shards, on one session of their own
    with the shards' certificate. Started once the compiled host is ready."""

    def __init__(self, hosted: Sequence[Hosted]) -> None:
        bus = session_bus(hosted)
        self.log = service_logger("index-coordinator", bus.robot, bus.log_level)
        conf = zenoh_config(bus, hosted[0].security, identity=session_identity(hosted), log=self.log)
        self.stop_event = threading.Event()
        self.session: zenoh.Session | None = open_session(conf, self.stop_event)
        self.coordinators: list[CompiledShardCoordinator] = []
        if self.session is None:
            return
        for h in hosted:
            b = h.config.bus
            metrics = ServiceMetrics.create(h.kind, b.robot, b.swarm)
            caller = Caller(self.session, b.robot, b.request_timeout_s, metrics, b.max_message_bytes)
            log = service_logger("index-coordinator", b.robot, b.log_level)
            own = ShardMetrics.create(metrics.registry)
            cn = h.security.identity or h.identity
            stop = self.stop_event
            ctx = ServiceContext(h.config, h.kind, self.session, metrics, caller, stop, log, own, cn)
            coordinator = CompiledShardCoordinator(CompiledShard(ctx))
            coordinator.start()
            self.coordinators.append(coordinator)

    def wait_checked(self, timeout_s: float, stop: threading.Event | None = None) -> bool:
        """Wait until every coordinator has done its start-up check; False on timeout or stop."""
        deadline = time.monotonic() + timeout_s
        for c in self.coordinators:
            while not c.checked.wait(0.05):
                if time.monotonic() > deadline or (stop is not None and stop.is_set()):
                    self.log.warning("shard coordinators still checking their placements: ready anyway")
                    return False
        return True

    def stop(self) -> None:
        self.stop_event.set()
        for c in self.coordinators:
            c.stop()
        if self.session is not None:
            self.session.close()  # type: ignore[no-untyped-call]  # untyped in zenoh's stub
            self.session = None


#: How long a process waits for its shards' coordinators to check their placements
#: before it declares the shards ready anyway.
CHECK_TIMEOUT_S = 30.0


def run_coordinators(hosted: Sequence[Hosted], *, stop: threading.Event | None = None) -> int:
    """The coordinators of ``hosted`` (compiled index shards served by another process, the
    compiled host that started this one) until SIGTERM/SIGINT or ``stop``; an exit code.

    Says on stdout, one JSON line, once every coordinator has done its start-up check
    (``{"event": "checked", "robots": [...]}``): the compiled host declares its shards
    ready then."""
    if not hosted:
        return 0
    stop = stop or threading.Event()
    install_signals(stop)
    coordinators = ShardCoordinators(hosted)
    try:
        if coordinators.wait_checked(CHECK_TIMEOUT_S, stop):
            robots = [c.shard.shard for c in coordinators.coordinators]
            print(json.dumps({"event": "checked", "robots": robots}), flush=True)
        stop.wait()
    finally:
        coordinators.stop()
    return 0
