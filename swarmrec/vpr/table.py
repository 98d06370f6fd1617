"""The routing table a live swarm shares: its k-means centres and their assignment to robots.

Every member builds it the same way from the same settings (:func:`swarm_table`), so all of
them route a descriptor to the same owner without talking: k = ``n_robots x
clusters_per_robot`` centres read from a centres file (the shipped
``models/descriptor/centres.npz`` by default; :mod:`swarmrec.vpr.centres` trains any k), and
either the paper's seeded random assignment or a table read from JSON
(:class:`~swarmrec.vpr.clusters.Assignment`). :attr:`SwarmTable.digest` fingerprints the
centres, so two members that route differently can be told apart from what they publish.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from swarmrec.errors import ConfigError
from swarmrec.models import DESCRIPTOR_CENTRES, ModelNotFound, shipped_model
from swarmrec.vpr.clusters import Assignment, Router, load_centres, random_assignment
from swarmrec.vpr.errors import StateFileError

__all__ = ["SwarmTable", "centres_digest", "default_centres_path", "swarm_table"]


def default_centres_path() -> Path:
    """The shipped centres (:data:`swarmrec.models.DESCRIPTOR_CENTRES`), or StateFileError."""
    try:
        return shipped_model(DESCRIPTOR_CENTRES)
    except ModelNotFound as e:
        raise StateFileError(e.model, str(e)) from None


def centres_digest(centres: npt.NDArray[np.float32]) -> str:
    """SHA-256 (hex) of the centres as little-endian float32, row-major."""
    return hashlib.sha256(np.ascontiguousarray(centres, "<f4").tobytes()).hexdigest()


@dataclass(frozen=True, eq=False)
class SwarmTable:
    """What routes a swarm's queries: the router (centres and assignment) and where they came from."""

    router: Router
    centres_path: Path
    digest: str

    @property
    def assignment(self) -> Assignment:
        return self.router.assignment


def swarm_table(
    n_robots: int,
    clusters_per_robot: int,
    seed: int,
    *,
    centres: str | Path | None = None,
    assignment: str | Path | None = None,
) -> SwarmTable:
    """The swarm's table (see the module docstring); ``centres`` None or empty: the shipped
    file; ``assignment`` None: the paper's random assignment of ``clusters_per_robot`` each
    with ``seed``. A table of another robot count, or centres of another k, is refused."""
    if n_robots < 1 or clusters_per_robot < 1:
        raise ConfigError(
            f"need n_robots >= 1 and clusters_per_robot >= 1, got {n_robots}, {clusters_per_robot}"
        )
    path = Path(centres) if centres else default_centres_path()
    if assignment:
        table = Assignment.load(assignment)
        if table.n_robots != n_robots:
            raise StateFileError(assignment, f"a table for {table.n_robots} robots, the swarm has {n_robots}")
        k = table.n_clusters
    else:
        k = n_robots * clusters_per_robot
        table = random_assignment(n_robots, clusters_per_robot, seed)
    c = load_centres(path, k)
    return SwarmTable(Router(c, table), path, centres_digest(c))
