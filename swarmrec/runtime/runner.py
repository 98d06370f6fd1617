"""The one runner every service shares: session, lifecycle, plumbing, metrics, logs.

A service is a small class (:class:`ServiceBase`): the endpoints it answers
(:class:`Endpoint`, a request type, a reply type and a handler), the
subscriptions it listens to (:class:`Subscription`, a message type and a
handler), what it says about itself (``member_info``) and ``close``. The
runner owns everything else, in this order:

1. open the zenoh session (``with zenoh.open``: nothing is left to interpreter exit),
2. serve Prometheus metrics: the families every service has
   (:class:`~swarmrec.runtime.metrics.ServiceMetrics`) and the set its kind
   declares (:class:`~swarmrec.runtime.metrics.MetricSet`), beside the probe pages
   ``/ready`` (200 once every hosted service serves, 503 before and while stopping)
   and ``/healthz`` (200 while the process answers),
3. build the service; a stateful one asks for its record logs
   (:meth:`ServiceContext.open_log`) and replays them in its constructor,
4. declare one queryable per endpoint, one subscriber per subscription, plus
   ``info``; zenoh's callbacks only put the query or sample in a channel or a
   bounded queue, worker threads do the work,
5. declare the liveliness token last, then print the readiness line,
6. on SIGTERM/SIGINT: drop the token first, undeclare queryables and
   subscribers, let the workers finish, close the service and its logs, close
   the session.

Requests and subscribed messages go through the same checks: the encoding's
schema must be the declared type's, the payload must fit ``max_message_bytes``
and decode; bytes are counted by message type and scope. A handler returns its
reply (or nothing, for a subscription) or raises: the error reply's code is the
exception's own (:class:`~swarmrec.errors.RequestError` and
:class:`~swarmrec.errors.WireError` carry one); anything else is answered
``INTERNAL`` with the traceback in the log. Every refusal is counted in
``swarmrec_rejected_requests_total{endpoint, code}``. Bad input is answered and
counted, never fatal. A router is a service with no endpoints whose session
runs in router mode.
"""

from __future__ import annotations

import functools
import json
import logging
import os
import queue
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, TypeVar

import zenoh

# protobuf ships no type stubs and types-protobuf is not a dev dependency; with
# the stubs installed the ignore is unused, hence both codes.
from google.protobuf.message import Message  # type: ignore[import-untyped, unused-ignore]
from prometheus_client import CollectorRegistry, Gauge

import swarmrec
from swarmrec.errors import (
    ConfigError,
    ErrorCode,
    InvalidArgument,
    MessageTooLargeError,
    PermissionDenied,
    RequestError,
    Unavailable,
    WireError,
)
from swarmrec.runtime import keys
from swarmrec.runtime.metrics import MetricSet, MetricsServer, ServiceMetrics, scope_between
from swarmrec.runtime.rpc import Caller, LocalEndpoints, caller_robot, encoding_for, schema_of
from swarmrec.runtime.settings import (
    AUTO_QUEUE_ABOVE,
    SINGLE_RUNTIME_TX_QUEUE,
    SINGLE_THREAD_RUNTIME,
    BusSettings,
    Component,
    Config,
    SecuritySettings,
    StorageSettings,
)
from swarmrec.runtime.storage import RecordLog
from swarmrec.runtime.tls import apply_security, no_shared_memory
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import decode, encode, error_reply, schema_name

__all__ = [
    "Endpoint",
    "Hosted",
    "RequestContext",
    "ServiceBase",
    "ServiceContext",
    "Subscription",
    "choose_zenoh_runtime",
    "deepen_send_queue",
    "dispatch_by_queue",
    "install_signals",
    "on_single_runtime",
    "open_session",
    "run_service",
    "run_services",
    "service_logger",
    "session_bus",
    "session_identity",
    "zenoh_config",
    "zenoh_log_from_env",
]

C = TypeVar("C", bound=Component)
S = TypeVar("S", bound=MetricSet)
T = TypeVar("T")

#: Subscribed messages waiting for a worker; beyond it the zenoh callback drops (and
#: counts, code UNAVAILABLE) rather than block zenoh's receive thread.
SUBSCRIPTION_CAPACITY = 65536

#: Bytes of subscribed messages waiting for a subscription's workers, at most: a flood of
#: big messages (each under ``max_message_bytes``) is bounded by memory, not count alone.
SUBSCRIPTION_MAX_BYTES = 32 << 20

#: Requests waiting for an endpoint's workers (``dispatch`` queue); beyond it the zenoh
#: callback answers UNAVAILABLE at once (counted) rather than block zenoh's receive
#: thread. zenoh's own channel holds as many.
ENDPOINT_CAPACITY = 256


@dataclass(frozen=True)
class RequestContext:
    """What a handler knows about a request or message besides its content."""

    #: The sender's robot id (from the attachment, or for a caller-bound endpoint from the
    #: key: keys.CALLER_BOUND); None for a client outside the swarm.
    caller_robot: int | None
    key: str

    def require_own(self, robot: int, frame: int) -> None:
        """Refuses (PERMISSION_DENIED) a request that acts on another robot's frame than the
        caller's own: a robot stores and queries with its own frames only. The same words
        as the compiled shard's (``own_slice``)."""
        if robot != self.caller_robot:
            who = "outside the swarm" if self.caller_robot is None else f"robot {self.caller_robot}"
            raise PermissionDenied(
                f"a request from {who} carries robot {robot}'s frame {frame}: "
                "a robot stores and queries with its own frames only"
            )


@dataclass(frozen=True)
class Endpoint:
    """One request type a service answers, at ``<kind>/<robot>/<name>``.

    ``handler`` is the service class's own method, called as ``handler(service,
    request, context)``; it returns a ``reply`` message or raises.
    """

    name: str
    request: type[Message]
    reply: type[Message]
    handler: Callable[[Any, Any, RequestContext], Message]
    doc: str = ""


@dataclass(frozen=True)
class Subscription:
    """Messages a service takes without answering (puts to ``<kind>/<robot>/<name>``).

    ``handler(service, message, context)`` returns nothing or raises; ``workers``
    is 1 by default so messages are handled in the order they arrived.
    """

    name: str
    message: type[Message]
    handler: Callable[[Any, Any, RequestContext], None]
    doc: str = ""
    workers: int = 1
    capacity: int = SUBSCRIPTION_CAPACITY


class ServiceBase:
    """What a service supplies to the runner. Subclasses set ``ENDPOINTS`` (and
    ``SUBSCRIPTIONS``) after their handlers, take a :class:`ServiceContext` in
    ``__init__`` and override :meth:`member_info` and :meth:`close` as needed."""

    ENDPOINTS: ClassVar[Sequence[Endpoint]] = ()
    SUBSCRIPTIONS: ClassVar[Sequence[Subscription]] = ()

    def member_info(self) -> pb.MemberInfo:
        """What the service says of itself beyond kind, robot and version (its label
        range, what it stores); the runner fills in the rest."""
        return pb.MemberInfo()

    def announce(self) -> dict[str, Any]:
        """Fields added to the service's readiness line (the gateway's gRPC address)."""
        return {}

    def serving(self, ready: bool) -> None:
        """Called with True once the service serves (its liveliness token is declared) and
        with False first thing when it stops (a service with its own listener, the gRPC
        gateway, tells its clients)."""

    def close(self) -> None:
        """Release what the service holds; its record logs are closed by the runner."""


@dataclass
class ServiceContext:
    """What the runner hands a service when building it."""

    config: Config
    kind: str
    session: zenoh.Session
    metrics: ServiceMetrics
    caller: Caller
    stop: threading.Event
    log: logging.Logger
    kind_metrics: MetricSet | None = None
    #: The common name of the certificate the session presents (mutual TLS).
    identity: str = ""
    _logs: list[RecordLog] = field(default_factory=list)

    @property
    def bus(self) -> BusSettings:
        return self.config.bus

    def settings(self, component: type[C]) -> C:
        """This service's ``component`` settings."""
        return self.config.get(component)

    def metric_set(self, kind: type[S]) -> S:
        """The metric set the registry declares for this kind (a ``kind`` instance)."""
        if not isinstance(self.kind_metrics, kind):
            raise TypeError(f"{self.kind} declares {type(self.kind_metrics).__name__}, not {kind.__name__}")
        return self.kind_metrics

    def open_log(self, name: str) -> RecordLog:
        """The record log ``<data_dir>/<name>.log`` (memory only without a data_dir);
        replay ``records()`` to restore, ``append`` before answering. Closed by the runner."""
        storage = self.config.get(StorageSettings) if self.config.has(StorageSettings) else None
        path = storage.data_dir / f"{name}.log" if storage and storage.data_dir else None
        log = RecordLog(path, fsync=bool(storage and storage.fsync), log=self.log)
        self._logs.append(log)
        return log

    def publish(self, key: str, msg: Message) -> None:
        """Publish an event; it must arrive, so congestion blocks rather than drops."""
        payload = encode(msg)
        self.metrics.count_sent(schema_name(msg).rsplit(".", 1)[-1], "client", len(payload))
        self.session.put(
            key, payload, encoding=encoding_for(msg), congestion_control=zenoh.CongestionControl.BLOCK
        )

    def put(self, key: str, msg: Message, *, target_robot: int, payload: bytes | None = None) -> None:
        """Put ``msg`` on another service's subscription key, signed with this robot's id
        (the receiver counts its scope); blocks rather than drops under congestion.
        ``payload`` passes bytes already encoded (one broadcast, many targets)."""
        data = encode(msg) if payload is None else payload
        self.session.put(
            key,
            data,
            encoding=encoding_for(msg),
            congestion_control=zenoh.CongestionControl.BLOCK,
            attachment=str(self.bus.robot).encode(),
        )
        scope = scope_between(self.bus.robot, target_robot)
        self.metrics.count_sent(schema_name(msg).rsplit(".", 1)[-1], scope, len(data))


class _JsonFormatter(logging.Formatter):
    def __init__(self, kind: str, robot: int) -> None:
        super().__init__()
        self.kind, self.robot = kind, robot

    def format(self, record: logging.LogRecord) -> str:
        entry = {
            "ts": round(record.created, 3),
            "level": record.levelname,
            "service": self.kind,
            "robot": self.robot,
            "msg": record.getMessage(),
        }
        entry.update(getattr(record, "fields", {}))
        if record.exc_info:
            entry["exc"] = self.formatException(record.exc_info)
        return json.dumps(entry)


#: Warnings of one text a service logs at most this many times a window (``WARNING_WINDOW_S``):
#: a flood of refused input is counted in full (``swarmrec_rejected_requests_total``) and
#: must not also be a log line each (1,500 refusals were 0.45 MB of log).
WARNING_BURST = 20
WARNING_WINDOW_S = 10.0


class WarningBudget(logging.Filter):
    """Lets through at most ``burst`` WARNING records of one message text per ``window_s``;
    the first one let through after a window that dropped some says how many
    (``not_logged``). Errors and other levels always pass."""

    def __init__(self, burst: int = WARNING_BURST, window_s: float = WARNING_WINDOW_S) -> None:
        super().__init__()
        self.burst, self.window_s = burst, window_s
        self._lock = threading.Lock()
        #: message text -> (window start, let through in it, dropped since last let through)
        self._seen: dict[str, tuple[float, int, int]] = {}

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno != logging.WARNING:
            return True
        key, now = record.getMessage(), time.monotonic()
        with self._lock:
            start, passed, dropped = self._seen.get(key, (now, 0, 0))
            if now - start >= self.window_s:
                start, passed = now, 0
            if passed >= self.burst:
                self._seen[key] = (start, passed, dropped + 1)
                return False
            self._seen[key] = (start, passed + 1, 0)
            if len(self._seen) > 1024:  # texts are few; a runaway set of them is dropped
                self._seen = {key: self._seen[key]}
        if dropped:
            record.fields = {**getattr(record, "fields", {}), "not_logged": dropped}
        return True


def service_logger(kind: str, robot: int, level: str) -> logging.Logger:
    """JSON lines on stderr, one logger per (kind, robot); warnings of one text at a
    bounded rate (:class:`WarningBudget`)."""
    log = logging.getLogger(f"swarmrec.{kind}.{robot}")
    log.handlers.clear()
    handler = logging.StreamHandler(sys.stderr)
    handler.addFilter(WarningBudget())
    handler.setFormatter(_JsonFormatter(kind, robot))
    log.addHandler(handler)
    log.setLevel(level.upper())
    log.propagate = False
    return log


#: The longest a mesh router waits between two dials of a neighbour it lost (ms).
ROUTER_REDIAL_MAX_MS = 500


def zenoh_config(
    bus: BusSettings,
    security: SecuritySettings | None = None,
    *,
    identity: str = "",
    log: logging.Logger | None = None,
) -> zenoh.Config:
    """A zenoh config from the bus settings: explicit endpoints, no multicast scouting
    (containers have no multicast), clients retry until the router is up; secured as
    ``security`` says (mutual TLS as ``identity``, a router with its access control;
    :func:`~swarmrec.runtime.tls.apply_security`). ``security`` None leaves it bare (tests
    of the plumbing itself)."""
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(bus.mode))
    if bus.connect and bus.mode != "router":
        conf.insert_json5("connect/endpoints", json.dumps(list(bus.connect)))
        # Without this a client fails at start when the router is not up yet.
        conf.insert_json5("connect/timeout_ms", "-1")
    if bus.listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(bus.listen)))
    conf.insert_json5("scouting/multicast/enabled", "false")
    if bus.mode == "router" and bus.peers:
        # Its robot's radio neighbours (the mesh): dialled again soon after a link comes back,
        # so a healed link carries traffic within about a second (ROUTER_REDIAL_MAX_MS).
        conf.insert_json5("connect/endpoints", json.dumps(list(bus.peers)))
        conf.insert_json5("connect/timeout_ms", "-1")
        conf.insert_json5("connect/exit_on_failure", "false")
        conf.insert_json5(
            "connect/retry",
            json.dumps(
                {"period_init_ms": 100, "period_max_ms": ROUTER_REDIAL_MAX_MS, "period_increase_factor": 2}
            ),
        )
    if bus.mode == "router" and bus.stats_keys:
        # The bytes of each message type on each link (zenoh's per-key payload histograms).
        conf.insert_json5("stats/filters", json.dumps([{"key": k} for k in bus.stats_keys]))
    if bus.mode == "router":
        # zenoh holds a router's open half a second for peers it might scout; with multicast
        # off there are none to wait for (every client dials it), so its start is 0.5 s shorter.
        conf.insert_json5("scouting/delay", "0")
        # Its admin space says where it listens (a port 0 is the port the OS gave:
        # router_locators). Read-only; under mutual TLS the access control grants no one
        # else its keys (@/**), so only the router's own session reads it.
        conf.insert_json5("adminspace/enabled", "true")
        conf.insert_json5("adminspace/permissions", json.dumps({"read": True, "write": False}))
    no_shared_memory(conf)
    if security is not None:
        apply_security(conf, bus, security, identity=identity, log=log or logging.getLogger("swarmrec"))
    if on_single_runtime(bus):
        deepen_send_queue(conf)
    return conf


def on_single_runtime(bus: BusSettings) -> bool:
    """Whether a service process with ``bus`` runs zenoh on one thread (:func:`choose_zenoh_runtime`).
    Never a router: it forwards messages it cannot bound (any client's) into the queues of
    receivers it does not control, and on one thread a full queue waits on itself."""
    return bus.zenoh_runtime == "single" and bus.mode != "router"


def deepen_send_queue(conf: zenoh.Config) -> None:
    """The send queue a process on the single runtime needs (``SINGLE_RUNTIME_TX_QUEUE``):
    requests and replies travel at zenoh's ``data`` priority, the one deepened."""
    conf.insert_json5("transport/link/tx/queue/size/data", str(SINGLE_RUNTIME_TX_QUEUE))


def zenoh_log_from_env() -> None:
    """zenoh's own log (its Rust side: links, routing) on stdout when ``RUST_LOG`` asks for it,
    e.g. ``RUST_LOG=warn``; nothing otherwise (its lines are not the services' JSON)."""
    zenoh.try_init_log_from_env()  # type: ignore[no-untyped-call]  # untyped in zenoh's stub


def choose_zenoh_runtime(bus: BusSettings) -> None:
    """Give this process's zenoh the runtime ``bus.zenoh_runtime`` names. zenoh reads
    ``ZENOH_RUNTIME`` once, when its runtime starts: call this before the first session of
    a service process (``swarmrec serve``/``host``), never in a process that already has
    one (a test running services in threads keeps its own). A variable already set wins.
    A router keeps zenoh's pools (:func:`on_single_runtime`)."""
    if on_single_runtime(bus):
        os.environ.setdefault("ZENOH_RUNTIME", SINGLE_THREAD_RUNTIME)


def install_signals(stop: threading.Event) -> None:
    if threading.current_thread() is not threading.main_thread():
        return  # only the main thread may set handlers (tests run services in threads)
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())


def _code_of(e: Exception) -> ErrorCode:
    if isinstance(e, RequestError | WireError):
        return e.code
    return ErrorCode.INTERNAL


class _Dispatcher:
    """Serves one endpoint or subscription: check, decode, call the handler, count,
    never raise."""

    def __init__(self, ctx: ServiceContext, service: ServiceBase, name: str, expected: type[Message]) -> None:
        self.ctx, self.service, self.name = ctx, service, name
        self.expected_type = expected
        self.expected = schema_name(expected)
        self.latency = ctx.metrics.request_seconds.labels(name)
        self.cpu = ctx.metrics.request_cpu_seconds.labels(name)
        self.cost = ctx.metrics.cost(name)

    def observe(self, t0: float, c0: float) -> None:
        """Count one request served from wall time ``t0`` and thread CPU time ``c0``."""
        self.latency.observe(time.perf_counter() - t0)
        cpu = time.thread_time() - c0
        self.cpu.inc(cpu)
        self.cost.add(cpu)

    def parse(self, data: bytes, schema: str, scope: str) -> Message:
        """The payload as the declared type, counted as received; raises the error to answer."""
        ctx = self.ctx
        ctx.metrics.count_received(self.expected_type.__name__, scope, len(data))
        if schema and schema != self.expected:
            raise InvalidArgument(f"{self.name} takes {self.expected}, got {schema}")
        if len(data) > ctx.bus.max_message_bytes:
            raise MessageTooLargeError(len(data), ctx.bus.max_message_bytes)
        return decode(data, self.expected_type)

    def refuse(self, e: Exception, sender: int | None) -> ErrorCode:
        """Count and log a refusal; the code to answer with."""
        ctx = self.ctx
        code = _code_of(e)
        ctx.metrics.rejected.labels(self.name, code.wire_name).inc()
        fields = {"endpoint": self.name, "code": code.wire_name, "sender": sender}
        if code == ErrorCode.INTERNAL:
            ctx.log.error("handler failed", exc_info=e, extra={"fields": fields})
        else:
            ctx.log.warning("rejected request", extra={"fields": fields | {"reason": str(e)[:300]}})
        return code


class _EndpointDispatcher(_Dispatcher):
    """One endpoint's requests, handed to its workers one of two ways (``dispatch``).

    * channel: the workers block on the queryable's zenoh channel. zenoh's receive thread
      never takes the interpreter lock, but a worker blocked on the channel wakes every
      100 ms (to check for signals; measured with strace), and a process hosting 50
      robots has over 1,800 of them: their wake-ups alone took a core and the lock.
    * queue: zenoh's callback puts each query in a bounded queue and returns, and the
      workers block on the queue, asleep until a request comes. The callback takes the
      lock on zenoh's receive thread for every request, which in a small process costs
      about what its few idle workers' wake-ups do (docs/swarm.md has both measured).
    """

    def __init__(self, ctx: ServiceContext, service: ServiceBase, endpoint: Endpoint) -> None:
        super().__init__(ctx, service, endpoint.name, endpoint.request)
        self.endpoint = endpoint
        # Replies go out on the service's own key, not the query's (which may be a wildcard:
        # detector/*/step): a router's access control allows a robot to reply on its own keys only.
        self.key = keys.endpoint(ctx.bus.swarm, ctx.kind, ctx.bus.robot, endpoint.name)
        #: The caller is the robot the request's key names (keys.CALLER_BOUND).
        self.bound = keys.caller_bound(ctx.kind, endpoint.name)
        self.inbox: queue.Queue[zenoh.Query | None] = queue.Queue(maxsize=ENDPOINT_CAPACITY)

    def caller(self, key: str, claimed: int | None) -> int | None:
        """Who sent a request on ``key``: the attachment's robot, or for a caller-bound
        endpoint the key's, which the router checked against the sender's certificate (an
        attachment that says otherwise is refused)."""
        if not self.bound:
            return claimed
        named = keys.bound_caller(key)
        if named is None:
            raise PermissionDenied(
                f"{self.name} takes its caller from the key: send it to {self.key}/<robot>"
            )
        if claimed is not None and claimed != named:
            raise PermissionDenied(
                f"the request's key names robot {named} as its sender, its attachment {claimed}"
            )
        return named

    def on_query(self, query: zenoh.Query) -> None:
        # zenoh's thread: hand the query over and return; a full queue is answered now.
        try:
            self.inbox.put_nowait(query)
        except queue.Full:
            self._refuse_now(query)

    def _refuse_now(self, query: zenoh.Query) -> None:
        robot = caller_robot(query.attachment)
        try:
            msg, payload, _ok = self._error(
                Unavailable(f"{self.name} has {ENDPOINT_CAPACITY} requests waiting: retry later"), robot
            )
            query.reply_err(payload, encoding=encoding_for(msg))
        except zenoh.ZError:
            pass  # the caller is gone
        finally:
            query.drop()  # type: ignore[no-untyped-call]  # untyped in zenoh's stub

    def work(self) -> None:
        _work(self.inbox, self.serve)

    def work_channel(self, queryable: zenoh.Queryable[Any]) -> None:
        # Iteration ends when the queryable is undeclared (its channel closes).
        for query in queryable.handler:
            self.serve(query)

    def answer(self, data: bytes, schema: str, robot: int | None, key: str) -> tuple[Message, bytes, bool]:
        """The reply to one request, or the ErrorReply to answer instead, encoded: (message,
        payload, True for a reply). Never raises: every refusal is counted and logged."""
        scope = scope_between(self.ctx.bus.robot, robot)
        try:
            request = self.parse(data, schema, scope)
            reply = self.endpoint.handler(self.service, request, RequestContext(robot, key))
            return reply, encode(reply), True
        except Exception as e:
            return self._error(e, robot)

    def _error(self, e: Exception, robot: int | None) -> tuple[Message, bytes, bool]:
        """The ErrorReply for ``e`` (counted and logged), as :meth:`answer` returns it."""
        code = self.refuse(e, robot)
        message = e.message if isinstance(e, RequestError) else str(e)
        if code == ErrorCode.INTERNAL and not isinstance(e, RequestError):
            message = f"{type(e).__name__}: {e}"
        err = error_reply(code, message)
        return err, encode(err), False

    def serve(self, query: zenoh.Query) -> None:
        t0, c0 = time.perf_counter(), time.thread_time()
        robot = caller_robot(query.attachment)
        try:
            try:
                data = query.payload.to_bytes() if query.payload is not None else b""
                schema, key = schema_of(query.encoding), str(query.key_expr)
                robot = self.caller(key, robot)
            except Exception as e:  # a query that cannot be read is answered too, never fatal
                msg, payload, ok = self._error(e, robot)
            else:
                msg, payload, ok = self.answer(data, schema, robot, key)
            try:
                if ok:
                    # A caller-bound request is answered on its own key (the caller's robot
                    # in it), which the service's certificate may reply on (`<kind>/<robot>/**`).
                    reply_key = keys.request_key(self.key, robot) if self.bound else self.key
                    query.reply(reply_key, payload, encoding=encoding_for(msg))
                else:
                    query.reply_err(payload, encoding=encoding_for(msg))
            except zenoh.ZError:
                return  # the caller is gone; nothing left to tell
            self.ctx.metrics.count_sent(
                type(msg).__name__, scope_between(self.ctx.bus.robot, robot), len(payload)
            )
        finally:
            query.drop()  # type: ignore[no-untyped-call]  # untyped in zenoh's stub  # finish the query so the caller does not wait for its timeout
            self.observe(t0, c0)

    def serve_local(self, data: bytes, schema: str, robot: int | None, key: str) -> tuple[bytes, str, bool]:
        """A call from a service of the same robot in this process (:class:`LocalEndpoints`)."""
        t0, c0 = time.perf_counter(), time.thread_time()
        try:
            msg, payload, ok = self.answer(data, schema, robot, key)
            self.ctx.metrics.count_sent(
                type(msg).__name__, scope_between(self.ctx.bus.robot, robot), len(payload)
            )
            return payload, schema_name(msg), ok
        finally:
            self.observe(t0, c0)


def _work(inbox: queue.Queue[T | None], handle: Callable[[T], None]) -> None:
    """A worker: handle each item of ``inbox`` until the None that :func:`_close_inbox` puts."""
    while (item := inbox.get()) is not None:
        handle(item)


def _close_inbox(inbox: queue.Queue[Any], threads: int) -> None:
    """After its queryable or subscriber is undeclared: the workers handle what is queued,
    then stop. A full queue means a stuck worker; it is a daemon thread and ends with the
    process."""
    for _ in range(threads):
        try:
            inbox.put(None, timeout=5.0)
        except queue.Full:
            return


@dataclass(frozen=True)
class _Sample:
    """What a subscription callback hands its worker: bytes and headers, nothing parsed."""

    data: bytes
    schema: str
    sender: int | None
    key: str


class _SubscriptionDispatcher(_Dispatcher):
    def __init__(self, ctx: ServiceContext, service: ServiceBase, sub: Subscription) -> None:
        super().__init__(ctx, service, sub.name, sub.message)
        self.sub = sub
        self.inbox: queue.Queue[_Sample | None] = queue.Queue(maxsize=sub.capacity)
        self.queued_bytes = 0
        self.bytes_lock = threading.Lock()

    def on_sample(self, sample: zenoh.Sample) -> None:
        # zenoh's thread: copy the bytes out and return; the worker does the rest. A message
        # over the size limit is refused here, before it is copied or queued: refused input
        # must not hold memory (it is counted, TOO_LARGE, and not logged one line each).
        size = len(sample.payload)
        if size > self.ctx.bus.max_message_bytes:
            self.ctx.metrics.rejected.labels(self.name, ErrorCode.TOO_LARGE.wire_name).inc()
            return
        with self.bytes_lock:
            room = self.queued_bytes + size <= SUBSCRIPTION_MAX_BYTES
            if room:
                self.queued_bytes += size
        if not room:
            self._dropped()
            return
        item = _Sample(
            sample.payload.to_bytes(),
            schema_of(sample.encoding),
            caller_robot(sample.attachment),
            str(sample.key_expr),
        )
        try:
            self.inbox.put_nowait(item)
        except queue.Full:
            with self.bytes_lock:
                self.queued_bytes -= size
            self._dropped()

    def _dropped(self) -> None:
        self.ctx.metrics.rejected.labels(self.name, ErrorCode.UNAVAILABLE.wire_name).inc()
        self.ctx.log.warning(
            "subscription queue full, message dropped", extra={"fields": {"endpoint": self.name}}
        )

    def work(self) -> None:
        _work(self.inbox, self.handle)

    def handle(self, item: _Sample) -> None:
        with self.bytes_lock:
            self.queued_bytes -= len(item.data)
        t0, c0 = time.perf_counter(), time.thread_time()
        try:
            msg = self.parse(item.data, item.schema, scope_between(self.ctx.bus.robot, item.sender))
            self.sub.handler(self.service, msg, RequestContext(item.sender, item.key))
        except Exception as e:  # one bad message must not end the worker
            self.refuse(e, item.sender)
        finally:
            self.observe(t0, c0)


@dataclass(frozen=True)
class Hosted:
    """One service a process runs: its configuration and its registry entry's parts."""

    config: Config
    kind: str
    wire_kind: int
    factory: Callable[[ServiceContext], ServiceBase]
    metric_set: type[MetricSet] | None = None
    #: The common name of the service's own certificate when its settings name none.
    identity: str = ""

    @property
    def name(self) -> str:
        return f"{self.kind}-{self.config.bus.robot}"

    @property
    def security(self) -> SecuritySettings:
        c = self.config
        return c.get(SecuritySettings) if c.has(SecuritySettings) else SecuritySettings()


def session_bus(hosted: Sequence[Hosted]) -> BusSettings:
    """The bus settings the shared session is opened with; every hosted service must agree
    on what the session is (swarm, mode, endpoints)."""
    first = hosted[0].config.bus
    for h in hosted[1:]:
        bus = h.config.bus
        same = (bus.swarm, bus.mode, bus.connect, bus.listen) == (
            first.swarm,
            first.mode,
            first.connect,
            first.listen,
        )
        if not same or h.security != hosted[0].security:
            raise ConfigError(
                f"{h.name} is on another session than {hosted[0].name}: one process, one session"
            )
    return first


def session_identity(hosted: Sequence[Hosted]) -> str:
    """The common name the shared session presents: its settings' or the one service's own.
    Several services share one certificate only when it is named (the access control
    grants each certificate one service's keys)."""
    security = hosted[0].security
    if security.security == "insecure" or security.identity or len(hosted) == 1:
        return hosted[0].identity
    raise ConfigError(
        f"{len(hosted)} services share one mutual-TLS session: name its certificate (--identity) "
        "or run them in processes of their own (the access control grants a certificate one "
        "service's keys)"
    )


@dataclass
class _Running:
    """What the host set up for one service, to be torn down in order."""

    hosted: Hosted
    ctx: ServiceContext
    service: ServiceBase | None = None
    declared: list[Any] = field(default_factory=list)
    threads: list[threading.Thread] = field(default_factory=list)
    #: The queues its endpoints' and subscriptions' workers take from, and how many workers each.
    inboxes: list[tuple[queue.Queue[Any], int]] = field(default_factory=list)
    token: Any = None
    #: Its endpoints' keys in the process's LocalEndpoints.
    local_keys: list[str] = field(default_factory=list)


def dispatch_by_queue(dispatch: str, services: int) -> bool:
    """Whether a process hosting ``services`` services feeds its endpoints' workers from
    queues (``dispatch`` auto, channel or queue: :class:`_EndpointDispatcher`)."""
    return dispatch == "queue" or (dispatch == "auto" and services > AUTO_QUEUE_ABOVE)


def _start(r: _Running, queues: bool) -> None:
    """Build the service and declare its endpoints (their workers fed by ``queues`` or by
    zenoh's channels), subscriptions, info and token."""
    ctx, h = r.ctx, r.hosted
    bus, session = ctx.bus, ctx.session
    r.service = service = h.factory(ctx)
    for ep in service.ENDPOINTS:
        key = keys.endpoint(bus.swarm, h.kind, bus.robot, ep.name)
        endpoint = _EndpointDispatcher(ctx, service, ep)
        # A caller-bound endpoint is asked at <key>/<caller>; a request at <key> alone is
        # answered too, with the refusal that says so.
        declared = f"{key}/**" if endpoint.bound else key
        if queues:
            work: Callable[[], None] = endpoint.work
            r.inboxes.append((endpoint.inbox, bus.workers))
            r.declared.append(session.declare_queryable(declared, endpoint.on_query))
        else:
            q = session.declare_queryable(declared)
            r.declared.append(q)
            work = functools.partial(endpoint.work_channel, q)
        for i in range(bus.workers):
            t = threading.Thread(target=work, name=f"{h.name}-{ep.name}-{i}", daemon=True)
            t.start()
            r.threads.append(t)
        if ctx.caller.local is not None:
            ctx.caller.local.add(key, bus.robot, endpoint.serve_local)
            r.local_keys.append(key)
    for sub in service.SUBSCRIPTIONS:
        dispatcher = _SubscriptionDispatcher(ctx, service, sub)
        for i in range(sub.workers):
            t = threading.Thread(target=dispatcher.work, name=f"{h.name}-{sub.name}-{i}", daemon=True)
            t.start()
            r.threads.append(t)
        r.inboxes.append((dispatcher.inbox, sub.workers))
        key = keys.endpoint(bus.swarm, h.kind, bus.robot, sub.name)
        r.declared.append(session.declare_subscriber(key, dispatcher.on_sample))
    r.declared.append(_declare_info(ctx, service, h.wire_kind, r))
    # Last: once the token is up, peers may route to this service.
    r.token = session.liveliness().declare_token(keys.alive(bus.swarm, h.kind, bus.robot))
    ctx.metrics.ready.set(1)
    service.serving(True)


def _tell_stopping(running: Sequence[_Running]) -> None:
    """``serving(False)`` for every service, all at once (each in a thread: one may wait,
    an index shard handing its groups on), while they all still serve."""
    threads = []
    for r in running:
        r.ctx.metrics.ready.set(0)
        if r.service is not None:
            t = threading.Thread(target=r.service.serving, args=(False,), name=f"stopping-{r.hosted.name}")
            t.start()
            threads.append(t)
    for t in threads:
        t.join()


def _stop(r: _Running) -> None:
    """Token first, then queryables and subscribers, workers, the service, its logs (the
    service was told it stops before: :func:`_tell_stopping`)."""
    if r.token is not None:
        r.token.undeclare()
    local = r.ctx.caller.local
    if local is not None:
        for key in r.local_keys:
            local.remove(key)
    for d in r.declared:
        d.undeclare()
    for inbox, workers in r.inboxes:
        _close_inbox(inbox, workers)
    for t in r.threads:
        t.join(timeout=5.0)
    if r.service is not None:
        r.service.close()
    for record_log in r.ctx._logs:
        record_log.close()


def run_services(
    hosted: Sequence[Hosted],
    *,
    stop: threading.Event | None = None,
    on_ready: Callable[[pb.MemberInfo], None] | None = None,
    also_ready: Sequence[dict[str, Any]] = (),
) -> int:
    """Run several services in this process over one zenoh session until ``stop`` is set
    (or SIGTERM/SIGINT); returns an exit code.

    ``also_ready``: services another process serves for this one (the compiled host's,
    :mod:`swarmrec.services.compiled`), listed in the readiness line beside its own.

    A robot's services in one process call each other directly (the caller's thread runs
    the endpoint's dispatcher: :class:`~swarmrec.runtime.rpc.LocalEndpoints`); many robots
    can share a process (a simulation), and talk to each other through the router. Each service keeps its
    own endpoints, worker threads, logs, metrics registry and liveliness token, so peers
    cannot tell it from a service alone in its process. Metrics: one HTTP endpoint for
    the process (:class:`~swarmrec.runtime.metrics.MetricsServer`).
    """
    if not hosted:
        raise ConfigError("a host runs at least one service")
    bus = session_bus(hosted)
    stop = stop or threading.Event()
    install_signals(stop)
    single = len(hosted) == 1
    queues = dispatch_by_queue(bus.dispatch, len(hosted))
    host_log = service_logger(hosted[0].kind if single else "host", bus.robot, bus.log_level)
    server = MetricsServer(bus.metrics_host, bus.metrics_port) if bus.metrics_port >= 0 else None
    host_ready = None
    if server is not None:
        server.start()
        if not single:
            host_registry = CollectorRegistry(auto_describe=True)
            host_ready = Gauge(
                "swarmrec_service_ready",
                "1 while every service of this process serves",
                registry=host_registry,
            )
            host_ready.set(0)
            server.add("/metrics", host_registry)
    running: list[_Running] = []
    # Calls between services of one robot in this process skip zenoh (rpc.LocalEndpoints).
    local = LocalEndpoints()
    conf = zenoh_config(bus, hosted[0].security, identity=session_identity(hosted), log=host_log)
    # Said before the wait for the router, which may be long: where it waits (and, to a
    # supervisor, that SIGTERM is handled from here on).
    host_log.info("connecting to the swarm", extra={"fields": {"connect": list(bus.connect)}})
    opened = open_session(conf, stop)
    if opened is None:
        # Stopped while the router was out of reach: nothing was declared yet.
        if server is not None:
            server.close()
        host_log.info("stopped before reaching the swarm")
        return 0
    with opened as session:
        try:
            for h in hosted:
                b = h.config.bus
                metrics = ServiceMetrics.create(h.kind, b.robot, b.swarm)
                if server is not None:
                    metrics.url = server.add(
                        "/metrics" if single else f"/metrics/{h.kind}/{b.robot}", metrics.registry
                    )
                caller = Caller(session, b.robot, b.request_timeout_s, metrics, b.max_message_bytes, local)
                own = h.metric_set.create(metrics.registry) if h.metric_set is not None else None
                log = host_log if single else service_logger(h.kind, b.robot, b.log_level)
                cn = h.security.identity or h.identity
                ctx = ServiceContext(h.config, h.kind, session, metrics, caller, stop, log, own, cn)
                r = _Running(h, ctx)
                running.append(r)
                _start(r, queues)
            if host_ready is not None:
                host_ready.set(1)
            if server is not None:
                server.set_ready(True)
            services = [
                {"service": r.hosted.kind, "robot": r.ctx.bus.robot, "metrics_url": r.ctx.metrics.url}
                | (r.service.announce() if r.service is not None else {})
                for r in running
            ]
            services += list(also_ready)
            ready: dict[str, Any] = (
                {"event": "ready", **services[0]}
                if len(services) == 1
                else {"event": "ready", "services": services}
            )
            ready["dispatch"] = "queue" if queues else "channel"
            listen = router_locators(session) if bus.mode == "router" else []
            listen = listen or list(bus.listen)
            if listen:
                ready["listen"] = listen
            host_log.info("ready", extra={"fields": {"services": services, "listen": listen}})
            print(json.dumps(ready), flush=True)
            if on_ready is not None:
                for r in running:
                    assert r.service is not None
                    on_ready(_member_info(r.service, r.ctx, r.hosted.wire_kind))
            stop.wait()
            host_log.info("stopping")
        finally:
            if server is not None:
                server.set_ready(False)  # first: a probe must not route to a stopping process
            if host_ready is not None:
                host_ready.set(0)
            # Every hosted service is told it stops at once (an index shard drains then, and
            # must see its neighbours in this process stopping too), then each is taken down.
            _tell_stopping(running)
            for r in reversed(running):
                _stop(r)
            if server is not None:
                server.close()
    host_log.info("stopped")
    return 0


def router_locators(session: zenoh.Session, timeout_s: float = 2.0) -> list[str]:
    """Where a router session listens, as zenoh bound it (a port 0 replaced by the port the
    OS gave), from its own admin space; [] when it does not say."""
    key = f"@/{session.info.zid()}/router"
    try:
        for reply in session.get(key, timeout=timeout_s):
            if reply.ok is not None:
                found = json.loads(reply.ok.payload.to_string()).get("locators", [])
                return [str(x) for x in found if isinstance(x, str)]
    except (zenoh.ZError, ValueError):
        pass
    return []


def open_session(conf: zenoh.Config, stop: threading.Event) -> zenoh.Session | None:
    """The zenoh session, or None when ``stop`` is set first. A client waits for its router
    as long as it takes (``connect/timeout_ms`` -1) and ``zenoh.open`` does not return until
    then, so it runs on a thread of its own: a service still waiting can be stopped (SIGTERM
    sets ``stop``; the waiting thread is a daemon and ends with the process)."""
    box: list[zenoh.Session | BaseException] = []
    done = threading.Event()

    def opening() -> None:
        try:
            box.append(zenoh.open(conf))
        except BaseException as e:  # handed to the waiting thread, raised there
            box.append(e)
        done.set()

    threading.Thread(target=opening, name="zenoh-open", daemon=True).start()
    while not done.wait(0.1):
        if stop.is_set():
            return None
    if isinstance(box[0], BaseException):
        raise box[0]
    return box[0]


def run_service(
    config: Config,
    *,
    kind: str,
    wire_kind: int,
    factory: Callable[[ServiceContext], ServiceBase],
    metric_set: type[MetricSet] | None = None,
    stop: threading.Event | None = None,
    on_ready: Callable[[pb.MemberInfo], None] | None = None,
) -> int:
    """Run one service until ``stop`` is set (or SIGTERM/SIGINT); returns an exit code.

    ``kind``, ``wire_kind``, ``factory`` and ``metric_set`` come from the service's
    registry entry (:func:`swarmrec.services.registry.serve` passes them)."""
    return run_services([Hosted(config, kind, wire_kind, factory, metric_set)], stop=stop, on_ready=on_ready)


def _declare_info(
    ctx: ServiceContext, service: ServiceBase, wire_kind: int, r: _Running
) -> zenoh.Queryable[Any]:
    bus = ctx.bus
    key = keys.endpoint(bus.swarm, ctx.kind, bus.robot, "info")
    inbox: queue.Queue[zenoh.Query | None] = queue.Queue(maxsize=ENDPOINT_CAPACITY)

    def answer(query: zenoh.Query) -> None:
        info = _member_info(service, ctx, wire_kind)
        try:
            query.reply(key, encode(info), encoding=encoding_for(info))
        finally:
            query.drop()  # type: ignore[no-untyped-call]  # untyped in zenoh's stub

    def enqueue(query: zenoh.Query) -> None:
        try:
            inbox.put_nowait(query)
        except queue.Full:
            query.drop()  # type: ignore[no-untyped-call]  # info is asked once per member: a flood gets nothing

    t = threading.Thread(target=_work, args=(inbox, answer), name="info", daemon=True)
    t.start()
    r.threads.append(t)
    r.inboxes.append((inbox, 1))
    return ctx.session.declare_queryable(key, enqueue)


def _member_info(service: ServiceBase, ctx: ServiceContext, wire_kind: int) -> pb.MemberInfo:
    info = service.member_info()
    info.kind = wire_kind  # type: ignore[assignment]  # an enum value
    info.robot_id = ctx.bus.robot
    info.version = swarmrec.__version__
    info.metrics_url = ctx.metrics.url
    info.swarm = ctx.bus.swarm
    return info
