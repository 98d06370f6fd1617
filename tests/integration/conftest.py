"""Fixtures for tests with a real zenoh router and real service processes.

Every swarm gets its own name (so keys never collide) and its own router on a
free loopback port; processes are stopped SIGTERM -> wait -> SIGKILL when the
test ends, and their logs are kept in the test's tmp dir. :func:`running_swarm`
is the one way the integration tests start a local swarm (module-scoped
fixtures use it directly; :func:`local_swarm` is the per-test router).
"""

from __future__ import annotations

import hashlib
import re
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import pytest

from swarmrec.client import ZenohClient
from swarmrec.deployments.base import SwarmSpec
from swarmrec.deployments.identities import Security
from swarmrec.deployments.local import LocalDeployment
from swarmrec.runtime.settings import BusSettings, Component
from swarmrec.services.registry import WORKLOADS
from swarmrec.services.settings import IndexSettings, PlaceSettings


def swarm_name(request: pytest.FixtureRequest) -> str:
    """A swarm name unique to the test, short enough for certificate common names
    (``r<robot>.<kind>.<swarm>`` fits X.509's 64 characters)."""
    name = re.sub(r"[^A-Za-z0-9_-]", "-", request.node.name)
    if len(name) <= 32:
        return name
    return f"{name[:24]}-{hashlib.sha1(name.encode()).hexdigest()[:7]}"


@contextmanager
def running_swarm(
    tmp: Path,
    swarm: str,
    *components: Component,
    robots: int = 2,
    kinds: Sequence[str] = WORKLOADS["places"],
    request_timeout_s: float = 2.0,
    start: bool = True,
    timeout_s: float = 90.0,
    swarm_kinds: Sequence[str] = ("gateway",),
    hosting: str = "service",
    security: Security = "mtls",
    **bus: object,
) -> Iterator[LocalDeployment]:
    """A local swarm of ``robots`` robots running ``kinds`` with ``components``; with
    ``start`` False only its router runs (the test starts what it needs)."""
    settings = BusSettings(swarm=swarm, n_robots=robots, request_timeout_s=request_timeout_s, **bus)  # type: ignore[arg-type]
    spec = SwarmSpec(settings, tuple(kinds), components, swarm_kinds=tuple(swarm_kinds))
    deployment = LocalDeployment(
        data_dir=tmp / "data", log_dir=tmp / "logs", hosting=hosting, security=security
    )
    try:
        if start:
            deployment.start(spec, timeout_s=timeout_s)
            deployment.wait_ready(timeout_s)
        else:
            deployment.start_router(spec)
        yield deployment
    finally:
        deployment.stop()


@contextmanager
def index_shards(tmp: Path, swarm: str, *, shards: int, n_labels: int) -> Iterator[LocalDeployment]:
    """``shards`` index shards alone (no other service, no gateway), quick to drop a member
    (member grace 0.5 s) and to act (a coordinator tick every 0.2 s)."""
    index = IndexSettings(member_grace_s=0.5, placement_tick_s=0.2)
    with running_swarm(
        tmp,
        swarm,
        PlaceSettings(n_labels=n_labels),
        index,
        robots=shards,
        kinds=["index-shard"],
        swarm_kinds=(),
    ) as deployment:
        yield deployment


@pytest.fixture
def local_swarm(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[LocalDeployment]:
    """A running router of a 2-robot place-recognition swarm (80 labels, lock-step off);
    robots are started by the test (``start_robot``)."""
    with running_swarm(tmp_path, swarm_name(request), start=False) as swarm:
        yield swarm


@pytest.fixture
def client(local_swarm: LocalDeployment) -> Iterator[ZenohClient]:
    with local_swarm.client(2.0) as c:
        yield c
