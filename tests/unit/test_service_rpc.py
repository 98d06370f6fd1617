"""Pure helpers of the request layer and the metrics: payload schemas, the
caller's robot id, byte scopes, and summing scraped Prometheus samples."""

from __future__ import annotations

from dataclasses import dataclass

import pytest
import zenoh
from prometheus_client import generate_latest

from swarmrec.deployments.metrics import Scrape, parse_metrics
from swarmrec.experiments.places.report import measured_store_weight
from swarmrec.runtime.metrics import ServiceMetrics, scope_between
from swarmrec.runtime.rpc import caller_robot, encoding_for, schema_of
from swarmrec.services.metrics import ShardMetrics
from swarmrec.wire import messages as pb

# --- schemas and callers --------------------------------------------------------------


def test_schema_of_reads_the_schema_a_payload_is_sent_with() -> None:
    assert schema_of(encoding_for(pb.CandidatesReply())) == "swarmrec.v1.CandidatesReply"
    assert schema_of(zenoh.Encoding.APPLICATION_PROTOBUF.with_schema("swarmrec.v1.ErrorReply")) == (
        "swarmrec.v1.ErrorReply"
    )


def test_schema_of_an_encoding_without_a_schema_is_empty() -> None:
    assert schema_of(zenoh.Encoding.APPLICATION_PROTOBUF) == ""
    assert schema_of(zenoh.Encoding.ZENOH_BYTES) == ""
    assert schema_of(None) == ""


def test_schema_of_keeps_everything_after_the_first_semicolon() -> None:
    assert schema_of(zenoh.Encoding("text/plain;charset=utf-8;x")) == "charset=utf-8;x"


@dataclass
class FakeAttachment:
    raw: bytes

    def to_bytes(self) -> bytes:
        return self.raw


@pytest.mark.parametrize(
    ("raw", "robot"),
    [(b"0", 0), (b"7", 7), (b"4294967295", 4294967295), (b"007", 7)],
)
def test_caller_robot_reads_a_decimal_robot_id(raw: bytes, robot: int) -> None:
    assert caller_robot(FakeAttachment(raw)) == robot  # type: ignore[arg-type]


@pytest.mark.parametrize(
    "raw", [b"", b"-1", b"+3", b" 3", b"3 ", b"3.0", b"robot3", b"12345678901", b"\xd9\xa3"]
)
def test_caller_robot_is_none_for_anything_but_a_short_decimal(raw: bytes) -> None:
    assert caller_robot(FakeAttachment(raw)) is None  # type: ignore[arg-type]


def test_caller_robot_is_none_without_an_attachment() -> None:
    assert caller_robot(None) is None


def test_caller_robot_reads_a_real_zenoh_attachment() -> None:
    assert caller_robot(zenoh.ZBytes(b"12")) == 12


@pytest.mark.parametrize(
    ("own", "other", "scope"),
    [(3, 3, "robot"), (0, 0, "robot"), (3, 4, "swarm"), (0, 1, "swarm"), (None, 3, "client"),
     (3, None, "client"), (None, None, "client")],
)  # fmt: skip
def test_scope_between_tells_robot_swarm_and_client_traffic_apart(
    own: int | None, other: int | None, scope: str
) -> None:
    assert scope_between(own, other) == scope


# --- scraped samples --------------------------------------------------------------------

SENT = "swarmrec_message_bytes_sent_total"


def hand_built() -> Scrape:
    return Scrape(
        samples={
            ("index-shard", 0): {
                (SENT, (("message", "CandidatesReply"), ("scope", "swarm"))): 100.0,
                (SENT, (("message", "CandidatesReply"), ("scope", "robot"))): 10.0,
                ("swarmrec_shard_partial_queries_total", ()): 4.0,
            },
            ("index-shard", 1): {
                (SENT, (("message", "CandidatesReply"), ("scope", "swarm"))): 200.0,
                ("swarmrec_shard_partial_queries_total", ()): 6.0,
            },
            ("descriptor", 1): {
                (SENT, (("message", "PartialQuery"), ("scope", "swarm"))): 30.0,
                (SENT, (("message", "VerifyRequest"), ("scope", "client"))): 1.0,
                ("swarmrec_shard_partial_queries_total", ()): 1000.0,  # not a shard: per_service skips it
            },
        }
    )


def test_total_sums_a_sample_over_every_service_whose_labels_match() -> None:
    s = hand_built()
    assert s.total(SENT) == 341.0
    assert s.total(SENT, scope="swarm") == 330.0
    assert s.total(SENT, scope="swarm", message="CandidatesReply") == 300.0
    assert s.total(SENT, scope="nowhere") == 0.0
    assert s.total("swarmrec_absent_total") == 0.0


def test_by_label_sums_per_value_of_one_label() -> None:
    s = hand_built()
    assert s.by_label(SENT, "message", scope="swarm") == {"CandidatesReply": 300.0, "PartialQuery": 30.0}
    assert s.by_label(SENT, "scope") == {"swarm": 330.0, "robot": 10.0, "client": 1.0}
    assert s.by_label("swarmrec_shard_partial_queries_total", "message") == {}


def test_per_service_sums_per_robot_over_one_kind_of_service() -> None:
    s = hand_built()
    assert s.per_service("swarmrec_shard_partial_queries_total", "index-shard") == {0: 4.0, 1: 6.0}
    assert s.per_service(SENT, "index-shard") == {0: 110.0, 1: 200.0}
    assert s.per_service(SENT, "verifier") == {}


def rendered_metrics() -> str:
    m = ServiceMetrics.create("index-shard", 3, "s")
    m.count_sent("CandidatesReply", "swarm", 39)
    m.count_sent("CandidatesReply", "swarm", 21)
    m.count_sent("CandidatesReply", "robot", 5)
    m.count_received("PartialQuery", "swarm", 29)
    shard = ShardMetrics.create(m.registry)
    shard.partial_queries.inc(2)
    shard.stored_descriptors.set(17)
    m.peer_failures.labels("verify", "timeout").inc()
    m.request_seconds.labels("query").observe(0.0015)
    text: str = generate_latest(m.registry).decode("utf-8")
    return text


def test_a_services_prometheus_page_parses_into_the_samples_the_report_sums() -> None:
    s = Scrape(samples={("index-shard", 3): parse_metrics(rendered_metrics())})
    assert s.total(SENT) == 65.0
    assert s.by_label(SENT, "scope") == {"swarm": 60.0, "robot": 5.0}
    assert s.total("swarmrec_messages_sent_total", scope="swarm") == 2.0
    assert s.total("swarmrec_message_bytes_received_total", message="PartialQuery") == 29.0
    assert s.per_service("swarmrec_shard_partial_queries_total", "index-shard") == {3: 2.0}
    assert s.total("swarmrec_shard_stored_descriptors") == 17.0
    assert s.total("swarmrec_peer_failures_total", endpoint="verify", reason="timeout") == 1.0
    assert s.total("swarmrec_rejected_requests_total") == 0.0  # declared, never counted: no sample
    assert s.total("swarmrec_request_duration_seconds_count", endpoint="query") == 1.0
    assert s.total("swarmrec_request_duration_seconds_bucket", endpoint="query", le="0.002") == 1.0
    assert s.total("swarmrec_request_duration_seconds_bucket", endpoint="query", le="0.001") == 0.0


def test_the_service_info_sample_names_the_process() -> None:
    series = parse_metrics(rendered_metrics())
    info = (("robot", "3"), ("service", "index-shard"), ("swarm", "s"))
    assert series[("swarmrec_service_info", info)] == 1.0


def test_a_shard_exports_shard_metrics_and_nothing_of_fusion() -> None:
    from swarmrec.services.registry import spec

    names = {m.name for m in spec("index-shard").metrics.describe()}  # type: ignore[union-attr]
    assert names == {
        "swarmrec_shard_partial_queries_total",
        "swarmrec_shard_stored_descriptors",
        "swarmrec_shard_group_queries_total",
        "swarmrec_shard_placement_version",
        "swarmrec_shard_groups",
        "swarmrec_shard_refused_total",
        "swarmrec_shard_handoff_records_total",
        "swarmrec_shard_placements_published_total",
    }
    every = {m.name for m in ServiceMetrics.describe()}
    assert not any("fusion" in n or "detector" in n for n in every | names)


def test_parse_metrics_keys_labels_sorted_by_name() -> None:
    text = '# TYPE x counter\nx_total{z="1",a="2"} 3\n'
    assert parse_metrics(text) == {("x_total", (("a", "2"), ("z", "1"))): 3.0}


def test_parse_metrics_of_an_empty_page_is_empty() -> None:
    assert parse_metrics("") == {}


def test_the_reports_store_weight_is_the_shards_cpu_a_store_over_a_query() -> None:
    def series(endpoint: str, n: float, cpu: float) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
        lab = (("endpoint", endpoint),)
        return {
            ("swarmrec_request_duration_seconds_count", lab): n,
            ("swarmrec_request_cpu_seconds_total", lab): cpu,
        }

    s = Scrape(
        samples={
            # Shard 0: 100 queries in 0.3 s, 50 stores in 0.05 s; shard 1: 100 and 0.1 s, 150 and 0.15 s.
            ("index-shard", 0): series("query", 100, 0.3) | series("store", 50, 0.05),
            ("index-shard", 1): series("query", 100, 0.1) | series("store", 150, 0.15),
            # A verifier's store endpoint is another thing altogether: left out.
            ("verifier", 0): series("store", 1000, 100.0),
        }
    )
    # Queries: 0.4 s / 200 = 2 ms; stores: 0.2 s / 200 = 1 ms.
    assert measured_store_weight(s) == pytest.approx(0.5)
    assert measured_store_weight(Scrape(samples={("index-shard", 0): series("query", 10, 0.1)})) is None
