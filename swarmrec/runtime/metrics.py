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
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import ClassVar, TypeVar

from prometheus_client import (
    CONTENT_TYPE_LATEST,
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    Info,
    generate_latest,
)

__all__ = [
    "HEALTH_PATH",
    "LATENCY_BUCKETS",
    "READY_PATH",
    "SCOPES",
    "MetricInfo",
    "MetricSet",
    "MetricsServer",
    "ServiceMetrics",
    "scope_between",
]

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
class EndpointCost:
    """The requests a service served on one endpoint and the CPU time they took (of the
    serving thread: reading, decoding, the handler, encoding and replying), which a
    service can read back (an index shard reports its queries' and stores' costs to
    the coordinator, which rebalances on them)."""

    calls: int = 0
    cpu_s: float = 0.0
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False, compare=False)

    def add(self, cpu_s: float) -> None:
        with self._lock:
            self.calls += 1
            self.cpu_s += cpu_s

    def snapshot(self) -> tuple[int, float]:
        """(calls, CPU seconds), read together."""
        with self._lock:
            return self.calls, self.cpu_s


@dataclass
class ServiceMetrics:
    """The families every service exports, in a registry of its own."""

    registry: CollectorRegistry
    bytes_sent: Counter
    bytes_received: Counter
    messages_sent: Counter
    messages_received: Counter
    request_seconds: Histogram
    request_cpu_seconds: Counter
    rejected: Counter
    peer_failures: Counter
    ready: Gauge
    url: str = ""
    costs: dict[str, EndpointCost] = field(default_factory=dict)

    def cost(self, endpoint: str) -> EndpointCost:
        """The running cost of ``endpoint`` (made on first use; one per endpoint name)."""
        return self.costs.setdefault(endpoint, EndpointCost())

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
            request_cpu_seconds=counter(
                "swarmrec_request_cpu_seconds",
                "CPU time of the serving thread to serve requests (or handle subscribed messages), "
                "by endpoint",
                ("endpoint",),
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


#: The probe pages every process serves beside its metrics (Kubernetes ``httpGet`` probes).
READY_PATH, HEALTH_PATH = "/ready", "/healthz"


class MetricsServer:
    """One process's Prometheus endpoint: each hosted service's registry at its own path,
    and two probe pages.

    A process hosting one service serves it at ``/metrics`` (what the containers' health
    check and Prometheus read). A process hosting several serves each at
    ``/metrics/<kind>/<robot>`` and, at ``/metrics``, the host's own registry
    (``swarmrec_service_ready``: 1 while every hosted service serves).

    ``/ready`` answers 200 while every hosted service serves (the runner calls
    :meth:`set_ready` when their liveliness tokens are up, and clears it first thing
    when stopping) and 503 otherwise; ``/healthz`` answers 200 as long as the process
    serves HTTP at all. Both are a few bytes and no metrics rendering, so a probe costs
    the process next to nothing (an exec probe starts a Python interpreter).
    """

    def __init__(self, host: str, port: int) -> None:
        self.host, self.port = host, port
        self.paths: dict[str, CollectorRegistry] = {}
        self._server: ThreadingHTTPServer | None = None
        self._ready = threading.Event()
        self.base_url = ""

    @property
    def ready(self) -> bool:
        """What ``/ready`` says now."""
        return self._ready.is_set()

    def set_ready(self, ready: bool) -> None:
        """Make ``/ready`` answer 200 (``True``) or 503 (``False``)."""
        if ready:
            self._ready.set()
        else:
            self._ready.clear()

    def start(self) -> str:
        """Listen (port 0: a free one) on a daemon thread; returns the base URL."""
        paths, ready = self.paths, self._ready

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                path = self.path.split("?", 1)[0].rstrip("/") or "/"
                if path == READY_PATH:
                    up = ready.is_set()
                    self._plain(200 if up else 503, b"ready\n" if up else b"not ready\n")
                    return
                if path == HEALTH_PATH:
                    self._plain(200, b"ok\n")
                    return
                registry = paths.get(path)
                if registry is None:
                    self.send_error(404, "no such metrics path")
                    return
                body = generate_latest(registry)
                self.send_response(200)
                self.send_header("Content-Type", CONTENT_TYPE_LATEST)
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def _plain(self, status: int, body: bytes) -> None:
                self.send_response(status)
                self.send_header("Content-Type", "text/plain; charset=utf-8")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, *_args: object) -> None:
                pass  # a scrape every few seconds is not worth a log line

        server = ThreadingHTTPServer((self.host, self.port), Handler)
        server.daemon_threads = True
        self._server = server
        threading.Thread(target=server.serve_forever, name="metrics", daemon=True).start()
        # Bound to every interface (a container): peers reach it by host name.
        shown = socket.gethostname() if self.host in ("0.0.0.0", "::", "") else self.host
        self.base_url = f"http://{shown}:{server.server_address[1]}"
        return self.base_url

    def add(self, path: str, registry: CollectorRegistry) -> str:
        """Serve ``registry`` at ``path``; returns its URL (after :meth:`start`)."""
        self.paths[path] = registry
        return self.base_url + path

    def close(self) -> None:
        if self._server is not None:
            # shutdown() waits for the serve loop; run it off-thread so a stuck
            # scrape cannot hold up the process's exit.
            t = threading.Thread(target=self._server.shutdown, daemon=True)
            t.start()
            t.join(timeout=2.0)
            self._server.server_close()
            self._server = None
