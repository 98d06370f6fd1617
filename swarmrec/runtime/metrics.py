"""Prometheus metrics of one service process: the families every service has, and
the set its own kind declares (:class:`MetricSet`, listed in the registry).

Names follow Prometheus conventions (``_total`` counters, base units:
bytes, seconds) and every label has a small fixed set of values:

* ``message``: a v1 schema's short name (PartialQuery, CandidatesReply, ...),
* ``scope``: ``robot`` (between two services of the same robot), ``swarm``
  (between robots: the radio traffic the paper counts), ``client`` (to or
  from a tool outside the swarm: the main job, the CLI),
* ``endpoint``: one of a service's few endpoint (or subscription) names,
* ``code``: an ErrorCode name; ``reason``: why a peer failed.

Each message is counted once by its sender (``*_sent_*``) and once by its
receiver (``*_received_*``); the report sums the senders' ``scope="swarm"``
bytes. Payload bytes are the protobuf bytes handed to zenoh; zenoh's own
framing (a few bytes a message) is not included, because the Python wheel
has no per-key traffic statistics (../shared/ZENOH.md).
"""

from __future__ import annotations

import socket
import threading
from dataclasses import dataclass
from typing import ClassVar, TypeVar

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, Info, start_http_server

__all__ = ["LATENCY_BUCKETS", "SCOPES", "MetricInfo", "MetricSet", "ServiceMetrics", "scope_between"]

SCOPES = ("robot", "swarm", "client")

#: Request latencies on loopback are 0.2-5 ms; buckets resolve that range.
LATENCY_BUCKETS = (0.0002, 0.0005, 0.001, 0.002, 0.003, 0.005, 0.0075, 0.01, 0.02, 0.05, 0.1, 0.5, 2.0)

S = TypeVar("S", bound="MetricSet")


def scope_between(own_robot: int | None, other_robot: int | None) -> str:
    """Scope of a message between ``own_robot`` and ``other_robot`` (None: not a robot)."""
    if own_robot is None or other_robot is None:
        return "client"
    return "robot" if own_robot == other_robot else "swarm"


@dataclass(frozen=True)
class MetricInfo:
    """One metric family as the contract pages list it."""

    name: str
    type: str
    help: str
    labels: tuple[str, ...]


class MetricSet:
    """The metric families of one service kind, created in the service's registry.

    A subclass implements :meth:`create`; the runner creates the set its registry
    entry names, and the service takes it with :meth:`ServiceContext.metric_set`.
    """

    title: ClassVar[str] = "metrics"

    @classmethod
    def create(cls: type[S], registry: CollectorRegistry) -> S:
        raise NotImplementedError

    @classmethod
    def describe(cls) -> list[MetricInfo]:
        """The families this set exports (created in a throwaway registry)."""
        registry = CollectorRegistry(auto_describe=True)
        cls.create(registry)
        return _families(registry)


def _families(registry: CollectorRegistry) -> list[MetricInfo]:
    out = []
    for fam in registry.collect():
        suffix = "_total" if fam.type == "counter" else ""
        labels: set[str] = set()
        for s in fam.samples:
            labels |= set(s.labels)
        labels -= {"le"}
        out.append(MetricInfo(fam.name + suffix, fam.type, fam.documentation, tuple(sorted(labels))))
    return out


@dataclass
class ServiceMetrics:
    """The families every service exports, in a registry of its own."""

    registry: CollectorRegistry
    bytes_sent: Counter
    bytes_received: Counter
    messages_sent: Counter
    messages_received: Counter
    request_seconds: Histogram
    rejected: Counter
    peer_failures: Counter
    ready: Gauge
    url: str = ""

    @classmethod
    def create(cls, kind: str, robot: int, swarm: str) -> ServiceMetrics:
        reg = CollectorRegistry(auto_describe=True)
        # Which process this is: Prometheus adds job/instance labels of its own,
        # and a scraper without them joins on this series.
        Info("swarmrec_service", "The service behind this endpoint", registry=reg).info(
            {"service": kind, "robot": str(robot), "swarm": swarm}
        )

        def counter(name: str, doc: str, labels: tuple[str, ...] = ()) -> Counter:
            return Counter(name, doc, labels, registry=reg)

        return cls(
            registry=reg,
            bytes_sent=counter(
                "swarmrec_message_bytes_sent",
                "Payload bytes sent, by message type and scope",
                ("message", "scope"),
            ),
            bytes_received=counter(
                "swarmrec_message_bytes_received",
                "Payload bytes received, by message type and scope",
                ("message", "scope"),
            ),
            messages_sent=counter(
                "swarmrec_messages_sent", "Messages sent, by message type and scope", ("message", "scope")
            ),
            messages_received=counter(
                "swarmrec_messages_received",
                "Messages received, by message type and scope",
                ("message", "scope"),
            ),
            request_seconds=Histogram(
                "swarmrec_request_duration_seconds",
                "Time to serve a request (or handle a subscribed message), by endpoint",
                ("endpoint",),
                buckets=LATENCY_BUCKETS,
                registry=reg,
            ),
            rejected=counter(
                "swarmrec_rejected_requests",
                "Requests (and subscribed messages) refused with an error, by endpoint and code",
                ("endpoint", "code"),
            ),
            peer_failures=counter(
                "swarmrec_peer_failures",
                "Requests to peers that failed, by endpoint and reason",
                ("endpoint", "reason"),
            ),
            ready=Gauge(
                "swarmrec_service_ready",
                "1 while the service serves (liveliness token declared), 0 while starting or stopping",
                registry=reg,
            ),
        )

    @classmethod
    def describe(cls) -> list[MetricInfo]:
        """The families every service exports."""
        return [m for m in _families(cls.create("kind", 0, "swarm").registry) if m.name != "swarmrec_service"]

    def count_sent(self, message: str, scope: str, size: int) -> None:
        self.bytes_sent.labels(message, scope).inc(size)
        self.messages_sent.labels(message, scope).inc()

    def count_received(self, message: str, scope: str, size: int) -> None:
        self.bytes_received.labels(message, scope).inc(size)
        self.messages_received.labels(message, scope).inc()

    def serve(self, host: str, port: int) -> str:
        """Serve ``/metrics`` over HTTP on a daemon thread; returns its URL."""
        server, _thread = start_http_server(port, addr=host, registry=self.registry)
        self._server = server
        # Bound to every interface (a container): peers reach it by host name.
        shown = socket.gethostname() if host in ("0.0.0.0", "::", "") else host
        self.url = f"http://{shown}:{server.server_port}/metrics"
        return self.url

    def close(self) -> None:
        server = getattr(self, "_server", None)
        if server is not None:
            # shutdown() waits for the serve loop; run it off-thread so a stuck
            # scrape cannot hold up the service's exit.
            t = threading.Thread(target=server.shutdown, daemon=True)
            t.start()
            t.join(timeout=2.0)
            server.server_close()
