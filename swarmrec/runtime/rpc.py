"""Request/response over zenoh queries, protobuf in and out (the gRPC-like layer).

A request is a zenoh ``get`` whose payload is one v1 message; the answer is
one reply whose encoding names its schema
(``application/protobuf;swarmrec.v1.CandidatesReply``), or an error reply
carrying a ``swarmrec.v1.ErrorReply``. The caller's robot id rides in the
query's attachment so the answering service can tell radio traffic between
robots from traffic inside one robot when it counts bytes.

A call from a service to another service of its own robot hosted in the same process
(``--hosting robot``) skips zenoh: the caller finds the endpoint in the process's
:class:`LocalEndpoints` and runs its dispatcher in its own thread, on the same bytes,
through the same checks, counters and error replies as a call over the bus (it has no
timeout: its handler runs in the caller's own thread, in the same process). Only calls
within one robot go so: between robots, even in one process, every byte goes through
the router, the links and the access control the swarm is measured on.

Per ../shared/ZENOH.md, zero replies is never success: a missing peer, a
crashed peer and a peer not yet discovered all look alike, so
:meth:`Pending.result` raises :class:`NoReply` for them, and a zenoh timeout
(an error reply whose payload is "Timeout") raises :class:`ReplyTimeout`.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

import zenoh

# protobuf ships no type stubs and types-protobuf is not a dev dependency; with
# the stubs installed the ignore is unused, hence both codes.
from google.protobuf.message import Message  # type: ignore[import-untyped, unused-ignore]

from swarmrec.errors import CallError, ErrorCode, NoReply, RemoteError, ReplyTimeout, WireError
from swarmrec.runtime import keys
from swarmrec.runtime.metrics import ServiceMetrics, scope_between
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import decode, encode, schema_name

__all__ = [
    "Caller",
    "DeclaredKeys",
    "LocalEndpoints",
    "LocalServe",
    "Outcome",
    "Pending",
    "caller_robot",
    "encoding_for",
    "schema_of",
]

M = TypeVar("M", bound=Message)
_ERROR_SCHEMA = schema_name(pb.ErrorReply)


def encoding_for(msg: Message) -> zenoh.Encoding:
    """The zenoh encoding of a v1 payload: protobuf with its schema name."""
    return zenoh.Encoding.APPLICATION_PROTOBUF.with_schema(schema_name(msg))


def schema_of(encoding: zenoh.Encoding | None) -> str:
    """The schema part of an encoding (``""`` when none was given)."""
    text = str(encoding) if encoding is not None else ""
    return text.split(";", 1)[1] if ";" in text else ""


def caller_robot(attachment: zenoh.ZBytes | None) -> int | None:
    """The caller's robot id from a query attachment; None for a non-robot client."""
    if attachment is None:
        return None
    raw = attachment.to_bytes()
    return int(raw) if raw.isdigit() and len(raw) <= 10 else None


def _short(schema: str) -> str:
    return schema.rsplit(".", 1)[-1] or "unknown"


#: Serves one request in this process: (payload, request schema, caller's robot, key) ->
#: (reply payload, reply schema, True for a reply or False for an ErrorReply).
LocalServe = Callable[[bytes, str, "int | None", str], tuple[bytes, str, bool]]


class LocalEndpoints:
    """The endpoints this process serves, by key, for calls within one robot."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._serve: dict[str, tuple[int, LocalServe]] = {}

    def add(self, key: str, robot: int, serve: LocalServe) -> None:
        with self._lock:
            self._serve[key] = (robot, serve)

    def remove(self, key: str) -> None:
        with self._lock:
            self._serve.pop(key, None)

    def find(self, key: str, robot: int) -> LocalServe | None:
        """The endpoint at ``key`` when it belongs to ``robot``; None otherwise."""
        found = self._serve.get(key)
        return found[1] if found is not None and found[0] == robot else None


@dataclass
class Outcome(Generic[M]):
    """One reply of a scatter/gather request: the message or the error."""

    reply: M | None
    error: CallError | None


@dataclass
class Pending:
    """A request in flight; replies are collected when asked for."""

    key: str
    caller: Caller
    target_robot: int | None
    endpoint: str
    _replies: Any = field(repr=False)
    started: float = field(default_factory=time.perf_counter)

    def _decode(self, rep: zenoh.Reply, reply_cls: type[M]) -> Outcome[M]:
        ok = rep.ok
        if ok is not None:
            return self._outcome(True, ok.payload.to_bytes(), schema_of(ok.encoding), reply_cls)
        err = rep.err
        assert err is not None  # a zenoh Reply holds exactly one of ok / err
        return self._outcome(False, err.payload.to_bytes(), schema_of(err.encoding), reply_cls)

    def _outcome(self, ok: bool, data: bytes, schema: str, reply_cls: type[M]) -> Outcome[M]:
        """One reply (``ok``) or error reply as the caller sees it."""
        if ok:
            self.caller.count_received(_short(schema), self.target_robot, len(data))
            if schema and schema != schema_name(reply_cls):
                return Outcome(
                    None,
                    RemoteError(
                        self.key,
                        ErrorCode.MALFORMED,
                        f"expected {schema_name(reply_cls)}, got {schema}",
                    ),
                )
            try:
                return Outcome(decode(data, reply_cls, max_size=self.caller.max_size), None)
            except WireError as e:
                return Outcome(None, RemoteError(self.key, ErrorCode.MALFORMED, str(e)))
        if schema == _ERROR_SCHEMA:
            self.caller.count_received("ErrorReply", self.target_robot, len(data))
            try:
                msg = decode(data, pb.ErrorReply, max_size=self.caller.max_size)
            except WireError as e:
                return Outcome(None, RemoteError(self.key, ErrorCode.MALFORMED, str(e)))
            return Outcome(None, RemoteError(self.key, msg.code, msg.message))
        text = data.decode("utf-8", "replace")
        # Not one of ours (no ErrorReply schema): zenoh's own error reply. Its only
        # signal for a query timeout is the payload text "Timeout" (ZENOH.md).
        if "timeout" in text.lower():
            return Outcome(None, ReplyTimeout(self.key, f"no answer in {self.caller.timeout_s:g} s"))
        return Outcome(None, RemoteError(self.key, ErrorCode.UNSPECIFIED, text[:200]))

    def gather(self, reply_cls: type[M]) -> list[Outcome[M]]:
        """Every reply (scatter/gather to ``*`` keys); an empty list when nobody answered."""
        return [self._decode(rep, reply_cls) for rep in self._replies]

    def result(self, reply_cls: type[M]) -> M:
        """The single reply; raises NoReply, ReplyTimeout or RemoteError."""
        outcomes = self.gather(reply_cls)
        if not outcomes:
            self.caller.count_failure(self.endpoint, "no_reply")
            raise NoReply(self.key, "no service answered")
        first = outcomes[0]
        if first.error is not None:
            self.caller.count_failure(self.endpoint, getattr(first.error, "reason", "error"))
            raise first.error
        assert first.reply is not None
        return first.reply


@dataclass
class LocalPending(Pending):
    """A request to an endpoint of the caller's own robot in this process: served in the
    caller's thread when its result is first asked for, so the requests started after
    it (to other robots) are already on their way meanwhile."""

    serve: LocalServe | None = None
    payload: bytes = b""
    schema: str = ""
    _answer: tuple[bytes, str, bool] | None = field(default=None, repr=False)

    def gather(self, reply_cls: type[M]) -> list[Outcome[M]]:
        if self._answer is None:
            assert self.serve is not None
            self._answer = self.serve(self.payload, self.schema, self.caller.robot, self.key)
        data, schema, ok = self._answer
        return [self._outcome(ok, data, schema, reply_cls)]


class DeclaredKeys:
    """Keys declared to the router on one session, each the first time it is asked.

    A query on a key no one declared is routed by matching it against the router's whole
    key tree, each time; a declared key has a resource whose route the router keeps (the
    compiled services declare one queryable per service, ``<kind>/<robot>/*``, so the
    callers make the keys). At most ``limit`` keys (a swarm's endpoints are robots x a
    few); past them, or on a session that refuses, the string goes as before."""

    def __init__(self, session: zenoh.Session, limit: int = 4096) -> None:
        self.session, self.limit = session, limit
        self._keys: dict[str, zenoh.KeyExpr] = {}
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._keys)

    def __call__(self, key: str) -> zenoh.KeyExpr | str:
        with self._lock:
            found = self._keys.get(key)
            if found is None and len(self._keys) < self.limit:
                try:
                    found = self._keys[key] = self.session.declare_keyexpr(key)
                except zenoh.ZError:
                    return key
            return key if found is None else found


@dataclass
class Caller:
    """Sends requests from one process; counts their bytes in ``metrics``."""

    session: zenoh.Session
    robot: int | None
    timeout_s: float = 2.0
    metrics: ServiceMetrics | None = None
    max_size: int = 1 << 20
    #: This process's endpoints (a robot's services hosted together): calls to the
    #: caller's own robot go to them directly.
    local: LocalEndpoints | None = None
    #: The keys asked, declared to the router; callers made per request (the gateway's)
    #: share their service's.
    keys: DeclaredKeys | None = None

    def __post_init__(self) -> None:
        if self.keys is None:
            self.keys = DeclaredKeys(self.session)

    def count_sent(self, message: str, target_robot: int | None, size: int) -> None:
        if self.metrics is not None:
            self.metrics.count_sent(message, scope_between(self.robot, target_robot), size)

    def count_received(self, message: str, target_robot: int | None, size: int) -> None:
        if self.metrics is not None:
            self.metrics.count_received(message, scope_between(self.robot, target_robot), size)

    def count_failure(self, endpoint: str, reason: str) -> None:
        if self.metrics is not None:
            self.metrics.peer_failures.labels(endpoint, reason).inc()

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
        """Send ``request`` to ``key`` and return at once; collect with result()/gather().

        ``scatter`` asks every matching service (``QueryTarget.ALL``, no
        consolidation: the default would keep one reply per key).
        """
        payload = encode(request)
        schema = schema_name(request)
        self.count_sent(_short(schema), target_robot, len(payload))
        endpoint = endpoint or key.rsplit("/", 1)[-1]
        if self.local is not None and not scatter and target_robot is not None and target_robot == self.robot:
            serve = self.local.find(key, target_robot)
            if serve is not None:
                return LocalPending(
                    key, self, target_robot, endpoint, None, serve=serve, payload=payload, schema=schema
                )
        kwargs: dict[str, Any] = {}
        if scatter:
            kwargs = {"target": zenoh.QueryTarget.ALL, "consolidation": zenoh.ConsolidationMode.NONE}
        # A caller-bound endpoint's request names its sender in the key (keys.CALLER_BOUND).
        wire_key = keys.request_key(key, self.robot)
        replies = self.session.get(
            self.keys(wire_key) if self.keys is not None else wire_key,
            payload=payload,
            encoding=encoding_for(request),
            attachment=None if self.robot is None else str(self.robot).encode(),
            timeout=self.timeout_s if timeout_s is None else timeout_s,
            # Requests must arrive: the default DROP loses messages under load.
            congestion_control=zenoh.CongestionControl.BLOCK,
            **kwargs,
        )
        return Pending(key, self, target_robot, endpoint, replies)

    def call(
        self,
        key: str,
        request: Message,
        reply_cls: type[M],
        *,
        target_robot: int | None,
        endpoint: str = "",
        timeout_s: float | None = None,
    ) -> M:
        """Send ``request`` and wait for its one reply."""
        return self.start(
            key, request, target_robot=target_robot, endpoint=endpoint, timeout_s=timeout_s
        ).result(reply_cls)
