"""The gRPC gateway: the swarm for clients in any language, on one port.

One per swarm (scope ``swarm``). It is a zenoh client of the swarm like the
Python client, with a client identity (``client.gateway.<swarm>``: it may query
and subscribe, never store), and serves ``swarmrec.v1.SwarmGateway``
(proto/swarmrec/v1/gateway.proto) over gRPC:

* unary calls: ``Members``, ``Query`` (the read-only two-step query run from the
  gateway's own session, through the shards' ``lookup``), ``LoopClosures``,
  ``Explain`` (a robot's descriptor's ``explain``), ``Status``;
* server streams of live events: loop closures, query reports, fusion
  decisions, membership changes (liveliness, starting with who is alive);
* the other methods (:mod:`swarmrec.services.gateway_methods`): full-image place
  recognition (``PlaceQuery`` by descriptor or by image, ``ClusterTable``,
  ``PlaceLoopClosures``, the place reports' stream), SLAM (``SlamTeam``,
  ``SlamRobotEstimate``, ``WatchSlamEstimate`` while a robot solves, ``SlamMap``: the
  merged map) and landmark rounds (``LandmarkRound``);
* the standard health service (``NOT_SERVING`` until the zenoh session is up
  and the gateway's liveliness token declared, ``NOT_SERVING`` again as soon as
  it stops) and server reflection.

A call's deadline is the deadline of every zenoh request it makes (never more
than ``request_timeout_s``); a call whose deadline passes ends
``DEADLINE_EXCEEDED``. A refusal of the swarm becomes a gRPC status by one table
(:data:`GRPC_STATUS`), with the swarm's code in the trailing metadata
``swarmrec-error-code``. The gRPC port is TLS with the gateway's certificate
from the swarm PKI and asks clients for theirs (``grpc_client_auth``).
"""

from __future__ import annotations

import contextlib
import math
import queue
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn, TypeVar

import grpc
import zenoh

# protobuf ships no type stubs (see swarmrec/runtime/rpc.py for the two codes).
from google.protobuf.message import Message  # type: ignore[import-untyped, unused-ignore]
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

import swarmrec
from swarmrec.client import ERROR_CODE_METADATA, ZenohClient
from swarmrec.errors import (
    ConfigError,
    ErrorCode,
    InvalidArgument,
    NoReply,
    RemoteError,
    ReplyTimeout,
    RequestError,
    WireError,
)
from swarmrec.runtime import ServiceBase, ServiceContext, keys
from swarmrec.runtime.rpc import Caller, Pending
from swarmrec.runtime.settings import SecuritySettings
from swarmrec.runtime.tls import TlsFiles
from swarmrec.services.gateway_methods import SUBSCRIBED_METADATA, GatewayMethods
from swarmrec.services.live_view import LiveView, event_is_publishers
from swarmrec.services.metrics import GatewayMetrics
from swarmrec.services.registry import kind_of_wire
from swarmrec.services.settings import GatewaySettings, VprSettings
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import constellation_from_proto
from swarmrec.wire.gen.swarmrec.v1 import gateway_pb2, gateway_pb2_grpc

__all__ = [
    "GRPC_STATUS",
    "SERVICE_NAME",
    "SERVICE_STREAMS",
    "SUBSCRIBED_METADATA",
    "Gateway",
    "caller_allowed",
    "grpc_status_of",
]

M = TypeVar("M", bound=Message)

#: The gateway's gRPC service name (reflection lists it; health reports it).
SERVICE_NAME: str = gateway_pb2.DESCRIPTOR.services_by_name["SwarmGateway"].full_name

#: The swarm's error codes as gRPC status codes: the one table.
GRPC_STATUS: Mapping[ErrorCode, grpc.StatusCode] = {
    ErrorCode.UNSPECIFIED: grpc.StatusCode.UNKNOWN,
    ErrorCode.INVALID_ARGUMENT: grpc.StatusCode.INVALID_ARGUMENT,
    ErrorCode.MALFORMED: grpc.StatusCode.INVALID_ARGUMENT,
    ErrorCode.UNKNOWN_LABEL: grpc.StatusCode.INVALID_ARGUMENT,
    ErrorCode.TOO_LARGE: grpc.StatusCode.RESOURCE_EXHAUSTED,
    ErrorCode.NOT_FOUND: grpc.StatusCode.NOT_FOUND,
    ErrorCode.UNAVAILABLE: grpc.StatusCode.UNAVAILABLE,
    ErrorCode.TIMEOUT: grpc.StatusCode.DEADLINE_EXCEEDED,
    ErrorCode.INTERNAL: grpc.StatusCode.INTERNAL,
    ErrorCode.FAILED_PRECONDITION: grpc.StatusCode.FAILED_PRECONDITION,
    ErrorCode.ALREADY_EXISTS: grpc.StatusCode.ALREADY_EXISTS,
    ErrorCode.PERMISSION_DENIED: grpc.StatusCode.PERMISSION_DENIED,
}


def grpc_status_of(e: Exception) -> tuple[grpc.StatusCode, ErrorCode]:
    """The gRPC status and the swarm's code a failure is answered with."""
    if isinstance(e, ReplyTimeout):
        return grpc.StatusCode.DEADLINE_EXCEEDED, ErrorCode.TIMEOUT
    if isinstance(e, NoReply):
        return grpc.StatusCode.UNAVAILABLE, ErrorCode.UNAVAILABLE
    if isinstance(e, RemoteError | RequestError | WireError):
        code = ErrorCode.of(int(e.code))
        return GRPC_STATUS[code], code
    if isinstance(e, ConfigError):
        return grpc.StatusCode.INVALID_ARGUMENT, ErrorCode.INVALID_ARGUMENT
    return grpc.StatusCode.INTERNAL, ErrorCode.INTERNAL


#: Streams of the standard services (reflection, health's Watch) open at once, at most: each
#: holds a gRPC worker thread, and a holder of idle ones must not starve the gateway's calls.
SERVICE_STREAMS = 4
#: The long-lived calls of the standard services that :data:`SERVICE_STREAMS` bounds.
_SERVICE_STREAM_METHODS = frozenset(
    {
        "/grpc.reflection.v1alpha.ServerReflection/ServerReflectionInfo",
        "/grpc.health.v1.Health/Watch",
    }
)


def _common_name(context: grpc.ServicerContext) -> str:
    """The caller's certificate's common name; "" without one (plaintext)."""
    names = context.auth_context().get("x509_common_name") or [b""]
    return str(names[0].decode("utf-8", "replace"))


def _stream_caller(context: grpc.ServicerContext) -> str:
    """Who holds a stream, for the per-caller limit: its certificate's common name, or
    without one (plaintext) its address without the port."""
    name = _common_name(context)
    if name:
        return name
    peer = str(context.peer())  # ipv4:127.0.0.1:5555, ipv6:[::1]:5555
    return peer.rsplit(":", 1)[0] if peer.count(":") >= 2 else peer


def caller_allowed(common_name: str, swarm: str) -> str:
    """Why a client certificate's holder may not use this swarm's gateway ("" when it may):
    only the swarm's clients and operators (``client.<name>.<swarm>``, ``operator.<name>.<swarm>``,
    the scheme of :mod:`swarmrec.security.identity`, a layer above) are served; its services,
    its router, another swarm's identities and names outside the scheme are not."""
    parts = common_name.split(".")
    if len(parts) != 3 or parts[0] not in ("client", "operator") or not parts[1]:
        return f"{common_name!r} is not a client or an operator"
    if parts[2] != swarm:
        return f"{common_name!r} belongs to swarm {parts[2]!r}, not {swarm!r}"
    return ""


class _Guard(grpc.ServerInterceptor):  # type: ignore[misc, unused-ignore]  # grpc's base is untyped
    """Every call: the caller's certificate names one of this swarm's clients or operators
    (under client authentication), and the standard services' streams stay few."""

    def __init__(self, swarm: str, check_identity: bool, metrics: GatewayMetrics) -> None:
        self.swarm, self.check_identity, self.metrics = swarm, check_identity, metrics
        self.streams = threading.BoundedSemaphore(SERVICE_STREAMS)

    def _admit(self, method: str, context: grpc.ServicerContext) -> None:
        """Abort the call PERMISSION_DENIED (counted) unless the caller may use the gateway."""
        if not self.check_identity:
            return
        why = caller_allowed(_common_name(context), self.swarm)
        if why:
            self.metrics.calls.labels(method=method.rsplit("/", 1)[-1], code="PERMISSION_DENIED").inc()
            context.abort(
                grpc.StatusCode.PERMISSION_DENIED,
                f"this gateway serves swarm {self.swarm!r}'s clients and operators: {why}",
            )

    def _streamed(
        self, method: str, context: grpc.ServicerContext, produce: Callable[[], Iterator[Any]]
    ) -> Iterator[Any]:
        """A streaming call's answers, once admitted, holding a slot while it streams when it
        is one of the standard services' long-lived calls."""
        self._admit(method, context)
        with self._slot(method in _SERVICE_STREAM_METHODS, context):
            yield from produce()

    def intercept_service(self, continuation: Any, details: Any) -> Any:
        handler = continuation(details)
        if handler is None:
            return None
        method: str = details.method
        guard = self
        if handler.unary_unary is not None:
            inner_uu = handler.unary_unary

            def unary_unary(request: Any, context: grpc.ServicerContext) -> Any:
                guard._admit(method, context)
                return inner_uu(request, context)

            return grpc.unary_unary_rpc_method_handler(
                unary_unary, handler.request_deserializer, handler.response_serializer
            )
        if handler.unary_stream is not None:
            inner_us = handler.unary_stream

            def unary_stream(request: Any, context: grpc.ServicerContext) -> Iterator[Any]:
                return guard._streamed(method, context, lambda: inner_us(request, context))

            return grpc.unary_stream_rpc_method_handler(
                unary_stream, handler.request_deserializer, handler.response_serializer
            )
        if handler.stream_stream is not None:
            inner_ss = handler.stream_stream

            def stream_stream(requests: Iterator[Any], context: grpc.ServicerContext) -> Iterator[Any]:
                return guard._streamed(method, context, lambda: inner_ss(requests, context))

            return grpc.stream_stream_rpc_method_handler(
                stream_stream, handler.request_deserializer, handler.response_serializer
            )
        return handler  # (no client-streaming call in these services)

    @contextlib.contextmanager
    def _slot(self, limited: bool, context: grpc.ServicerContext) -> Iterator[None]:
        """A stream slot, or the call aborted RESOURCE_EXHAUSTED (``limited`` calls only)."""
        if not limited:
            yield
            return
        if not self.streams.acquire(blocking=False):
            context.abort(
                grpc.StatusCode.RESOURCE_EXHAUSTED,
                f"{SERVICE_STREAMS} reflection and health streams are open; close one first",
            )
        try:
            yield
        finally:
            self.streams.release()


class _Deadline(Exception):
    """The call's deadline passed."""


@dataclass
class _DeadlineCaller(Caller):
    """A caller whose every request times out at the gRPC call's deadline at the latest."""

    deadline: float = math.inf

    def start(
        self,
        key: str,
        request: Message,
        *,
        target_robot: int | None,
        endpoint: str = "",
        scatter: bool = False,
        timeout_s: float | None = None,
    ) -> Pending:
        left = self.deadline - time.monotonic()
        if left <= 0:
            raise ReplyTimeout(key, "the call's deadline passed before the request was sent")
        timeout = min(self.timeout_s if timeout_s is None else timeout_s, left)
        return super().start(
            key, request, target_robot=target_robot, endpoint=endpoint, scatter=scatter, timeout_s=timeout
        )


@dataclass(frozen=True)
class _Event:
    """What a stream's zenoh callback hands the stream: bytes and headers, nothing parsed."""

    data: bytes
    key: str
    put: bool


class Gateway(ServiceBase):
    """The gRPC server and the zenoh side it answers from."""

    def __init__(self, ctx: ServiceContext) -> None:
        self.ctx = ctx
        self.bus = ctx.bus
        self.settings = ctx.settings(GatewaySettings)
        self.security = ctx.settings(SecuritySettings)
        self.metrics = ctx.metric_set(GatewayMetrics)
        # A client's caller: no robot id in the attachment (the services count it as client traffic).
        self.caller = Caller(
            ctx.session, None, self.bus.request_timeout_s, ctx.metrics, self.bus.max_message_bytes
        )
        self.swarm = ZenohClient.attached(
            ctx.session, self.bus.swarm, self.caller, timeout_s=self.bus.request_timeout_s
        )
        self.stopping = threading.Event()
        #: The RPCs of the full-image, SLAM and landmark methods.
        self.methods = GatewayMethods(self, ctx.settings(VprSettings))
        self.lock = threading.Lock()
        self.open_streams = 0
        #: Event streams open, by caller (`_stream_caller`).
        self.streams_by_caller: dict[str, int] = {}
        self.ready = False
        self.health = health.HealthServicer(experimental_non_blocking=True)
        self._set_health(health_pb2.HealthCheckResponse.NOT_SERVING)
        self.executor = ThreadPoolExecutor(self.settings.grpc_workers, thread_name_prefix="grpc")
        limit = self.bus.max_message_bytes
        # Whether the port asks for client certificates is known once its credentials are made.
        credentials = self._credentials()
        self.server = grpc.server(
            self.executor,
            interceptors=[_Guard(self.bus.swarm, self._client_auth, self.metrics)],
            options=[("grpc.max_receive_message_length", limit), ("grpc.max_send_message_length", 1 << 24)],
        )
        gateway_pb2_grpc.add_SwarmGatewayServicer_to_server(_Servicer(self), self.server)  # type: ignore[no-untyped-call]  # generated
        health_pb2_grpc.add_HealthServicer_to_server(self.health, self.server)
        reflection.enable_server_reflection(
            (SERVICE_NAME, health.SERVICE_NAME, reflection.SERVICE_NAME), self.server
        )
        address = f"{self.settings.grpc_host}:{self.settings.grpc_port}"
        try:
            if credentials is None:
                self.port = self.server.add_insecure_port(address)
            else:
                self.port = self.server.add_secure_port(address, credentials)
        except RuntimeError as e:
            raise ConfigError(f"the gateway cannot listen on {address}: {e}") from None
        self.tls = credentials is not None
        self.server.start()
        host = self.settings.grpc_host
        self.address = f"grpc://{'127.0.0.1' if host in ('0.0.0.0', '') else host}:{self.port}"
        fields = {"grpc": self.address, "tls": self.tls, "client_auth": self._client_auth}
        ctx.log.info("gRPC gateway listening", extra={"fields": fields})
        self.live: LiveView | None = None
        if self.settings.web_port >= 0:
            try:
                self.live = LiveView(
                    ctx.session,
                    self.bus.swarm,
                    self.swarm,
                    host=self.settings.web_host,
                    port=self.settings.web_port,
                    max_streams=self.settings.web_max_streams,
                    log=ctx.log,
                )
            except OSError as e:
                self.close()
                where = f"{self.settings.web_host}:{self.settings.web_port}"
                raise ConfigError(f"the live view cannot listen on {where}: {e.strerror}") from None
            # (Its address with the token is in the ready line, as readable as the run's folder.)
            ctx.log.info("live view listening", extra={"fields": {"port": self.live.port}})

    # --- lifecycle ---------------------------------------------------------------------

    def _set_health(self, status: int) -> None:
        for name in ("", SERVICE_NAME):
            self.health.set(name, status)

    def announce(self) -> dict[str, Any]:
        info: dict[str, Any] = {"grpc": self.address, "grpc_tls": self.tls}
        if self.live is not None:
            info["web"] = self.live.url
        return info

    def serving(self, ready: bool) -> None:
        self.ready = ready
        if ready:
            self._set_health(health_pb2.HealthCheckResponse.SERVING)
        else:
            self.stopping.set()
            self._set_health(health_pb2.HealthCheckResponse.NOT_SERVING)

    def close(self) -> None:
        self.stopping.set()
        if self.live is not None:
            self.live.close()
        # Calls in flight get a moment to finish; streams see `stopping` and end UNAVAILABLE.
        self.server.stop(grace=2.0).wait(5.0)
        self.executor.shutdown(wait=False, cancel_futures=True)

    # --- the gRPC port's TLS -------------------------------------------------------------

    _client_auth = False

    def _credentials(self) -> grpc.ServerCredentials | None:
        g, sec = self.settings, self.security
        ca: Path | None = None
        if g.grpc_cert is not None and g.grpc_key is not None:
            cert, key = g.grpc_cert, g.grpc_key
            ca = sec.pki_dir / "ca.pem" if sec.pki_dir is not None else None
        elif sec.security == "mtls" and sec.pki_dir is not None:
            files = TlsFiles.in_dir(sec.pki_dir, self.ctx.identity)
            files.check()
            cert, key, ca = files.cert, files.key, files.root_ca
        else:
            self.ctx.log.warning(
                "INSECURE MODE: the gateway's gRPC port is plaintext and unauthenticated: anyone who "
                "reaches it can read the swarm's answers. Give grpc_cert and grpc_key, or run with mtls.",
                extra={"fields": {"security": "insecure"}},
            )
            return None
        self._client_auth = g.grpc_client_auth and ca is not None
        return grpc.ssl_server_credentials(
            [(key.read_bytes(), cert.read_bytes())],
            root_certificates=ca.read_bytes() if self._client_auth and ca is not None else None,
            require_client_auth=self._client_auth,
        )

    # --- answering -----------------------------------------------------------------------

    def caller_for(self, context: grpc.ServicerContext) -> _DeadlineCaller:
        """A caller whose requests end at the call's deadline (or request_timeout_s)."""
        left = context.time_remaining()
        deadline = time.monotonic() + (left if left is not None else math.inf)
        return _DeadlineCaller(
            self.ctx.session,
            None,
            self.bus.request_timeout_s,
            self.ctx.metrics,
            self.bus.max_message_bytes,
            keys=self.caller.keys,  # one set of declared keys, not one per call
            deadline=deadline,
        )

    def unary(self, method: str, context: grpc.ServicerContext, work: Callable[[_DeadlineCaller], M]) -> M:
        """Run ``work`` with the call's deadline; map a failure to its gRPC status."""
        t0 = time.perf_counter()
        code = grpc.StatusCode.OK
        try:
            if not self.ready:
                raise NoReply(
                    f"gateway {self.bus.swarm}", "the gateway is not serving (starting or stopping)"
                )
            caller = self.caller_for(context)
            reply = work(caller)
            if time.monotonic() > caller.deadline:
                raise _Deadline()
            return reply
        except _Deadline:
            code = grpc.StatusCode.DEADLINE_EXCEEDED
            self._abort(
                context, code, ErrorCode.TIMEOUT, "the call's deadline passed before the swarm answered"
            )
        except Exception as e:
            code, swarm_code = grpc_status_of(e)
            if code == grpc.StatusCode.INTERNAL:
                self.ctx.log.error("gateway call failed", exc_info=e, extra={"fields": {"method": method}})
            message = e.message if isinstance(e, RequestError) else str(e)
            self._abort(context, code, swarm_code, message)
        finally:
            self.metrics.calls.labels(method, code.name).inc()
            self.metrics.call_seconds.labels(method).observe(time.perf_counter() - t0)

    def abort_for(self, context: grpc.ServicerContext, e: Exception) -> NoReturn:
        """End a streaming call with the status of ``e`` (the table of unary calls)."""
        code, swarm_code = grpc_status_of(e)
        if code == grpc.StatusCode.INTERNAL:
            self.ctx.log.error("gateway stream failed", exc_info=e)
        self._abort(context, code, swarm_code, e.message if isinstance(e, RequestError) else str(e))

    @staticmethod
    def _abort(context: grpc.ServicerContext, code: grpc.StatusCode, swarm: ErrorCode, text: str) -> NoReturn:
        context.set_trailing_metadata(((ERROR_CODE_METADATA, swarm.wire_name),))
        context.abort(code, text[:1000])
        raise AssertionError("unreachable: abort raises")

    def members(self, caller: _DeadlineCaller) -> gateway_pb2.MembersReply:
        left = max(caller.deadline - time.monotonic(), 0.001)
        infos = self.swarm.member_infos(min(left, self.bus.request_timeout_s))
        return gateway_pb2.MembersReply(members=infos)

    def query(self, req: gateway_pb2.QueryRequest, caller: _DeadlineCaller) -> gateway_pb2.QueryReply:
        if not req.HasField("constellation") or not req.constellation.labels:
            raise InvalidArgument("a query needs a constellation with at least one object")
        left = max(caller.deadline - time.monotonic(), 0.001)
        plan = self.swarm.plan(req.preset or "paper", timeout_s=min(left, self.bus.request_timeout_s))
        constellation = constellation_from_proto(req.constellation, plan.n_labels)
        t0 = time.perf_counter()
        result = self.swarm.query(constellation, plan=plan, caller=caller)
        if time.monotonic() > caller.deadline:
            raise _Deadline()  # what timed out is listed as failed, but the caller gave up first
        return gateway_pb2.QueryReply(
            matches=result.matches,
            n_candidates=result.n_candidates,
            verified_robot_ids=result.verified_robots,
            failed_shard_robot_ids=result.failed_shards,
            failed_verifier_robot_ids=result.failed_verifiers,
            duration_us=min(int((time.perf_counter() - t0) * 1e6), 2**32 - 1),
        )

    def loop_closures(
        self, req: gateway_pb2.RobotLoopClosuresRequest, caller: _DeadlineCaller
    ) -> pb.LoopClosureList:
        key = keys.endpoint(self.bus.swarm, "descriptor", req.robot_id, "loop_closures")
        try:
            return caller.call(
                key, pb.LoopClosuresRequest(min_score=req.min_score), pb.LoopClosureList, target_robot=None
            )
        except NoReply:
            raise RequestError(
                f"robot {req.robot_id} has no live descriptor", code=ErrorCode.NOT_FOUND
            ) from None

    def explain(self, req: gateway_pb2.RobotExplainRequest, caller: _DeadlineCaller) -> pb.ExplainReply:
        if not req.HasField("frame_index"):
            raise InvalidArgument("RobotExplainRequest has no frame_index; it is required")
        key = keys.endpoint(self.bus.swarm, "descriptor", req.robot_id, "explain")
        try:
            return caller.call(
                key, pb.ExplainRequest(frame_index=req.frame_index), pb.ExplainReply, target_robot=None
            )
        except NoReply:
            raise RequestError(
                f"robot {req.robot_id} has no live descriptor", code=ErrorCode.NOT_FOUND
            ) from None

    def status(self, caller: _DeadlineCaller) -> gateway_pb2.StatusReply:
        left = max(caller.deadline - time.monotonic(), 0.001)
        infos = self.swarm.member_infos(min(left, self.bus.request_timeout_s))
        by_kind: dict[str, int] = {}
        for info in infos:
            by_kind[kind_of_wire(info.kind)] = by_kind.get(kind_of_wire(info.kind), 0) + 1
        shards = [i.robot_id for i in infos if i.kind == pb.ServiceKind.SERVICE_KIND_INDEX_SHARD]
        return gateway_pb2.StatusReply(
            swarm=self.bus.swarm,
            version=swarmrec.__version__,
            serving=self.ready,
            n_robots=len(set(shards)),
            services_by_kind=by_kind,
            zenoh_security=self.security.security,
            open_streams=self.open_streams,
        )

    # --- streams -------------------------------------------------------------------------

    def take_stream_slot(
        self, context: grpc.ServicerContext, on_release: Callable[[], None]
    ) -> Callable[[], None]:
        """A stream slot for this call (or the call aborted: the gateway not serving,
        UNAVAILABLE; every slot or the caller's share taken, RESOURCE_EXHAUSTED). Returns the
        release, which runs ``on_release`` then frees the slot, once however often it is called."""
        if not self.ready:
            self._abort(
                context, grpc.StatusCode.UNAVAILABLE, ErrorCode.UNAVAILABLE, "the gateway is not serving"
            )
        caller, per_caller = _stream_caller(context), self.settings.grpc_max_streams_per_caller
        with self.lock:
            held = self.streams_by_caller.get(caller, 0)
            if self.open_streams >= self.settings.grpc_max_streams:
                full = f"{self.settings.grpc_max_streams} streams are open already (grpc_max_streams)"
            elif held >= per_caller:
                full = f"{caller} holds {held} streams open already (grpc_max_streams_per_caller)"
            else:
                full = ""
                self.open_streams += 1
                self.streams_by_caller[caller] = held + 1
                self.metrics.streams_open.set(self.open_streams)
        if full:
            self._abort(context, grpc.StatusCode.RESOURCE_EXHAUSTED, ErrorCode.UNAVAILABLE, full)
        released = threading.Lock()

        def release() -> None:
            # Once, when the call ends: from the stream's own loop, or from gRPC's termination
            # callback when the client leaves while the stream waits at a `yield` (gRPC then
            # never resumes it, and the slot would stay taken until the generator is collected).
            if not released.acquire(blocking=False):
                return
            on_release()
            with self.lock:
                self.open_streams -= 1
                left = self.streams_by_caller.pop(caller) - 1
                if left:
                    self.streams_by_caller[caller] = left
                self.metrics.streams_open.set(self.open_streams)

        return release

    def stream(
        self,
        name: str,
        context: grpc.ServicerContext,
        subscribe: Callable[[Callable[[zenoh.Sample], None]], Sequence[Any]],
        convert: Callable[[_Event], Message | None],
    ) -> Iterator[Message]:
        """Events from the subscribers ``subscribe`` declares, converted, until the client
        leaves or the gateway stops (then UNAVAILABLE)."""
        subscribers: list[Any] = []

        def undeclare() -> None:
            for sub in subscribers:
                sub.undeclare()

        release = self.take_stream_slot(context, undeclare)
        inbox: queue.Queue[_Event] = queue.Queue(maxsize=self.settings.grpc_stream_buffer)
        overflow = threading.Event()

        def on_sample(sample: zenoh.Sample) -> None:
            # zenoh's thread: copy the bytes out and return.
            event = _Event(
                sample.payload.to_bytes(), str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT
            )
            try:
                inbox.put_nowait(event)
            except queue.Full:
                overflow.set()

        subscribers += subscribe(on_sample)
        if not context.add_callback(release):
            release()  # the call has ended already
        sent = self.metrics.events_sent.labels(name)
        try:
            context.send_initial_metadata(((SUBSCRIBED_METADATA, "1"),))
            while context.is_active():
                if self.stopping.is_set():
                    self._abort(
                        context, grpc.StatusCode.UNAVAILABLE, ErrorCode.UNAVAILABLE, "the gateway is stopping"
                    )
                try:
                    event = inbox.get(timeout=0.1)
                except queue.Empty:
                    if overflow.is_set():
                        self._abort(
                            context,
                            grpc.StatusCode.RESOURCE_EXHAUSTED,
                            ErrorCode.UNAVAILABLE,
                            f"the client reads slower than events arrive ({inbox.maxsize} queued)",
                        )
                    continue
                msg = convert(event)
                if msg is not None:
                    sent.inc()
                    yield msg
        finally:
            release()

    def event_stream(
        self, name: str, event: str, cls: type[M], robots: Sequence[int], context: grpc.ServicerContext
    ) -> Iterator[Message]:
        session, swarm = self.ctx.session, self.bus.swarm
        targets: list[int | str] = list(dict.fromkeys(robots)) or ["*"]

        def subscribe(callback: Callable[[zenoh.Sample], None]) -> list[Any]:
            return [session.declare_subscriber(keys.event(swarm, event, r), callback) for r in targets]

        def convert(e: _Event) -> Message | None:
            try:
                msg = cls.FromString(e.data)
            except Exception:  # a malformed event is the publisher's problem, not the stream's
                return None
            # A payload claiming another robot than the key it came on (its publisher's) is not
            # passed on as that robot's.
            if not event_is_publishers(msg, e.key):
                self.metrics.calls.labels(method=f"{name}:forged_event", code="DROPPED").inc()
                return None
            return msg

        return self.stream(name, context, subscribe, convert)

    def membership_stream(self, robots: Sequence[int], context: grpc.ServicerContext) -> Iterator[Message]:
        session, swarm = self.ctx.session, self.bus.swarm
        wanted = set(robots)

        def subscribe(callback: Callable[[zenoh.Sample], None]) -> list[Any]:
            # history: the tokens alive now come first, as joins.
            return [session.liveliness().declare_subscriber(keys.alive_all(swarm), callback, history=True)]

        def convert(e: _Event) -> Message | None:
            parsed = keys.parse_alive(e.key)
            if parsed is None or (wanted and parsed[1] not in wanted):
                return None
            return gateway_pb2.MembershipChange(kind=parsed[0], robot_id=parsed[1], alive=e.put)

        return self.stream("membership", context, subscribe, convert)


class _Servicer(gateway_pb2_grpc.SwarmGatewayServicer):  # type: ignore[misc, unused-ignore]  # generated, untyped
    """The generated servicer's methods, each handed to the gateway."""

    def __init__(self, gateway: Gateway) -> None:
        self.g = gateway

    def Members(self, request: Any, context: grpc.ServicerContext) -> Any:  # gRPC's method names
        return self.g.unary("Members", context, self.g.members)

    def Query(self, request: Any, context: grpc.ServicerContext) -> Any:
        return self.g.unary("Query", context, lambda caller: self.g.query(request, caller))

    def LoopClosures(self, request: Any, context: grpc.ServicerContext) -> Any:
        return self.g.unary("LoopClosures", context, lambda caller: self.g.loop_closures(request, caller))

    def Explain(self, request: Any, context: grpc.ServicerContext) -> Any:
        return self.g.unary("Explain", context, lambda caller: self.g.explain(request, caller))

    def Status(self, request: Any, context: grpc.ServicerContext) -> Any:
        return self.g.unary("Status", context, self.g.status)

    def WatchLoopClosures(self, request: Any, context: grpc.ServicerContext) -> Any:
        return self.g.event_stream(
            "loop_closures", "loop_closure", pb.LoopClosure, request.robot_ids, context
        )

    def WatchQueryReports(self, request: Any, context: grpc.ServicerContext) -> Any:
        return self.g.event_stream("query_reports", "query", pb.QueryReport, request.robot_ids, context)

    def WatchFusion(self, request: Any, context: grpc.ServicerContext) -> Any:
        return self.g.event_stream("fusion", "fusion", pb.FusionUpdate, request.robot_ids, context)

    def WatchMembership(self, request: Any, context: grpc.ServicerContext) -> Any:
        return self.g.membership_stream(request.robot_ids, context)

    # The other methods (swarmrec.services.gateway_methods).

    def PlaceQuery(self, request: Any, context: grpc.ServicerContext) -> Any:
        return self.g.unary("PlaceQuery", context, lambda caller: self.g.methods.place_query(request, caller))

    def ClusterTable(self, request: Any, context: grpc.ServicerContext) -> Any:
        return self.g.unary("ClusterTable", context, self.g.methods.cluster_table)

    def PlaceLoopClosures(self, request: Any, context: grpc.ServicerContext) -> Any:
        return self.g.unary(
            "PlaceLoopClosures", context, lambda caller: self.g.methods.place_loop_closures(request, caller)
        )

    def WatchPlaceReports(self, request: Any, context: grpc.ServicerContext) -> Any:
        return self.g.event_stream("place_reports", "place_query", pb.PlaceReport, request.robot_ids, context)

    def SlamTeam(self, request: Any, context: grpc.ServicerContext) -> Any:
        return self.g.unary("SlamTeam", context, self.g.methods.slam_team)

    def SlamRobotEstimate(self, request: Any, context: grpc.ServicerContext) -> Any:
        return self.g.unary(
            "SlamRobotEstimate", context, lambda caller: self.g.methods.slam_estimate(request, caller)
        )

    def WatchSlamEstimate(self, request: Any, context: grpc.ServicerContext) -> Any:
        return self.g.methods.watch_estimate(request, context)

    def SlamMap(self, request: Any, context: grpc.ServicerContext) -> Any:
        return self.g.unary("SlamMap", context, self.g.methods.slam_map)

    def LandmarkRound(self, request: Any, context: grpc.ServicerContext) -> Any:
        return self.g.unary(
            "LandmarkRound", context, lambda caller: self.g.methods.landmark_round(request, caller)
        )
