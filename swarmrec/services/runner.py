"""The one runner every service shares: session, lifecycle, metrics, logs.

A service is a small object (see :class:`Service`): its endpoints, each a
request type and a handler, and its membership info. The runner owns the
rest, in this order:

1. open the zenoh session (``with zenoh.open``: nothing is left to interpreter exit),
2. serve Prometheus metrics, build the service (its ``setup``: load stored data),
3. declare one queryable per endpoint plus ``info``; zenoh's callback only
   puts the query in a channel, ``workers`` threads per endpoint do the work,
4. declare the liveliness token last, then print the readiness line,
5. on SIGTERM/SIGINT: drop the token first, undeclare the queryables, let the
   workers finish, close the service, close the session.

A handler returns its reply message or raises :class:`RequestError`; any
other exception becomes an ``ERROR_CODE_INTERNAL`` reply with the traceback in
the log. Bad input is answered and counted, never fatal.
"""

from __future__ import annotations

import json
import logging
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, cast

import zenoh

# protobuf ships no type stubs and types-protobuf is not a dev dependency; with
# the stubs installed the ignore is unused, hence both codes.
from google.protobuf.message import Message  # type: ignore[import-untyped, unused-ignore]

import swarmrec
from swarmrec.errors import SwarmrecError, WireError
from swarmrec.services import keys
from swarmrec.services.config import ServiceSettings
from swarmrec.services.metrics import ServiceMetrics, scope_between
from swarmrec.services.rpc import Caller, caller_robot, encoding_for, schema_of
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import decode, encode, error_reply, schema_name

__all__ = [
    "Endpoint",
    "RequestContext",
    "RequestError",
    "Service",
    "ServiceContext",
    "install_signals",
    "run_service",
    "service_logger",
    "zenoh_config",
]

KIND_ENUM = {
    "detector": pb.ServiceKind.SERVICE_KIND_DETECTOR,
    "descriptor": pb.ServiceKind.SERVICE_KIND_DESCRIPTOR,
    "index-shard": pb.ServiceKind.SERVICE_KIND_INDEX_SHARD,
    "verifier": pb.ServiceKind.SERVICE_KIND_VERIFIER,
    "fusion": pb.ServiceKind.SERVICE_KIND_FUSION,
}


class RequestError(SwarmrecError):
    """Raised by a handler to answer with an ErrorReply of ``code``."""

    def __init__(self, code: int, message: str) -> None:
        super().__init__(message)
        self.code = code
        self.message = message


@dataclass(frozen=True)
class RequestContext:
    """What a handler knows about the request besides its message."""

    caller_robot: int | None
    key: str


@dataclass(frozen=True)
class Endpoint:
    """One request type a service answers, at ``<kind>/<robot>/<name>``."""

    name: str
    request: type[Message]
    handler: Callable[[Any, RequestContext], Message]


class Service(Protocol):
    """What a service supplies to the runner."""

    def endpoints(self) -> Sequence[Endpoint]: ...

    def member_info(self) -> pb.MemberInfo: ...

    def close(self) -> None: ...


@dataclass
class ServiceContext:
    """What the runner hands a service when building it."""

    settings: ServiceSettings
    kind: str
    session: zenoh.Session
    metrics: ServiceMetrics
    caller: Caller
    stop: threading.Event
    log: logging.Logger

    def publish(self, key: str, msg: Message) -> None:
        """Publish an event; it must arrive, so congestion blocks rather than drops."""
        payload = encode(msg)
        self.metrics.count_sent(schema_name(msg).rsplit(".", 1)[-1], "client", len(payload))
        self.session.put(
            key, payload, encoding=encoding_for(msg), congestion_control=zenoh.CongestionControl.BLOCK
        )


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


def service_logger(kind: str, robot: int, level: str) -> logging.Logger:
    log = logging.getLogger(f"swarmrec.{kind}.{robot}")
    log.handlers.clear()
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_JsonFormatter(kind, robot))
    log.addHandler(handler)
    log.setLevel(level.upper())
    log.propagate = False
    return log


def zenoh_config(settings: ServiceSettings) -> zenoh.Config:
    """A zenoh config from the settings: explicit endpoints, no multicast scouting
    (containers have no multicast), clients retry until the router is up."""
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(settings.mode))
    if settings.connect and settings.mode != "router":
        conf.insert_json5("connect/endpoints", json.dumps(list(settings.connect)))
        # Without this a client fails at start when the router is not up yet.
        conf.insert_json5("connect/timeout_ms", "-1")
    if settings.listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(settings.listen)))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


def install_signals(stop: threading.Event) -> None:
    if threading.current_thread() is not threading.main_thread():
        return  # only the main thread may set handlers (tests run services in threads)
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())


class _Dispatcher:
    """Serves one endpoint: decode, call the handler, encode, count, never raise."""

    def __init__(self, ctx: ServiceContext, endpoint: Endpoint) -> None:
        self.ctx, self.endpoint = ctx, endpoint
        self.expected = schema_name(endpoint.request)
        self.latency = ctx.metrics.request_seconds.labels(endpoint.name)

    def serve(self, query: zenoh.Query) -> None:
        t0 = time.perf_counter()
        ctx, ep = self.ctx, self.endpoint
        robot = caller_robot(query.attachment)
        scope = scope_between(ctx.settings.robot, robot)
        try:
            data = query.payload.to_bytes() if query.payload is not None else b""
            ctx.metrics.count_received(ep.request.__name__, scope, len(data))
            schema = schema_of(query.encoding)
            if schema and schema != self.expected:
                raise RequestError(
                    pb.ErrorCode.ERROR_CODE_INVALID_ARGUMENT, f"{ep.name} takes {self.expected}, got {schema}"
                )
            if len(data) > ctx.settings.max_message_bytes:
                raise RequestError(
                    pb.ErrorCode.ERROR_CODE_TOO_LARGE,
                    f"{len(data)} bytes exceed the limit of {ctx.settings.max_message_bytes}",
                )
            try:
                request = decode(data, ep.request)
            except WireError as e:
                raise RequestError(pb.ErrorCode.ERROR_CODE_MALFORMED, str(e)) from None
            reply = ep.handler(request, RequestContext(robot, str(query.key_expr)))
            payload = encode(reply)
            query.reply(query.key_expr, payload, encoding=encoding_for(reply))
            ctx.metrics.count_sent(type(reply).__name__, scope, len(payload))
        except Exception as e:
            self._reject(query, scope, e)
        finally:
            query.drop()  # type: ignore[no-untyped-call]  # untyped in zenoh's stub  # finish the query so the caller does not wait for its timeout
            self.latency.observe(time.perf_counter() - t0)

    def _reject(self, query: zenoh.Query, scope: str, e: Exception) -> None:
        ctx = self.ctx
        if isinstance(e, RequestError):
            code, message = e.code, e.message
        elif isinstance(e, WireError):
            code, message = pb.ErrorCode.ERROR_CODE_INVALID_ARGUMENT, str(e)
        else:
            code, message = pb.ErrorCode.ERROR_CODE_INTERNAL, f"{type(e).__name__}: {e}"
            ctx.log.error("handler failed", exc_info=e, extra={"fields": {"endpoint": self.endpoint.name}})
        name = pb.ErrorCode.Name(code)
        ctx.metrics.rejected.labels(self.endpoint.name, name).inc()
        if code != pb.ErrorCode.ERROR_CODE_INTERNAL:
            ctx.log.warning(
                "rejected request",
                extra={"fields": {"endpoint": self.endpoint.name, "code": name, "reason": message[:300]}},
            )
        err = error_reply(cast(pb.ErrorCode, code), message)
        payload = encode(err)
        try:
            query.reply_err(payload, encoding=encoding_for(err))
            ctx.metrics.count_sent("ErrorReply", scope, len(payload))
        except zenoh.ZError:
            pass  # the caller is gone; nothing left to tell


def _work(queryable: zenoh.Queryable[Any], serve: Callable[[zenoh.Query], None]) -> None:
    # Iteration ends when the queryable is undeclared (its channel closes).
    for query in queryable.handler:
        serve(query)


def run_service(
    settings: ServiceSettings,
    kind: str,
    factory: Callable[[ServiceContext], Service],
    *,
    stop: threading.Event | None = None,
    on_ready: Callable[[pb.MemberInfo], None] | None = None,
) -> int:
    """Run one service until ``stop`` is set (or SIGTERM/SIGINT); returns an exit code."""
    stop = stop or threading.Event()
    install_signals(stop)
    log = service_logger(kind, settings.robot, settings.log_level)
    metrics = ServiceMetrics.create(kind, settings.robot, settings.swarm)
    with zenoh.open(zenoh_config(settings)) as session:
        if settings.metrics_port >= 0:
            metrics.serve(settings.metrics_host, settings.metrics_port)
        caller = Caller(
            session, settings.robot, settings.request_timeout_s, metrics, settings.max_message_bytes
        )
        ctx = ServiceContext(settings, kind, session, metrics, caller, stop, log)
        service = factory(ctx)
        queryables: list[zenoh.Queryable[Any]] = []
        threads: list[threading.Thread] = []
        try:
            for ep in service.endpoints():
                q = session.declare_queryable(keys.endpoint(settings.swarm, kind, settings.robot, ep.name))
                queryables.append(q)
                serve = _Dispatcher(ctx, ep).serve
                for i in range(settings.workers):
                    t = threading.Thread(target=_work, args=(q, serve), name=f"{ep.name}-{i}", daemon=True)
                    t.start()
                    threads.append(t)
            info_q = session.declare_queryable(keys.endpoint(settings.swarm, kind, settings.robot, "info"))
            queryables.append(info_q)

            def answer_info(query: zenoh.Query) -> None:
                info = _member_info(service, settings, kind, metrics.url)
                try:
                    query.reply(query.key_expr, encode(info), encoding=encoding_for(info))
                finally:
                    query.drop()  # type: ignore[no-untyped-call]  # untyped in zenoh's stub

            t = threading.Thread(target=_work, args=(info_q, answer_info), name="info", daemon=True)
            t.start()
            threads.append(t)
            token = session.liveliness().declare_token(keys.alive(settings.swarm, kind, settings.robot))
            metrics.ready.set(1)
            info = _member_info(service, settings, kind, metrics.url)
            log.info("ready", extra={"fields": {"metrics_url": metrics.url}})
            print(
                json.dumps(
                    {"event": "ready", "service": kind, "robot": settings.robot, "metrics_url": metrics.url}
                ),
                flush=True,
            )
            if on_ready is not None:
                on_ready(info)
            stop.wait()
            log.info("stopping")
            metrics.ready.set(0)
            token.undeclare()  # type: ignore[no-untyped-call]  # untyped in zenoh's stub
        finally:
            for q in queryables:
                q.undeclare()  # type: ignore[no-untyped-call]  # untyped in zenoh's stub
            for t in threads:
                t.join(timeout=5.0)
            service.close()
            metrics.close()
    log.info("stopped")
    return 0


def _member_info(service: Service, settings: ServiceSettings, kind: str, url: str) -> pb.MemberInfo:
    info = service.member_info()
    info.kind = KIND_ENUM.get(kind, pb.ServiceKind.SERVICE_KIND_UNSPECIFIED)
    info.robot_id = settings.robot
    info.version = swarmrec.__version__
    info.n_labels = settings.n_labels
    info.metrics_url = url
    info.swarm = settings.swarm
    return info
