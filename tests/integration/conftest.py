"""Fixtures for tests with a real zenoh router and real service processes.

Every test gets its own swarm name (so keys never collide) and its own
router on a free loopback port; processes are stopped SIGTERM -> wait ->
SIGKILL when the test ends, and their logs are kept in the test's tmp dir.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import pytest

from swarmrec.client import SwarmClient
from swarmrec.services.config import ServiceSettings
from swarmrec.swarm.processes import LocalSwarm


def swarm_name(request: pytest.FixtureRequest) -> str:
    return re.sub(r"[^A-Za-z0-9_-]", "-", request.node.name)[:60]


@pytest.fixture
def local_swarm(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[LocalSwarm]:
    """A running router; robots are started by the test (``start_robot``).

    Parametrise the base settings with ``@pytest.mark.parametrize`` on
    ``swarm_settings`` or use the default: 2 robots, 80 labels, lock-step off.
    """
    base: ServiceSettings = getattr(request, "param", None) or ServiceSettings(
        swarm=swarm_name(request), n_robots=2, request_timeout_s=2.0
    )
    swarm = LocalSwarm(base, data_dir=tmp_path / "data", log_dir=tmp_path / "logs", dataset="")
    swarm.start_router()
    try:
        yield swarm
    finally:
        swarm.stop()


@pytest.fixture
def client(local_swarm: LocalSwarm) -> Iterator[SwarmClient]:
    with SwarmClient([local_swarm.endpoint], local_swarm.base.swarm, timeout_s=2.0) as c:
        yield c
