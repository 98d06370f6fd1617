"""One robot's place database: the descriptors routed to it, searched exactly, saved to disk.

The paper's *add-query*: when a query arrives, its owner searches everything routed to it
so far, answers with the nearest entry (squared L2 distance, robot, frame), then stores the
query, so every place seen is in the database of its cluster's owner for later queries.
:meth:`OwnerIndex.query_then_store` does both under one lock, so two queries arriving at
once each see the other in one order or the other, never half of it.

The search is faiss's exact flat L2 index (``IndexFlatL2``) behind an id map: an owner holds
a share of a mission's frames (thousands, not millions), where exact search costs tens of
microseconds and approximate graphs (HNSW: hnswlib, usearch) only add recall loss and build
cost; faiss also filters by id during the search and serialises the whole index to bytes.

**Own frames are excluded**: a robot's query never returns a frame of the same robot, as in
the paper's evaluation ("matches within the same trajectory are excluded"): a robot closes
its own loops with its own SLAM; the swarm is for the places other robots saw. Ids are
``robot << 40 | frame`` so the exclusion is one id range (``IDSelectorNot(IDSelectorRange)``).

**Persistence**: :meth:`save` writes the serialised faiss index and its format in one
``.npz``, atomically (temporary file, then rename); :meth:`load` restores every entry, so a
restarted owner answers exactly as before. Thread-safety: every public method takes the lock.
"""

from __future__ import annotations

import json
import os
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import faiss
import numpy as np
import numpy.typing as npt

from swarmrec.errors import ConfigError
from swarmrec.vpr.errors import StateFileError
from swarmrec.vpr.vectors import as_descriptor

__all__ = ["INDEX_FORMAT", "MAX_FRAME", "MAX_ROBOT", "Match", "OwnerIndex", "set_faiss_threads"]

INDEX_FORMAT = "swarmrec.vpr.index/1"
_FRAME_BITS = 40
#: Frame numbers fit in 40 bits and robot ids in the 23 bits above them (faiss ids are int64 >= 0).
MAX_FRAME = (1 << _FRAME_BITS) - 1
MAX_ROBOT = (1 << (63 - _FRAME_BITS)) - 1


def set_faiss_threads(threads: int) -> None:
    """faiss's OpenMP threads, for the whole process (faiss has no per-call setting). An owner's
    single-query search over thousands of vectors gains nothing from threads, and OpenMP's
    waiting threads made it 5-20x slower on 2 cores shared with other processes: use 1 there."""
    if threads < 1:
        raise ConfigError(f"threads must be >= 1, got {threads}")
    faiss.omp_set_num_threads(threads)


@dataclass(frozen=True)
class Match:
    """The answer to a query: the nearest stored frame of another robot."""

    distance: float  # squared L2
    robot: int
    frame: int


def _entry_id(robot: int, frame: int) -> int:
    if not (0 <= robot <= MAX_ROBOT and 0 <= frame <= MAX_FRAME):
        raise ConfigError(
            f"robot must be in [0, {MAX_ROBOT}] and frame in [0, {MAX_FRAME}], got {robot}, {frame}"
        )
    return (robot << _FRAME_BITS) | frame


class OwnerIndex:
    """The descriptors routed to one owner (any number of robots' frames), exact L2 search."""

    def __init__(self, dimension: int) -> None:
        if dimension < 1:
            raise ConfigError(f"dimension must be >= 1, got {dimension}")
        self.dimension = dimension
        self._index = faiss.IndexIDMap2(faiss.IndexFlatL2(dimension))
        self._ids: set[int] = set()
        self._lock = threading.Lock()
        # One set of search parameters per querying robot: building faiss's selector objects
        # costs more than searching a few thousand vectors.
        self._params: dict[int, Any] = {}
        # The selectors the parameters point to: SWIG does not keep them alive by itself.
        self._selectors: list[Any] = []

    def __len__(self) -> int:
        with self._lock:
            return int(self._index.ntotal)

    def query_then_store(self, descriptor: npt.NDArray[np.floating], robot: int, frame: int) -> Match | None:
        """Search for the nearest frame of another robot, then store this one (atomically).

        A frame already stored (a query delivered twice) is answered again but not stored twice."""
        x = as_descriptor(descriptor, self.dimension)
        entry = _entry_id(robot, frame)
        with self._lock:
            match = self._search(x, robot)
            self._add(x, entry)
            return match

    def store(self, descriptor: npt.NDArray[np.floating], robot: int, frame: int) -> bool:
        """Store without searching (entries moved from another owner); False if already stored."""
        x = as_descriptor(descriptor, self.dimension)
        entry = _entry_id(robot, frame)
        with self._lock:
            return self._add(x, entry)

    def search(self, descriptor: npt.NDArray[np.floating], robot: int) -> Match | None:
        """The nearest stored frame of a robot other than ``robot``, without storing anything."""
        x = as_descriptor(descriptor, self.dimension)
        _entry_id(robot, 0)
        with self._lock:
            return self._search(x, robot)

    def get(self, robot: int, frame: int) -> npt.NDArray[np.float32] | None:
        """The stored descriptor of ``robot``'s ``frame`` (a copy), or None when none is stored:
        what a service compares a store against (the same content again is accepted, other
        content refused)."""
        entry = _entry_id(robot, frame)
        with self._lock:
            if entry not in self._ids:
                return None
            vector = np.asarray(self._index.reconstruct(entry), np.float32)
        return vector.reshape(self.dimension).copy()

    def _add(self, x: npt.NDArray[np.float32], entry: int) -> bool:
        if entry in self._ids:
            return False
        self._index.add_with_ids(x[None], np.array([entry], np.int64))
        self._ids.add(entry)
        return True

    def _search(self, x: npt.NDArray[np.float32], robot: int) -> Match | None:
        if self._index.ntotal == 0:
            return None
        params = self._params.get(robot)
        if params is None:
            own = faiss.IDSelectorRange(robot << _FRAME_BITS, (robot + 1) << _FRAME_BITS)
            # faiss's stubs list no constructor arguments; the selector is set as an attribute.
            params = faiss.SearchParameters()
            params.sel = faiss.IDSelectorNot(own)
            self._selectors += [own, params.sel]
            self._params[robot] = params
        distances, ids = self._index.search(x[None], 1, params=params)
        found = int(ids[0, 0])
        if found < 0:  # every stored frame is the querier's own
            return None
        return Match(float(distances[0, 0]), found >> _FRAME_BITS, found & MAX_FRAME)

    def export(self) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], npt.NDArray[np.float32]]:
        """Robots, frames and descriptors of every stored entry, in storage order: what an owner
        hands over when a cluster moves to another robot (with :meth:`remove` after)."""
        with self._lock:
            ids = faiss.vector_to_array(self._index.id_map).astype(np.int64)
            vectors = self._index.index.reconstruct_n(0, self._index.ntotal)
        return (
            ids >> _FRAME_BITS,
            ids & MAX_FRAME,
            np.asarray(vectors, np.float32).reshape(-1, self.dimension),
        )

    def remove(self, robots: npt.ArrayLike, frames: npt.ArrayLike) -> int:
        """Forget these entries (robot and frame pairs); returns how many were stored."""
        entries = [_entry_id(int(r), int(f)) for r, f in zip(np.ravel(robots), np.ravel(frames), strict=True)]
        with self._lock:
            present = [e for e in entries if e in self._ids]
            if present:
                # The numpy wrapper takes an id array; faiss's stubs give the C++ IDSelector signature.
                self._index.remove_ids(np.array(present, np.int64))  # type: ignore[arg-type]
                self._ids.difference_update(present)
            return len(present)

    def save(self, path: str | Path) -> None:
        """Write the whole index to ``path`` (``.npz``), atomically."""
        path = Path(path)
        with self._lock:
            blob = faiss.serialize_index(self._index)
        meta = json.dumps({"format": INDEX_FORMAT, "dimension": self.dimension})
        tmp = path.with_name(path.name + ".tmp.npz")
        np.savez(tmp, index=np.asarray(blob, np.uint8), meta=np.array(meta))
        os.replace(tmp, path)

    @classmethod
    def load(cls, path: str | Path) -> OwnerIndex:
        """An index written by :meth:`save`, or :class:`StateFileError` saying what is wrong."""
        try:
            with np.load(path, allow_pickle=False) as data:
                meta = json.loads(str(data["meta"]))
                blob = np.asarray(data["index"], np.uint8)
        except (OSError, KeyError, ValueError) as exc:
            raise StateFileError(path, f"not a saved owner index: {exc}") from exc
        if not isinstance(meta, dict) or meta.get("format") != INDEX_FORMAT:
            raise StateFileError(path, f"not a saved owner index (expected format {INDEX_FORMAT!r})")
        dimension = int(meta.get("dimension", -1))
        try:
            inner = faiss.deserialize_index(blob)
        # faiss raises RuntimeError for a truncated or corrupt blob.
        except RuntimeError as exc:
            raise StateFileError(path, f"the faiss index does not load: {exc}") from exc
        if inner.d != dimension or not isinstance(inner, faiss.IndexIDMap2):
            raise StateFileError(
                path,
                f"index of dimension {inner.d} and type {type(inner).__name__}, "
                f"expected an id-mapped index of dimension {dimension}",
            )
        index = cls(dimension)
        index._index = inner
        index._ids = {int(i) for i in faiss.vector_to_array(inner.id_map)}
        return index
