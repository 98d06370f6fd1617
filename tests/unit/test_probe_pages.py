"""The probe pages of every process's metrics server: ``/ready`` (200 once every hosted service
serves, 503 before and while stopping) and ``/healthz`` (200 while the process answers), which the
Kubernetes manifests probe with ``httpGet`` instead of exec'ing Python."""

from __future__ import annotations

import threading
import urllib.error
import urllib.request
from collections.abc import Iterator
from typing import ClassVar

import pytest
from prometheus_client import CollectorRegistry, Gauge

from swarmrec.runtime.metrics import HEALTH_PATH, READY_PATH, MetricsServer
from swarmrec.runtime.runner import Hosted, ServiceBase, ServiceContext, run_services
from swarmrec.runtime.settings import BusSettings, Config, SecuritySettings
from swarmrec.wire import messages as pb


def get(url: str) -> tuple[int, bytes]:
    """Status and body of a GET (an HTTP error status is an answer here, not an exception)."""
    try:
        with urllib.request.urlopen(url, timeout=5.0) as resp:
            return resp.status, resp.read()
    except urllib.error.HTTPError as e:
        return e.code, e.read()


@pytest.fixture
def server() -> Iterator[MetricsServer]:
    s = MetricsServer("127.0.0.1", 0)
    s.start()
    yield s
    s.close()


def test_ready_answers_503_until_set_and_again_after_cleared(server: MetricsServer) -> None:
    url = server.base_url + READY_PATH
    assert get(url) == (503, b"not ready\n")
    server.set_ready(True)
    assert get(url) == (200, b"ready\n") and server.ready
    assert get(url + "/") == (200, b"ready\n")  # a trailing slash or a query string is the same page
    assert get(url + "?verbose=1") == (200, b"ready\n")
    server.set_ready(False)
    assert get(url) == (503, b"not ready\n") and not server.ready


def test_healthz_answers_200_whether_ready_or_not(server: MetricsServer) -> None:
    assert get(server.base_url + HEALTH_PATH) == (200, b"ok\n")
    server.set_ready(True)
    assert get(server.base_url + HEALTH_PATH) == (200, b"ok\n")


def test_the_metrics_pages_are_served_beside_the_probe_pages(server: MetricsServer) -> None:
    registry = CollectorRegistry()
    Gauge("probe_page_test_value", "a value", registry=registry).set(7)
    server.add("/metrics", registry)
    status, body = get(server.base_url + "/metrics")
    assert status == 200 and b"probe_page_test_value 7.0" in body
    assert get(server.base_url + "/other")[0] == 404


class _Watcher(ServiceBase):
    """A service that reads its own process's /ready while it is built, once it serves and
    when it stops, into the class's ``seen``."""

    seen: ClassVar[list[tuple[str, int]]] = []
    url: ClassVar[list[str]] = []

    def __init__(self, ctx: ServiceContext) -> None:
        self.url.append(ctx.metrics.url.removesuffix("/metrics") + READY_PATH)
        self.seen.append(("building", get(self.url[0])[0]))

    def serving(self, ready: bool) -> None:
        if not ready:
            self.seen.append(("stopping", get(self.url[0])[0]))


def test_the_runner_makes_ready_200_only_between_serving_and_stopping() -> None:
    # An isolated peer session: no endpoints, no scouting, so nothing leaves the process.
    bus = BusSettings(swarm="probe_pages", mode="peer", connect=(), metrics_port=0)
    security = SecuritySettings(security="insecure", insecure_reason="a unit test without a network")
    hosted = Hosted(Config.of(bus, security), "probe-test", pb.ServiceKind.SERVICE_KIND_ROUTER, _Watcher)
    stop = threading.Event()

    def on_ready(_info: pb.MemberInfo) -> None:
        _Watcher.seen.append(("serving", get(_Watcher.url[0])[0]))
        stop.set()

    assert run_services([hosted], stop=stop, on_ready=on_ready) == 0
    assert _Watcher.seen == [("building", 503), ("serving", 200), ("stopping", 503)]
