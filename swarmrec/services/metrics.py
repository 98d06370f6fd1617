"""The metric families each service kind exports beyond the runner's own.

The registry names one set per kind; the runner creates it in the service's
Prometheus registry and the service takes it with ``ctx.metric_set(...)``. An
index shard therefore exports shard metrics and nothing of fusion. Label values
are small fixed sets: ``reason`` (why the fusion service rejected a message, or
why the detector dropped a box, docs/fusion.md, docs/detector.md; where a query's
candidate stopped, :class:`swarmrec.core.funnel.Reason`), ``outcome`` (what the
detector or the descriptor made of a frame), ``stage`` (a step of the detector's
frame pipeline, or of the loop-closure funnel).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram

from swarmrec.core.funnel import Reason
from swarmrec.runtime.metrics import LATENCY_BUCKETS, MetricSet

__all__ = [
    "DESCRIPTOR_FRAME_OUTCOMES",
    "DescriptorMetrics",
    "DetectorMetrics",
    "FusionMetrics",
    "GatewayMetrics",
    "PlaceOwnerMetrics",
    "RouterMetrics",
    "ShardMetrics",
    "SlamMetrics",
    "VerifierMetrics",
]

# The detector's stages take 0.1 ms (object points) to 100 ms (a model on a busy core).
_STAGE_BUCKETS = (0.0001, 0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.03, 0.05, 0.1, 0.2, 0.5, 2.0)


@dataclass
class RouterMetrics(MetricSet):
    """What the router refused, its links to other routers (a mesh) and their bytes.
    Counted by the compiled router only (zenoh's TLS listener, access control, link state
    and transports report to the Rust side; the Python binding is built without zenoh's
    statistics): the Python router exports the families, empty."""

    title: ClassVar[str] = "router"

    refused_handshakes: Counter
    denied_messages: Counter
    link_bytes: Counter
    key_bytes: Counter
    neighbours: Gauge
    graph_links: Gauge
    zid: Gauge

    @classmethod
    def create(cls, registry: CollectorRegistry) -> RouterMetrics:
        return cls(
            refused_handshakes=Counter(
                "swarmrec_router_refused_handshakes",
                "TLS connections the router refused during the handshake, by reason",
                ["reason"],
                registry=registry,
            ),
            denied_messages=Counter(
                "swarmrec_router_denied_messages",
                "Messages the access control dropped, by the certificate's name, direction (received from "
                "it, or not sent to it) and zenoh message type",
                ["identity", "direction", "message"],
                registry=registry,
            ),
            link_bytes=Counter(
                "swarmrec_router_link_bytes",
                "Bytes on the links to other routers (a mesh), as zenoh's transports counted them, by the "
                "neighbour's certificate name and direction (sent to it, received from it); relayed traffic "
                "included",
                ["peer", "direction"],
                registry=registry,
            ),
            key_bytes=Counter(
                "swarmrec_router_key_bytes",
                "Payload bytes on the links to other routers (a mesh) by message type: zenoh's per-key "
                "counts for each key expression of the bus setting stats_keys, by neighbour, direction, "
                "key and zenoh message (query, reply, put); relayed traffic included, framing not",
                ["peer", "direction", "key", "message"],
                registry=registry,
            ),
            neighbours=Gauge(
                "swarmrec_router_neighbours",
                "Links to another router now (a mesh's router, at each scrape), by the neighbour's "
                "zenoh id: 1 while linked, 0 after a link it had closed",
                ["peer_zid"],
                registry=registry,
            ),
            graph_links=Gauge(
                "swarmrec_router_graph_links",
                "The links between routers in this router's view of the router graph now (zenoh's link "
                "state, at each scrape), by the two routers' zenoh ids: 1 while in it, 0 after it left",
                ["a", "b"],
                registry=registry,
            ),
            zid=Gauge("swarmrec_router_zid", "This router's zenoh id", ["zid"], registry=registry),
        )


@dataclass
class ShardMetrics(MetricSet):
    title: ClassVar[str] = "index shard"

    partial_queries: Counter
    stored_descriptors: Gauge
    group_queries: Counter
    placement_version: Gauge
    groups: Gauge
    refused: Counter
    handoff_records: Counter
    placements_published: Counter

    @classmethod
    def create(cls, registry: CollectorRegistry) -> ShardMetrics:
        return cls(
            partial_queries=Counter(
                "swarmrec_shard_partial_queries",
                "Partial queries served by this index shard",
                registry=registry,
            ),
            stored_descriptors=Gauge(
                "swarmrec_shard_stored_descriptors",
                "Partial descriptors held by this index shard (every group it owns or copies)",
                registry=registry,
            ),
            group_queries=Counter(
                "swarmrec_shard_group_queries",
                "Robots' partial queries served by this index shard, by label group (the rebalancing "
                "load; a client's lookups are not in it)",
                ["group"],
                registry=registry,
            ),
            placement_version=Gauge(
                "swarmrec_shard_placement_version",
                "Version of the placement this shard follows",
                registry=registry,
            ),
            groups=Gauge(
                "swarmrec_shard_groups",
                "Label groups this shard owns or is copying",
                ["role"],
                registry=registry,
            ),
            refused=Counter(
                "swarmrec_shard_refused",
                "Requests refused because the sender routed with another placement (stale) or before "
                "the shard's placement was confirmed (unconfirmed), or for a group it does not hold",
                ["reason"],
                registry=registry,
            ),
            handoff_records=Counter(
                "swarmrec_shard_handoff_records",
                "Partial descriptors copied into this shard from another one (handoffs)",
                registry=registry,
            ),
            placements_published=Counter(
                "swarmrec_shard_placements_published",
                "Placements this shard published as the coordinator, by why (members: a shard came, "
                "went or drains; rebalance: the observed load; handoff_done: the learners own)",
                ["reason"],
                registry=registry,
            ),
        )


@dataclass
class VerifierMetrics(MetricSet):
    title: ClassVar[str] = "verifier"

    stored_frames: Gauge

    @classmethod
    def create(cls, registry: CollectorRegistry) -> VerifierMetrics:
        return cls(
            stored_frames=Gauge(
                "swarmrec_verifier_stored_frames", "Constellations held by this verifier", registry=registry
            )
        )


#: What a descriptor made of a frame: queried it, had too few objects to query, or its
#: own verifier did not store it (the frame was refused).
DESCRIPTOR_FRAME_OUTCOMES = ("queried", "too_few_objects", "not_stored")


@dataclass
class DescriptorMetrics(MetricSet):
    title: ClassVar[str] = "descriptor"

    loop_closures: Counter
    query_seconds: Histogram
    pending_stores: Gauge
    store_retries: Counter
    placement_refreshes: Counter
    frames: Counter
    funnel: Counter

    @classmethod
    def create(cls, registry: CollectorRegistry) -> DescriptorMetrics:
        metrics = cls(
            pending_stores=Gauge(
                "swarmrec_descriptor_pending_stores",
                "Descriptor slices not yet acknowledged by every shard that must hold them (kept on disk)",
                registry=registry,
            ),
            store_retries=Counter(
                "swarmrec_descriptor_store_retries",
                "Stores sent again to a shard that had not acknowledged them",
                registry=registry,
            ),
            placement_refreshes=Counter(
                "swarmrec_descriptor_placement_refreshes",
                "Times this descriptor fetched the index placement again (a shard said it was stale)",
                registry=registry,
            ),
            loop_closures=Counter(
                "swarmrec_loop_closures", "Loop closures found by this robot", registry=registry
            ),
            query_seconds=Histogram(
                "swarmrec_query_duration_seconds",
                "Time of one two-step query, frame in to last verifier reply",
                buckets=LATENCY_BUCKETS,
                registry=registry,
            ),
            frames=Counter(
                "swarmrec_descriptor_frames",
                "Frames this robot's descriptor processed, by outcome (queried, too_few_objects, not_stored)",
                ("outcome",),
                registry=registry,
            ),
            funnel=Counter(
                "swarmrec_funnel_candidates",
                "Candidates of this robot's queries, by the loop-closure funnel stage and reason they "
                "stopped at (accepted: the loop closures)",
                ("stage", "reason"),
                registry=registry,
            ),
        )
        # Every label value exists from the start (at 0), so a rate over a run sees each one;
        # the values are the enums', a fixed set.
        for outcome in DESCRIPTOR_FRAME_OUTCOMES:
            metrics.frames.labels(outcome)
        for reason in Reason:
            if reason not in (Reason.UNSPECIFIED, Reason.BELOW_SHARD_CUT, Reason.MATCHED):
                metrics.funnel.labels(reason.stage.label, reason.label)
        return metrics


@dataclass
class PlaceOwnerMetrics(MetricSet):
    title: ClassVar[str] = "place-owner"

    owner_queries: Counter
    cluster_queries: Counter
    stored_descriptors: Gauge
    snapshots: Counter
    loop_closures: Counter
    query_seconds: Histogram
    table_version: Gauge
    tables_adopted: Counter
    moved: Counter
    copies_stored: Counter
    copies_failed: Counter
    rerouted: Counter

    @classmethod
    def create(cls, registry: CollectorRegistry) -> PlaceOwnerMetrics:
        return cls(
            owner_queries=Counter(
                "swarmrec_place_owner_queries",
                "Queries this robot answered as the owner of their cluster (its load), its own included",
                registry=registry,
            ),
            cluster_queries=Counter(
                "swarmrec_place_owner_cluster_queries",
                "Queries this owner answered, by cluster",
                ["cluster"],
                registry=registry,
            ),
            stored_descriptors=Gauge(
                "swarmrec_place_owner_stored_descriptors",
                "Descriptors this owner holds (every robot's frames routed to its clusters)",
                registry=registry,
            ),
            snapshots=Counter(
                "swarmrec_place_owner_snapshots",
                "Times this owner saved its faiss index to its data folder",
                registry=registry,
            ),
            loop_closures=Counter(
                "swarmrec_loop_closures", "Loop closures found by this robot", registry=registry
            ),
            query_seconds=Histogram(
                "swarmrec_place_query_duration_seconds",
                "Time of one full-image query of this robot's, frame in to the verifier's reply",
                buckets=LATENCY_BUCKETS,
                registry=registry,
            ),
            table_version=Gauge(
                "swarmrec_place_owner_table_version",
                "Version of the cluster table this owner routes and owns by (0: the settings')",
                registry=registry,
            ),
            tables_adopted=Counter(
                "swarmrec_place_owner_tables_adopted",
                "Cluster tables this owner adopted after a re-balancing",
                registry=registry,
            ),
            moved=Counter(
                "swarmrec_place_owner_moved_descriptors",
                "Stored descriptors moved by new tables: sent to their new holders, received, removed here",
                ["direction"],
                registry=registry,
            ),
            copies_stored=Counter(
                "swarmrec_place_owner_copies_stored",
                "Queries of other cells stored here as boundary copies (never searched for their querier)",
                registry=registry,
            ),
            copies_failed=Counter(
                "swarmrec_place_owner_copies_failed",
                "Boundary copies of this robot's queries that their holder did not store",
                registry=registry,
            ),
            rerouted=Counter(
                "swarmrec_place_owner_rerouted_queries",
                "This robot's queries sent again: refused for their table's version, or unanswered",
                registry=registry,
            ),
        )


@dataclass
class FusionMetrics(MetricSet):
    title: ClassVar[str] = "fusion"

    rounds: Counter
    incorporated: Counter
    duplicates: Counter
    rejected: Counter
    early: Counter

    @classmethod
    def create(cls, registry: CollectorRegistry) -> FusionMetrics:
        return cls(
            rounds=Counter("swarmrec_fusion_rounds", "Fusion rounds this robot started", registry=registry),
            incorporated=Counter(
                "swarmrec_fusion_incorporated",
                "Other robots' classifier outputs folded into this robot's posterior",
                registry=registry,
            ),
            duplicates=Counter(
                "swarmrec_fusion_duplicates",
                "Flooded copies of an already-heard origin, ignored (Algorithm 1 line 11)",
                registry=registry,
            ),
            rejected=Counter(
                "swarmrec_fusion_rejected",
                "Flooded messages that decoded but were rejected by the robot, by reason",
                ("reason",),
                registry=registry,
            ),
            early=Counter(
                "swarmrec_fusion_early_messages",
                "Flooded messages that arrived before this robot started their round, kept for it",
                registry=registry,
            ),
        )


@dataclass
class DetectorMetrics(MetricSet):
    title: ClassVar[str] = "detector"

    frames: Counter
    boxes_dropped: Counter
    objects: Counter
    stage_seconds: Histogram

    @classmethod
    def create(cls, registry: CollectorRegistry) -> DetectorMetrics:
        return cls(
            frames=Counter(
                "swarmrec_detector_frames",
                "RGB-D frames the detector handled, by outcome (detected, no_objects, or why it skipped)",
                ("outcome",),
                registry=registry,
            ),
            boxes_dropped=Counter(
                "swarmrec_detector_boxes_dropped",
                "Detected boxes left out of the constellation, by reason (no_depth: no valid depth pixel)",
                ("reason",),
                registry=registry,
            ),
            objects=Counter(
                "swarmrec_detector_objects",
                "Objects in the constellations the detector made",
                registry=registry,
            ),
            stage_seconds=Histogram(
                "swarmrec_detector_stage_seconds",
                "Time of one frame in each detector stage (decode, detect, points; describe: the full-image "
                "descriptor, place_method dvpr)",
                ("stage",),
                buckets=_STAGE_BUCKETS,
                registry=registry,
            ),
        )


@dataclass
class GatewayMetrics(MetricSet):
    title: ClassVar[str] = "gateway"

    calls: Counter
    call_seconds: Histogram
    streams_open: Gauge
    events_sent: Counter

    @classmethod
    def create(cls, registry: CollectorRegistry) -> GatewayMetrics:
        return cls(
            calls=Counter(
                "swarmrec_gateway_calls",
                "gRPC calls answered, by method and gRPC status code",
                ["method", "code"],
                registry=registry,
            ),
            call_seconds=Histogram(
                "swarmrec_gateway_call_seconds",
                "Time to answer a unary gRPC call",
                ["method"],
                buckets=LATENCY_BUCKETS,
                registry=registry,
            ),
            streams_open=Gauge("swarmrec_gateway_streams_open", "Event streams open now", registry=registry),
            events_sent=Counter(
                "swarmrec_gateway_events_sent",
                "Events sent on streams, by stream",
                ["stream"],
                registry=registry,
            ),
        )


@dataclass
class SlamMetrics(MetricSet):
    title: ClassVar[str] = "distributed SLAM"

    steps: Counter
    sent_bytes: Counter
    sent_messages: Counter
    sent_floats: Counter
    rejected: Counter
    solves: Counter
    step_seconds: Histogram

    @classmethod
    def create(cls, registry: CollectorRegistry) -> SlamMetrics:
        return cls(
            steps=Counter(
                "swarmrec_slam_steps",
                "Gauss-Seidel steps this robot took, by stage",
                ("stage",),
                registry=registry,
            ),
            sent_bytes=Counter(
                "swarmrec_slam_sent_bytes",
                "Payload bytes of the SlamStep messages this robot sent, by receiving robot (peer), "
                "stage, and whether they carried separator estimates (estimates) or only the report (report)",
                ("peer", "stage", "carries"),
                registry=registry,
            ),
            sent_messages=Counter(
                "swarmrec_slam_sent_messages",
                "SlamStep messages this robot sent, by peer, stage and carries (one per peer and iteration)",
                ("peer", "stage", "carries"),
                registry=registry,
            ),
            sent_floats=Counter(
                "swarmrec_slam_sent_floats",
                "Separator estimate floats this robot sent (9 per key in the rotation stage, 6 in a pose "
                "stage: the communication model), by peer and stage",
                ("peer", "stage"),
                registry=registry,
            ),
            rejected=Counter(
                "swarmrec_slam_rejected",
                "Team members' messages this robot refused (nothing changed), by reason",
                ("reason",),
                registry=registry,
            ),
            solves=Counter(
                "swarmrec_slam_solves",
                "Solves this robot ended, by outcome (converged, unconverged, aborted, failed)",
                ("outcome",),
                registry=registry,
            ),
            step_seconds=Histogram(
                "swarmrec_slam_step_seconds",
                "Time of one local solve (a Gauss-Seidel step), by stage",
                ("stage",),
                buckets=_STAGE_BUCKETS,
                registry=registry,
            ),
        )
