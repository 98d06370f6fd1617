"""A 4-robot swarm of containers (docker compose), driven from the host.

One swarm for the module, mutual TLS on every zenoh link (the default): it
replays 800 frames of the synthetic world in lock-step, the job driving it as
the operator through the router's published loopback port; the host's client
checks go through the gRPC gateway's port only. Its loop closures
must be those of the local process swarm on the same input, its Prometheus
must scrape every service, and ``compose down`` must leave nothing behind.
The last test takes the swarm down, so the tests run in file order.
"""

from __future__ import annotations

import csv
import json
import os
import re
import subprocess
import sys
import time
import urllib.parse
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import docker
import pytest

from swarmrec.deployments.compose import ComposeDeployment, SwarmFile, down
from swarmrec.deployments.local import LocalDeployment
from swarmrec.deployments.metrics import scrape_prometheus
from swarmrec.evaluation.source import DatasetSource
from swarmrec.experiments.places import PlacesSettings, main
from tests.e2e.conftest import project_leftovers, run_attached, start_swarm

ROBOTS, FRAMES = 4, 800
KINDS = ("detector", "descriptor", "index-shard", "verifier")


@pytest.fixture(scope="module")
def swarm(engine: docker.DockerClient, tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    tmp = tmp_path_factory.mktemp("compose-swarm")
    info = start_swarm(tmp / "compose", f"swarmrec-e2e-swarm-{os.getpid()}", ROBOTS, FRAMES)
    try:
        summary = run_attached(tmp / "compose", tmp / "attached")
        yield {"info": info, "summary": summary, "tmp": tmp}
    finally:
        down(info)


def _closures(folder: Path) -> list[dict[str, str]]:
    with (folder / "loop_closures.csv").open() as f:
        return list(csv.DictReader(f))


def _prometheus(info: SwarmFile, path: str, **params: str) -> Any:
    url = f"{info.prometheus_url}{path}?{urllib.parse.urlencode(params)}"
    with urllib.request.urlopen(url, timeout=10) as resp:
        body = json.loads(resp.read())
    assert body["status"] == "success", body
    return body["data"]


@pytest.mark.slow
def test_compose_swarm_finds_the_loop_closures_of_the_local_process_swarm(
    swarm: dict[str, Any], tmp_path: Path
) -> None:
    summary = swarm["summary"]
    assert summary.queries.missing_slots == 0
    assert summary.queries.errors == []
    assert summary.offline_check.identical is True
    local = main(
        PlacesSettings(
            source=DatasetSource(frames=FRAMES),
            robots=ROBOTS,
            out=tmp_path / "local",
            swarm="e2e_local",
            progress=False,
            plots=False,
        ),
        LocalDeployment.for_run(tmp_path / "local"),
    )
    assert local.offline_check is not None and local.offline_check.identical is True
    in_containers = _closures(swarm["tmp"] / "attached")
    assert len(in_containers) > 50  # the synthetic world revisits places: a swarm that finds none is broken
    assert in_containers == _closures(tmp_path / "local")
    assert summary.loop_closures.count == local.loop_closures.count == len(in_containers)
    # Same frames, same protocol: the same bytes crossed between robots.
    assert summary.bytes.per_query == pytest.approx(local.bytes.per_query)


@pytest.mark.slow
def test_prometheus_scrapes_every_service_and_sees_bytes_and_shard_load(swarm: dict[str, Any]) -> None:
    info: SwarmFile = swarm["info"]
    # Every service a target, each scraped after now (one scrape that timed out, the swarm's
    # timeout is 1 s, has a few more to answer on this loaded machine): none is down.
    fresh = scrape_prometheus(info.prometheus_url, fresh_after=time.time(), down_grace_s=20.0)
    targets = _prometheus(info, "/api/v1/targets", state="active")["activeTargets"]
    seen = {(t["labels"]["service"], t["labels"]["robot"]) for t in targets}
    expected = {("router", "0"), ("gateway", "0")} | {(k, str(r)) for r in range(ROBOTS) for k in KINDS}
    assert seen == expected
    assert fresh.failed == []

    sent = _prometheus(
        info, "/api/v1/query", query='sum by (robot) (swarmrec_message_bytes_sent_total{scope="swarm"})'
    )["result"]
    per_robot = {s["metric"]["robot"]: float(s["value"][1]) for s in sent}
    assert set(per_robot) == {str(r) for r in range(ROBOTS)}
    assert all(v > 0 for v in per_robot.values()), per_robot

    load = _prometheus(
        info, "/api/v1/query", query='swarmrec_shard_partial_queries_total{service="index-shard"}'
    )["result"]
    per_shard = {s["metric"]["robot"]: float(s["value"][1]) for s in load}
    assert set(per_shard) == {str(r) for r in range(ROBOTS)}
    assert all(v > 0 for v in per_shard.values()), per_shard
    # The report read the same counters through Prometheus.
    assert swarm["summary"].shard_load.partial_queries == [int(per_shard[str(r)]) for r in range(ROBOTS)]


@pytest.mark.slow
def test_a_user_on_the_host_lists_the_swarm_with_the_cli_and_opens_prometheus_web_page(
    swarm: dict[str, Any],
) -> None:
    info: SwarmFile = swarm["info"]
    assert info.security == "mtls" and info.gateway_address.startswith("grpc://127.0.0.1:")
    cli = Path(sys.executable).with_name("swarmrec")
    out = subprocess.run(
        [
            str(cli), "members", "--connect", info.gateway_address, "--swarm", info.swarm,
            "--pki-dir", info.pki_dir,
        ],
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    ).stdout  # fmt: skip
    for r in range(ROBOTS):
        for kind in KINDS:
            assert re.search(rf"^{kind}\s+{r}\b", out, re.MULTILINE), (kind, r, out)
    # Through the gateway: the loop closures the job collected over zenoh, and a query.
    deployment = ComposeDeployment(Path(info.compose_file).parent)
    with deployment.gateway_client(10.0) as gw:
        closures = [c for r in range(ROBOTS) for c in gw.loop_closures(r)]
        assert len(closures) == swarm["summary"].loop_closures.count
        assert gw.status().zenoh_security == "mtls"
    with urllib.request.urlopen(f"{info.prometheus_url}/", timeout=10) as resp:
        page = resp.read().decode()
        assert resp.status == 200
    assert "Prometheus" in page


@pytest.mark.slow
def test_containers_are_healthy_unprivileged_and_published_on_loopback_only(
    swarm: dict[str, Any], engine: docker.DockerClient
) -> None:
    info: SwarmFile = swarm["info"]
    containers = engine.containers.list(filters={"label": f"com.docker.compose.project={info.project}"})
    assert len(containers) == 4 * ROBOTS + 3
    published: dict[str, list[str]] = {}
    for c in containers:
        state = c.attrs["State"]
        assert state["Health"]["Status"] == "healthy", c.name
        service = c.labels["com.docker.compose.service"]
        if service != "prometheus":
            assert c.attrs["Config"]["User"] == "swarmrec", c.name
        for bindings in (c.attrs["NetworkSettings"]["Ports"] or {}).values():
            for b in bindings or []:
                published.setdefault(service, []).append(f"{b['HostIp']}:{b['HostPort']}")
    router_port = info.router_endpoint.rsplit(":", 1)[1]
    prometheus_port = info.prometheus_url.rsplit(":", 1)[1]
    gateway_port = info.gateway_address.rsplit(":", 1)[1]
    assert published == {
        "router": [f"127.0.0.1:{router_port}"],
        "gateway": [f"127.0.0.1:{gateway_port}"],
        "prometheus": [f"127.0.0.1:{prometheus_port}"],
    }
    # Each container sees the CA certificate and its own pair only, never ca.key.
    for c in containers:
        mounts = [m for m in c.attrs["Mounts"] if m["Destination"] == "/run/swarmrec/pki"]
        if c.labels["com.docker.compose.service"] == "prometheus":
            assert mounts == []
            continue
        listed = sorted(p.name for p in Path(mounts[0]["Source"]).iterdir())
        assert "ca.key" not in listed and "ca.pem" in listed and len(listed) in (3, 4), listed


@pytest.mark.slow
def test_compose_down_leaves_no_containers_networks_or_volumes(
    swarm: dict[str, Any], engine: docker.DockerClient
) -> None:
    info: SwarmFile = swarm["info"]
    before = project_leftovers(engine, info.project)
    assert len(before["containers"]) == 4 * ROBOTS + 3
    assert len(before["volumes"]) == 3 * ROBOTS + 1  # shard, verifier, descriptor per robot; Prometheus
    down(info)
    assert project_leftovers(engine, info.project) == {"containers": [], "networks": [], "volumes": []}
