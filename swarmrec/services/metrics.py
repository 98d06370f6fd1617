"""Prometheus metrics of one service process.

Names follow Prometheus conventions (``_total`` counters, base units:
bytes, seconds) and every label has a small fixed set of values:

* ``message``: a v1 schema's short name (PartialQuery, CandidatesReply, ...),
* ``scope``: ``robot`` (between two services of the same robot), ``swarm``
  (between robots: the radio traffic the paper counts), ``client`` (to or
  from a tool outside the swarm: the main job, the CLI),
* ``endpoint``: one of a service's few endpoint names,
* ``code``: an ErrorCode name; ``reason``: why a peer failed, or why the
  fusion service rejected a flooded message (a few fixed names, docs/fusion.md),
  or why the detector dropped a box,
* ``outcome``: what the detector made of a frame, ``stage``: a step of its
  frame pipeline (docs/detector.md).

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

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, Info, start_http_server

__all__ = ["SCOPES", "ServiceMetrics", "scope_between"]

SCOPES = ("robot", "swarm", "client")

# Request latencies on loopback are 0.2-5 ms; buckets resolve that range.
_LATENCY_BUCKETS = (0.0002, 0.0005, 0.001, 0.002, 0.003, 0.005, 0.0075, 0.01, 0.02, 0.05, 0.1, 0.5, 2.0)
# The detector's stages take 0.1 ms (object points) to 100 ms (a model on a busy core).
_STAGE_BUCKETS = (0.0001, 0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.03, 0.05, 0.1, 0.2, 0.5, 2.0)


def scope_between(own_robot: int | None, other_robot: int | None) -> str:
    """Scope of a message between ``own_robot`` and ``other_robot`` (None: not a robot)."""
    if own_robot is None or other_robot is None:
        return "client"
    return "robot" if own_robot == other_robot else "swarm"


@dataclass
class ServiceMetrics:
    """The metric families every service exports, in a registry of its own."""

    registry: CollectorRegistry
    bytes_sent: Counter
    bytes_received: Counter
    messages_sent: Counter
    messages_received: Counter
    request_seconds: Histogram
    rejected: Counter
    peer_failures: Counter
    shard_partial_queries: Counter
    stored_descriptors: Gauge
    stored_frames: Gauge
    loop_closures: Counter
    query_seconds: Histogram
    fusion_rounds: Counter
    fusion_incorporated: Counter
    fusion_duplicates: Counter
    fusion_rejected: Counter
    fusion_early: Counter
    detector_frames: Counter
    detector_boxes_dropped: Counter
    detector_objects: Counter
    detector_stage_seconds: Histogram
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
                "Time to serve a request, by endpoint",
                ("endpoint",),
                buckets=_LATENCY_BUCKETS,
                registry=reg,
            ),
            rejected=counter(
                "swarmrec_rejected_requests",
                "Requests answered with an error reply, by endpoint and code",
                ("endpoint", "code"),
            ),
            peer_failures=counter(
                "swarmrec_peer_failures",
                "Requests to peers that failed, by endpoint and reason",
                ("endpoint", "reason"),
            ),
            shard_partial_queries=counter(
                "swarmrec_shard_partial_queries", "Partial queries served by this index shard"
            ),
            stored_descriptors=Gauge(
                "swarmrec_shard_stored_descriptors",
                "Partial descriptors held by this index shard",
                registry=reg,
            ),
            stored_frames=Gauge(
                "swarmrec_verifier_stored_frames",
                "Constellations held by this verifier",
                registry=reg,
            ),
            loop_closures=counter("swarmrec_loop_closures", "Loop closures found by this robot"),
            query_seconds=Histogram(
                "swarmrec_query_duration_seconds",
                "Time of one two-step query, frame in to last verifier reply",
                buckets=_LATENCY_BUCKETS,
                registry=reg,
            ),
            fusion_rounds=counter("swarmrec_fusion_rounds", "Fusion rounds this robot started"),
            fusion_incorporated=counter(
                "swarmrec_fusion_incorporated",
                "Other robots' classifier outputs folded into this robot's posterior",
            ),
            fusion_duplicates=counter(
                "swarmrec_fusion_duplicates",
                "Flooded copies of an already-heard origin, ignored (Algorithm 1 line 11)",
            ),
            fusion_rejected=counter(
                "swarmrec_fusion_rejected",
                "Flooded messages rejected by the fusion service, by reason",
                ("reason",),
            ),
            fusion_early=counter(
                "swarmrec_fusion_early_messages",
                "Flooded messages that arrived before this robot started their round, kept for it",
            ),
            detector_frames=counter(
                "swarmrec_detector_frames",
                "RGB-D frames the detector handled, by outcome (detected, no_objects, or why it skipped)",
                ("outcome",),
            ),
            detector_boxes_dropped=counter(
                "swarmrec_detector_boxes_dropped",
                "Detected boxes left out of the constellation, by reason (no_depth: no valid depth pixel)",
                ("reason",),
            ),
            detector_objects=counter(
                "swarmrec_detector_objects", "Objects in the constellations the detector made"
            ),
            detector_stage_seconds=Histogram(
                "swarmrec_detector_stage_seconds",
                "Time of one frame in each detector stage (decode, detect, points)",
                ("stage",),
                buckets=_STAGE_BUCKETS,
                registry=reg,
            ),
            ready=Gauge(
                "swarmrec_service_ready",
                "1 while the service serves (liveliness token declared), 0 while starting or stopping",
                registry=reg,
            ),
        )

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
