"""Append-only record log: how stateful services keep what they store.

Each record is a 4-byte little-endian length and the record's bytes (a
serialized protobuf message). A service validates a record before appending
it, appends before it answers, and on start replays the log, so a restart
answers exactly as before. A crash in the middle of an append leaves a
truncated last record: it is reported, cut off, and the log goes on from
the last whole record (nothing acknowledged is lost, because the append
happened before the answer).
"""

from __future__ import annotations

import logging
import os
import struct
import threading
from collections.abc import Iterator
from pathlib import Path

__all__ = ["MAX_RECORD_BYTES", "RecordLog"]

_HEADER = struct.Struct("<I")
#: Largest record; max_message_bytes is capped below it (runtime/settings.py).
MAX_RECORD_BYTES = _MAX_RECORD = 1 << 24


class RecordLog:
    """Records appended to one file (or kept nowhere when ``path`` is None)."""

    def __init__(self, path: Path | None, *, fsync: bool = False, log: logging.Logger | None = None) -> None:
        self.path = path
        self.fsync = fsync
        self._lock = threading.Lock()
        self._file = None
        self.truncated_bytes = 0
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            self._repair(log)
            self._file = path.open("ab")

    def _repair(self, log: logging.Logger | None) -> None:
        assert self.path is not None
        if not self.path.exists():
            return
        good = 0
        for end, _record in self._scan():
            good = end
        size = self.path.stat().st_size
        if good < size:
            self.truncated_bytes = size - good
            if log:
                log.warning(
                    "cut a truncated record off the log",
                    extra={"fields": {"path": str(self.path), "bytes": size - good}},
                )
            with self.path.open("r+b") as f:
                f.truncate(good)

    def _scan(self) -> Iterator[tuple[int, bytes]]:
        assert self.path is not None
        with self.path.open("rb") as f:
            pos = 0
            while True:
                head = f.read(_HEADER.size)
                if len(head) < _HEADER.size:
                    return
                (n,) = _HEADER.unpack(head)
                if n > _MAX_RECORD:
                    return
                body = f.read(n)
                if len(body) < n:
                    return
                pos += _HEADER.size + n
                yield pos, body

    def records(self) -> Iterator[bytes]:
        """Every whole record, oldest first."""
        if self.path is None or not self.path.exists():
            return
        for _end, record in self._scan():
            yield record

    def append(self, record: bytes) -> None:
        """Append one record; it is in the file (and fsynced if asked) on return."""
        if len(record) > _MAX_RECORD:
            # The reader would stop at such a record and cut off everything after it.
            raise ValueError(f"record of {len(record)} bytes exceeds the log's limit of {_MAX_RECORD}")
        if self._file is None:
            return
        with self._lock:
            self._file.write(_HEADER.pack(len(record)) + record)
            self._file.flush()
            if self.fsync:
                os.fsync(self._file.fileno())

    def rewrite(self, records: list[bytes]) -> None:
        """Replace every record with ``records`` (compaction): written to a new file, synced,
        then renamed over the log, so a crash leaves the old log or the new one whole."""
        with self._lock:
            if self.path is None:
                return
            tmp = self.path.with_name(self.path.name + ".tmp")
            with tmp.open("wb") as f:
                for record in records:
                    if len(record) > _MAX_RECORD:
                        raise ValueError(f"record of {len(record)} bytes is over {_MAX_RECORD}")
                    f.write(_HEADER.pack(len(record)) + record)
                f.flush()
                os.fsync(f.fileno())
            if self._file is not None:
                self._file.close()
            os.replace(tmp, self.path)
            self._file = self.path.open("ab")

    def close(self) -> None:
        with self._lock:
            if self._file is not None:
                self._file.close()
                self._file = None
