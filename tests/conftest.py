"""Shared test fixtures: where the shared data lives, and small builders."""

from __future__ import annotations

import os
import socket
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from swarmrec.core.types import Constellation
from swarmrec.datasets.labels import COCO_NAMES

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("SWARMREC_SHARED_DATA", REPO.parent / "shared" / "data"))
TUM_ZIP = SHARED_DATA / "tum_fr3_long_office_household_constellations.zip"
TUM_GROUNDTRUTH = SHARED_DATA / "tum_fr3_long_office_household_groundtruth.txt"


def label(name: str) -> int:
    return COCO_NAMES.index(name)


@pytest.fixture
def refused_port() -> Iterator[int]:
    """A loopback port where a connection is refused for the whole test: bound by the test
    and never listened on, so no other program can take it meanwhile."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        yield int(s.getsockname()[1])


def make(*objects: tuple[str, float, float, float]) -> Constellation:
    """A constellation from (label name, x, y, z) tuples."""
    if not objects:
        return Constellation.empty()
    return Constellation(np.array([label(o[0]) for o in objects]), np.array([o[1:] for o in objects], float))


@pytest.fixture(scope="session")
def tum_zip() -> Path:
    """The real TUM constellations (../shared/data)."""
    return shared(TUM_ZIP)


def shared(path: Path) -> Path:
    """A file of ../shared/data. Skipped only where ../shared is absent (a user's machine);
    CI always has it, so there the test must run."""
    if not path.exists():
        if os.environ.get("CI"):
            pytest.fail(f"CI must have the shared data at {path}")
        pytest.skip(f"shared data not found at {path}")
    return path


@pytest.fixture(scope="session")
def tum_groundtruth() -> Path:
    """The TUM sequence's motion-capture trajectory (../shared/data)."""
    return shared(TUM_GROUNDTRUTH)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Mark each test by its folder (unit / integration / e2e)."""
    for item in items:
        parts = Path(str(item.fspath)).parts
        for marker in ("unit", "integration", "e2e"):
            if marker in parts:
                item.add_marker(getattr(pytest.mark, marker))


def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """How ``make test``'s workers (pytest-xdist, ``-n 3 --dist loadscope``) share the suite:
    a worker takes a whole module (its module-scoped swarm starts once), and one worker all
    the container tests (one Docker engine builds the images once; one Kubernetes cluster,
    whose two cores hold one test swarm at a time). Other ``--dist`` modes are xdist's own."""
    if config.getvalue("dist") != "loadscope":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class ModulesAndContainers(LoadScopeScheduling):  # type: ignore[misc]
        def _split_scope(self, nodeid: str) -> str:
            path = nodeid.split("::", 1)[0]
            return "tests/e2e" if path.startswith("tests/e2e/") else path

    return ModulesAndContainers(config, log)
