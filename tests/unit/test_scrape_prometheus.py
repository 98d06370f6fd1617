"""Reading the services' counters through Prometheus: /api/v1/targets, then /federate.

A canned HTTP server stands in for the Prometheus API, serving what
Prometheus 2.42 serves (a real Prometheus is scraped in tests/e2e).
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, HTTPServer
from typing import Any
from urllib.parse import parse_qs, urlparse

import pytest

from swarmrec.deployments.metrics import _rfc3339, scrape_prometheus

FEDERATE = """# TYPE swarmrec_message_bytes_sent_total untyped
swarmrec_message_bytes_sent_total{instance="r0-descriptor:9464",job="swarmrec",message="PartialQuery",robot="0",scope="swarm",service="descriptor"} 120 1795265653538
swarmrec_message_bytes_sent_total{instance="r1-descriptor:9464",job="swarmrec",message="PartialQuery",robot="1",scope="swarm",service="descriptor"} 80 1795265653538
# TYPE swarmrec_shard_partial_queries_total untyped
swarmrec_shard_partial_queries_total{instance="r1-index-shard:9464",job="swarmrec",robot="1",service="index-shard"} 7 1795265653538
"""  # noqa: E501


def _target(service: str, robot: str, health: str, last: str) -> dict[str, Any]:
    return {
        "labels": {"job": "swarmrec", "service": service, "robot": robot},
        "health": health,
        "lastScrape": last,
    }


@pytest.fixture
def prometheus() -> Iterator[tuple[str, dict[str, Any]]]:
    state: dict[str, Any] = {"targets": [], "federate_queries": []}

    class Handler(BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            url = urlparse(self.path)
            if url.path == "/api/v1/targets":
                body = json.dumps({"status": "success", "data": {"activeTargets": state["targets"]}}).encode()
            elif url.path == "/federate":
                state["federate_queries"].append(parse_qs(url.query))
                body = FEDERATE.encode()
            else:
                self.send_error(404)
                return
            self.send_response(200)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *_args: object) -> None:
            pass

    server = HTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    yield f"http://127.0.0.1:{server.server_address[1]}", state
    server.shutdown()
    server.server_close()


def test_rfc3339_reads_prometheus_nanosecond_times() -> None:
    assert _rfc3339("2026-11-21T12:00:00.123456789Z") == pytest.approx(1795262400.123456)
    assert _rfc3339("2026-11-21T12:00:00Z") == 1795262400.0


def test_samples_are_grouped_by_service_and_robot_and_down_targets_are_failed(
    prometheus: tuple[str, dict[str, Any]],
) -> None:
    url, state = prometheus
    state["targets"] = [
        _target("descriptor", "0", "up", "2030-01-01T00:00:00.5Z"),
        _target("descriptor", "1", "up", "2030-01-01T00:00:00.5Z"),
        _target("index-shard", "1", "up", "2030-01-01T00:00:00.5Z"),
        _target("verifier", "3", "down", "2001-01-01T00:00:00Z"),  # stale, but down: not waited for
    ]
    result = scrape_prometheus(url, fresh_after=time.time(), timeout_s=5, down_grace_s=0.2)
    assert state["federate_queries"] == [{"match[]": ['{job="swarmrec"}']}]
    assert result.failed == ["verifier-3"]
    assert result.total("swarmrec_message_bytes_sent_total", scope="swarm") == 200
    assert result.per_service("swarmrec_shard_partial_queries_total", "index-shard") == {1: 7}
    # job and instance are Prometheus' own labels, not the service's.
    ((_, labels),) = result.samples[("index-shard", 1)]
    assert labels == ()


def test_waits_for_a_scrape_after_the_given_instant_and_times_out_without_one(
    prometheus: tuple[str, dict[str, Any]],
) -> None:
    url, state = prometheus
    state["targets"] = [_target("descriptor", "0", "up", "2001-01-01T00:00:00Z")]
    t0 = time.monotonic()
    with pytest.raises(TimeoutError, match="has not scraped every target"):
        scrape_prometheus(url, fresh_after=time.time(), timeout_s=1.0)
    assert time.monotonic() - t0 >= 1.0


def test_a_target_down_for_one_scrape_is_waited_for_not_failed(
    prometheus: tuple[str, dict[str, Any]],
) -> None:
    """A scrape that timed out once (a loaded machine) is not a failed service: the target
    gets a few scrapes to answer again, and its figures are then read."""
    url, state = prometheus
    fresh = "2030-01-01T00:00:00.5Z"
    state["targets"] = [_target("descriptor", "0", "up", fresh), _target("index-shard", "1", "down", fresh)]

    def recovers() -> None:
        time.sleep(0.5)
        state["targets"] = [_target("descriptor", "0", "up", fresh), _target("index-shard", "1", "up", fresh)]

    threading.Thread(target=recovers, daemon=True).start()
    t0 = time.monotonic()
    result = scrape_prometheus(url, fresh_after=time.time(), timeout_s=5, down_grace_s=3.0)
    assert result.failed == []
    assert 0.4 < time.monotonic() - t0 < 3.0
    assert result.per_service("swarmrec_shard_partial_queries_total", "index-shard") == {1: 7}
