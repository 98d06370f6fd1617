"""Request/response over zenoh queries, protobuf in and out (the gRPC-like layer).

A request is a zenoh ``get`` whose payload is one v1 message; the answer is
one reply whose encoding names its schema
(``application/protobuf;swarmrec.v1.CandidatesReply``), or an error reply
carrying a ``swarmrec.v1.ErrorReply``. The caller's robot id rides in the
query's attachment so the answering service can tell radio traffic between
robots from traffic inside one robot when it counts bytes.

Per ../shared/ZENOH.md, zero replies is never success: a missing peer, a
crashed peer and a peer not yet discovered all look alike, so
:meth:`Pending.result` raises :class:`NoReply` for them, and a zenoh timeout
(an error reply whose payload is "Timeout") raises :class:`ReplyTimeout`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

import zenoh

# protobuf ships no type stubs and types-protobuf is not a dev dependency; with
# the stubs installed the ignore is unused, hence both codes.
from google.protobuf.message import Message  # type: ignore[import-untyped, unused-ignore]

from swarmrec.errors import CallError, ErrorCode, NoReply, RemoteError, ReplyTimeout, WireError
from swarmrec.runtime.metrics import ServiceMetrics, scope_between
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import decode, encode, schema_name

__all__ = [
    "Caller",
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
            data = ok.payload.to_bytes()
            self.caller.count_received(_short(schema_of(ok.encoding)), self.target_robot, len(data))
            schema = schema_of(ok.encoding)
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
        err = rep.err
        assert err is not None  # a zenoh Reply holds exactly one of ok / err
        data = err.payload.to_bytes()
        if schema_of(err.encoding) == _ERROR_SCHEMA:
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
class Caller:
    """Sends requests from one process; counts their bytes in ``metrics``."""

    session: zenoh.Session
    robot: int | None
    timeout_s: float = 2.0
    metrics: ServiceMetrics | None = None
    max_size: int = 1 << 20

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
        self.count_sent(_short(schema_name(request)), target_robot, len(payload))
        kwargs: dict[str, Any] = {}
        if scatter:
            kwargs = {"target": zenoh.QueryTarget.ALL, "consolidation": zenoh.ConsolidationMode.NONE}
        replies = self.session.get(
            key,
            payload=payload,
            encoding=encoding_for(request),
            attachment=None if self.robot is None else str(self.robot).encode(),
            timeout=self.timeout_s if timeout_s is None else timeout_s,
            # Requests must arrive: the default DROP loses messages under load.
            congestion_control=zenoh.CongestionControl.BLOCK,
            **kwargs,
        )
        return Pending(key, self, target_robot, endpoint or key.rsplit("/", 1)[-1], replies)

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
