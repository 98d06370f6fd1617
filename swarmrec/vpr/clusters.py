"""Cells of the descriptor space and who owns them: k-means, assignment, routing.

Before deployment, k = ``n_robots x clusters_per_robot`` k-means centres are trained on
descriptors of *other* data than the deployment's; each centre (cluster) is owned by one
robot. A query goes only to the owner of its nearest centre (squared L2; ties go to the
lower cluster index).

k-means is faiss's (``faiss.Kmeans``): the index (:mod:`swarmrec.vpr.index`) and the product
quantiser (:mod:`swarmrec.vpr.quantize`) are faiss too, so one compiled dependency serves all
three, and it trains k = 400 centres on 10^4 descriptors in well under a second on one core
(scikit-learn's KMeans would add a second large dependency for the same result).

The assignment is a table ``owners[cluster] = robot`` (:class:`Assignment`), written as JSON:

.. code-block:: json

    {"format": "swarmrec.vpr.assignment/1", "n_robots": 3, "owners": [2, 0, 1, 1, 0, 2],
     "method": "random", "seed": 7, "version": 0}

``version`` counts the tables a swarm has used (0: its first); a live swarm's queries carry
the version they were routed with, so an owner can tell a sender routing with another table.

The paper's assignment (:func:`random_assignment`) gives every robot exactly c clusters in a
seeded random order; :mod:`swarmrec.vpr.balance` builds others. :class:`Router` is immutable,
so any number of threads may route with one instance.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import faiss
import numpy as np
import numpy.typing as npt

from swarmrec.errors import ConfigError
from swarmrec.vpr.errors import StateFileError
from swarmrec.vpr.vectors import as_descriptor, as_descriptors

__all__ = [
    "ASSIGNMENT_FORMAT",
    "Assignment",
    "Route",
    "Router",
    "load_centres",
    "nearest_centre",
    "random_assignment",
    "save_centres",
    "train_centres",
]

Float32Array = npt.NDArray[np.float32]
IntArray = npt.NDArray[np.int64]

ASSIGNMENT_FORMAT = "swarmrec.vpr.assignment/1"
#: k-means iterations: faiss's default (25) moves no centre noticeably after ~20 here.
KMEANS_ITERATIONS = 25


def train_centres(descriptors: npt.NDArray[np.floating], k: int, seed: int) -> Float32Array:
    """``k`` k-means centres ``(k, d)`` of ``descriptors`` (seeded initialisation)."""
    x = as_descriptors(descriptors, _width(descriptors))
    if not 1 <= k <= len(x):
        raise ConfigError(f"k must be in [1, {len(x)}] (the number of descriptors), got {k}")
    # faiss warns on stderr below 39 points per centre and samples above 256; both fine here.
    kmeans = faiss.Kmeans(
        x.shape[1],
        k,
        niter=KMEANS_ITERATIONS,
        seed=int(seed),
        verbose=False,
        max_points_per_centroid=1 << 20,
        min_points_per_centroid=1,
    )
    kmeans.train(x)
    centres: Float32Array = np.ascontiguousarray(kmeans.centroids, np.float32)
    return centres


def nearest_centre(centres: Float32Array, descriptors: npt.NDArray[np.floating]) -> IntArray:
    """Index of the nearest centre (squared L2) of each descriptor ``(N, d)``; ties: lowest index.

    Computed in float64 from ``|c|^2 - 2 x.c`` (``|x|^2`` is the same for every centre), so the
    answer does not depend on a library's summation order."""
    x = as_descriptors(descriptors, centres.shape[1]).astype(np.float64)
    c = centres.astype(np.float64)
    cost = (c * c).sum(1)[None, :] - 2.0 * (x @ c.T)
    nearest: IntArray = np.argmin(cost, axis=1).astype(np.int64)
    return nearest


@dataclass(frozen=True)
class Assignment:
    """Which robot owns each cluster: ``owners[cluster] = robot`` (robots ``0..n_robots-1``)."""

    owners: tuple[int, ...]
    n_robots: int
    method: str = "given"
    seed: int | None = None
    extra: dict[str, Any] = field(default_factory=dict, compare=False)
    #: Which table of a swarm this is (0: its first; a re-assignment makes the next).
    version: int = 0

    def __post_init__(self) -> None:
        if self.n_robots < 1:
            raise ConfigError(f"n_robots must be >= 1, got {self.n_robots}")
        if not self.owners:
            raise ConfigError("an assignment needs at least one cluster")
        bad = [o for o in self.owners if not (isinstance(o, int) and 0 <= o < self.n_robots)]
        if bad:
            raise ConfigError(f"owners must be robots in [0, {self.n_robots}), got {bad[:5]}")
        if not (isinstance(self.version, int) and 0 <= self.version < 2**63):
            raise ConfigError(f"version must be an integer >= 0, got {self.version!r}")

    @property
    def n_clusters(self) -> int:
        return len(self.owners)

    def owner_array(self) -> IntArray:
        return np.array(self.owners, np.int64)

    def clusters_of(self, robot: int) -> tuple[int, ...]:
        """The clusters ``robot`` owns, ascending."""
        return tuple(i for i, o in enumerate(self.owners) if o == robot)

    def clusters_per_robot(self) -> IntArray:
        counts: IntArray = np.bincount(self.owner_array(), minlength=self.n_robots).astype(np.int64)
        return counts

    def to_json(self) -> dict[str, Any]:
        return {
            "format": ASSIGNMENT_FORMAT,
            "n_robots": self.n_robots,
            "owners": list(self.owners),
            "method": self.method,
            "seed": self.seed,
            "version": self.version,
            **({"extra": self.extra} if self.extra else {}),
        }

    @classmethod
    def from_json(cls, data: object, source: str | Path = "<assignment>") -> Assignment:
        if not isinstance(data, dict) or data.get("format") != ASSIGNMENT_FORMAT:
            raise StateFileError(source, f"not an assignment table (expected format {ASSIGNMENT_FORMAT!r})")
        try:
            return cls(
                owners=tuple(int(o) for o in data["owners"]),
                n_robots=int(data["n_robots"]),
                method=str(data.get("method", "given")),
                seed=None if data.get("seed") is None else int(data["seed"]),
                extra=dict(data.get("extra", {})),
                version=int(data.get("version", 0)),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise StateFileError(source, f"bad assignment table: {exc}") from exc

    def save(self, path: str | Path) -> None:
        _atomic_write(Path(path), json.dumps(self.to_json(), indent=1).encode() + b"\n")

    @classmethod
    def load(cls, path: str | Path) -> Assignment:
        try:
            data = json.loads(Path(path).read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as exc:
            raise StateFileError(path, f"cannot read the assignment: {exc}") from exc
        return cls.from_json(data, path)


def random_assignment(n_robots: int, clusters_per_robot: int, seed: int) -> Assignment:
    """The paper's assignment: exactly ``clusters_per_robot`` clusters per robot, shuffled (seeded)."""
    if n_robots < 1 or clusters_per_robot < 1:
        raise ConfigError(
            f"need n_robots >= 1 and clusters_per_robot >= 1, got {n_robots}, {clusters_per_robot}"
        )
    owners = np.repeat(np.arange(n_robots), clusters_per_robot)
    np.random.default_rng([seed, 0xA551]).shuffle(owners)
    return Assignment(tuple(int(o) for o in owners), n_robots, "random", seed)


@dataclass(frozen=True)
class Route:
    """Where one query goes: its nearest cluster and that cluster's owner."""

    cluster: int
    owner: int


class Router:
    """Routes descriptors to the owner of their nearest centre. Immutable: thread-safe."""

    def __init__(self, centres: npt.NDArray[np.floating], assignment: Assignment) -> None:
        c = as_descriptors(centres, _width(centres))
        if len(c) != assignment.n_clusters:
            raise ConfigError(f"{len(c)} centres but the assignment has {assignment.n_clusters} clusters")
        self._centres = c
        self._centres.setflags(write=False)
        self.assignment = assignment
        self._owners = assignment.owner_array()

    @property
    def centres(self) -> Float32Array:
        return self._centres

    @property
    def dimension(self) -> int:
        return int(self._centres.shape[1])

    def route(self, descriptor: npt.NDArray[np.floating]) -> Route:
        cluster = int(nearest_centre(self._centres, as_descriptor(descriptor, self.dimension)[None])[0])
        return Route(cluster, int(self._owners[cluster]))

    def route_many(self, descriptors: npt.NDArray[np.floating]) -> tuple[IntArray, IntArray]:
        """Clusters and owners of many descriptors ``(N, d)``."""
        clusters = nearest_centre(self._centres, descriptors)
        owners: IntArray = self._owners[clusters]
        return clusters, owners


def save_centres(path: str | Path, centres: dict[int, Float32Array], meta: dict[str, Any]) -> None:
    """Centres for several k in one ``.npz``: array ``k<k>`` is ``(k, d)``, ``meta`` a JSON string
    (what data and seed trained them)."""
    arrays: dict[str, Any] = {f"k{k}": np.asarray(c, np.float32) for k, c in centres.items()}
    for k, c in centres.items():
        if c.shape[0] != k:
            raise ConfigError(f"centres for k={k} have {c.shape[0]} rows")
    arrays["meta"] = np.array(json.dumps(meta))
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez(tmp, **arrays)
    os.replace(tmp, path)


def load_centres(path: str | Path, k: int) -> Float32Array:
    """The ``(k, d)`` centres of a file written by :func:`save_centres`."""
    try:
        with np.load(path, allow_pickle=False) as data:
            if f"k{k}" not in data.files:
                have = sorted(int(n[1:]) for n in data.files if n.startswith("k"))
                raise StateFileError(
                    path,
                    f"no centres for k={k} (it has k in {have}); train them with "
                    f"swarmrec vpr centres --ks {k} --out FILE",
                )
            centres = np.asarray(data[f"k{k}"], np.float32)
    except StateFileError:
        raise
    except (OSError, ValueError) as exc:
        raise StateFileError(path, f"cannot read centres: {exc}") from exc
    return as_descriptors(centres, _width(centres))


def _atomic_write(path: Path, payload: bytes) -> None:
    """Write to a temporary file beside ``path`` and rename it: a crash leaves the old file whole."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(payload)
    os.replace(tmp, path)


def _width(values: object) -> int:
    """The row length of a 2-D array (-1 otherwise, which :func:`as_descriptors` then refuses)."""
    return int(values.shape[1]) if isinstance(values, np.ndarray) and values.ndim == 2 else -1
