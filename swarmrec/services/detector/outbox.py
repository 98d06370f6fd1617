"""A detector's frames its descriptor has not taken yet, kept on disk, in order.

Every frame the detector plays is added here before it is sent, and marked done
once the descriptor has answered for it (its own verifier and the index stores
hold it, or are queued by the descriptor). A frame the descriptor could not take
(unreachable, its verifier frozen, the router restarting) stays and is sent again,
oldest first, until it is taken; the descriptor's stores are idempotent per (robot,
frame), so a frame sent twice is stored once. The queue is a record log
(``<data_dir>/outbox.log``: ``+``/``-`` and the frame index): a restart keeps it.
"""

from __future__ import annotations

import struct
import threading

from swarmrec.errors import Unavailable
from swarmrec.runtime.storage import RecordLog

__all__ = ["Outbox"]

_FRAME = struct.Struct("<I")
_ADD, _DONE = b"+", b"-"


class Outbox:
    """Frame indices waiting for the descriptor, oldest first; thread-safe."""

    def __init__(self, log: RecordLog, capacity: int) -> None:
        self._log = log
        self.capacity = capacity
        self._lock = threading.Lock()
        self._frames: dict[int, None] = {}  # insertion-ordered
        self._done = 0
        for record in log.records():
            if len(record) != 1 + _FRAME.size:
                continue
            (frame,) = _FRAME.unpack(record[1:])
            if record[:1] == _ADD:
                self._frames[frame] = None
            elif record[:1] == _DONE:
                self._frames.pop(frame, None)
                self._done += 1

    def __len__(self) -> int:
        with self._lock:
            return len(self._frames)

    def __contains__(self, frame: int) -> bool:
        with self._lock:
            return frame in self._frames

    def add(self, frame: int) -> None:
        """Keep ``frame`` until :meth:`done` (on disk when this returns); Unavailable when full."""
        with self._lock:
            if frame in self._frames:
                return
            if len(self._frames) >= self.capacity:
                raise Unavailable(
                    f"{len(self._frames)} frames wait for the descriptor (outbox_capacity {self.capacity}): "
                    "refusing new ones until it takes them"
                )
            self._log.append(_ADD + _FRAME.pack(frame))
            self._frames[frame] = None

    def waiting(self) -> list[int]:
        """The frames waiting, oldest first."""
        with self._lock:
            return list(self._frames)

    def done(self, frame: int) -> None:
        with self._lock:
            if frame not in self._frames:
                return
            del self._frames[frame]
            self._log.append(_DONE + _FRAME.pack(frame))
            self._done += 1
            if self._done > max(1000, 2 * len(self._frames)):
                self._log.rewrite([_ADD + _FRAME.pack(f) for f in self._frames])
                self._done = 0
