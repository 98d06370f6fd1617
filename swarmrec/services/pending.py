"""A descriptor's stores that some shard has not acknowledged yet, kept on disk.

A frame's slice must reach every owner and learner of its label group. When one of
them does not acknowledge it (gone, frozen, behind the placement), the slice is
added here before the frame's query is answered, and retried until every shard that
should hold it under the current placement has acknowledged it. The queue is a
record log (``<data_dir>/pending-stores.log``): a ``+`` record adds a slice, a
``-`` record marks it done; a restart replays both, so nothing acknowledged to the
detector is ever lost. It is bounded: when full, the descriptor refuses new frames
(UNAVAILABLE) rather than drop a store.
"""

from __future__ import annotations

import struct
import threading
from collections import deque

from swarmrec.errors import Unavailable
from swarmrec.runtime.storage import RecordLog
from swarmrec.wire import messages as pb

__all__ = ["PendingStores", "SliceKey", "slice_key"]

SliceKey = tuple[int, int, int, int]
_KEY = struct.Struct("<IIII")
_ADD, _DONE = b"+", b"-"


def slice_key(desc: pb.PartialDescriptor) -> SliceKey:
    """(robot, frame, label_lo, label_hi): one slice of one frame."""
    return (desc.robot_id, desc.frame_index, desc.label_lo, desc.label_hi)


class PendingStores:
    """The queue (see the module docstring); thread-safe."""

    def __init__(self, log: RecordLog, capacity: int) -> None:
        self._log = log
        self.capacity = capacity
        self._lock = threading.Lock()
        self._items: dict[SliceKey, pb.PartialDescriptor] = {}
        self._done_since_compaction = 0
        # The pass under way (see next_batch): the keys it has still to reach.
        self._pass: deque[SliceKey] = deque()
        for record in log.records():
            tag, body = record[:1], record[1:]
            if tag == _ADD:
                desc = pb.PartialDescriptor.FromString(body)
                self._items[slice_key(desc)] = desc
            elif tag == _DONE and len(body) == _KEY.size:
                self._items.pop(_KEY.unpack(body), None)
                self._done_since_compaction += 1

    def __len__(self) -> int:
        with self._lock:
            return len(self._items)

    def room(self) -> int:
        """How many slices may still be added."""
        with self._lock:
            return self.capacity - len(self._items)

    def add(self, desc: pb.PartialDescriptor) -> None:
        """Keep ``desc`` until :meth:`done`; on disk when this returns. Unavailable when full."""
        key = slice_key(desc)
        with self._lock:
            if key in self._items:
                return
            if len(self._items) >= self.capacity:
                raise Unavailable(
                    f"{len(self._items)} stores are waiting for shards to acknowledge them "
                    f"(pending_capacity {self.capacity}): refusing new frames until they are"
                )
            self._log.append(_ADD + desc.SerializeToString())
            self._items[key] = desc

    def next_batch(self, limit: int) -> tuple[list[pb.PartialDescriptor], bool]:
        """The next ``limit`` slices of the pass under way, and whether they end it. A pass
        takes every slice that was waiting when it began, oldest first, so a retry that
        sends a batch a round reaches each of them within one pass, however many wait."""
        with self._lock:
            if not self._pass:
                self._pass = deque(self._items)
            batch: list[pb.PartialDescriptor] = []
            while self._pass and len(batch) < limit:
                desc = self._items.get(self._pass.popleft())
                if desc is not None:
                    batch.append(desc)
            while self._pass and self._pass[0] not in self._items:
                self._pass.popleft()
            return batch, not self._pass

    def done(self, desc: pb.PartialDescriptor) -> None:
        """Every shard that must hold ``desc`` has acknowledged it."""
        key = slice_key(desc)
        with self._lock:
            if self._items.pop(key, None) is None:
                return
            self._log.append(_DONE + _KEY.pack(*key))
            self._done_since_compaction += 1
            if self._done_since_compaction > max(1000, 2 * len(self._items)):
                # Rewrite the log with what is still waiting, so it does not grow for ever.
                self._log.rewrite([_ADD + d.SerializeToString() for d in self._items.values()])
                self._done_since_compaction = 0
