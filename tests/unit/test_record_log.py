"""The append-only record log: records survive a reopen, a torn last record is
cut off, and a log without a path keeps nothing."""

from __future__ import annotations

import logging
import struct
from pathlib import Path

import pytest

from swarmrec.runtime.storage import RecordLog

RECORDS = [b"first", b"", b"\x00\x01\x02" * 100, bytes(range(256))]


def written(path: Path, records: list[bytes], *, fsync: bool = False) -> None:
    log = RecordLog(path, fsync=fsync)
    for r in records:
        log.append(r)
    log.close()


def read_back(path: Path) -> list[bytes]:
    """The records of a freshly reopened log (closed again: it holds an open file)."""
    log = RecordLog(path)
    try:
        return list(log.records())
    finally:
        log.close()


def framed(record: bytes) -> bytes:
    """A record as the file holds it, built here by hand: 4-byte little-endian length, then bytes."""
    return struct.pack("<I", len(record)) + record


@pytest.mark.parametrize("fsync", [False, True])
def test_appended_records_read_back_in_order_after_a_reopen(tmp_path: Path, fsync: bool) -> None:
    path = tmp_path / "store.log"
    written(path, RECORDS, fsync=fsync)
    log = RecordLog(path)
    assert list(log.records()) == RECORDS
    assert log.truncated_bytes == 0
    log.close()


def test_the_file_holds_each_record_behind_its_little_endian_length(tmp_path: Path) -> None:
    path = tmp_path / "store.log"
    written(path, [b"ab", b"cde"])
    assert path.read_bytes() == b"\x02\x00\x00\x00ab\x03\x00\x00\x00cde"


def test_an_appended_record_is_readable_before_the_log_is_closed(tmp_path: Path) -> None:
    log = RecordLog(tmp_path / "store.log")
    log.append(b"one")
    log.append(b"two")
    assert list(log.records()) == [b"one", b"two"]
    assert read_back(tmp_path / "store.log") == [b"one", b"two"]
    log.close()


def test_appends_after_a_reopen_follow_the_earlier_records(tmp_path: Path) -> None:
    path = tmp_path / "store.log"
    written(path, RECORDS[:2])
    written(path, RECORDS[2:])
    assert read_back(path) == RECORDS


@pytest.mark.parametrize(
    "torn",
    [
        b"\x05\x00",  # half a header
        b"\x05\x00\x00\x00ab",  # a header promising 5 bytes, then 2
        b"\x05\x00\x00\x00",  # a header and no body
        b"\xff\xff\xff\xff" + b"x" * 64,  # a length past the 16 MiB record limit: garbage
    ],
)
def test_a_torn_last_record_is_cut_off_and_later_appends_are_readable(tmp_path: Path, torn: bytes) -> None:
    path = tmp_path / "store.log"
    whole = b"".join(framed(r) for r in RECORDS)
    path.write_bytes(whole + torn)

    log = RecordLog(path)
    assert log.truncated_bytes == len(torn)
    assert path.stat().st_size == len(whole)
    assert list(log.records()) == RECORDS
    log.append(b"after the crash")
    log.close()

    reopened = RecordLog(path)
    assert reopened.truncated_bytes == 0
    assert list(reopened.records()) == [*RECORDS, b"after the crash"]
    reopened.close()


def test_cutting_a_torn_record_is_logged(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "store.log"
    path.write_bytes(framed(b"whole") + b"\x09\x00\x00\x00abc")
    with caplog.at_level(logging.WARNING, logger="test.storage"):
        RecordLog(path, log=logging.getLogger("test.storage")).close()
    assert [r.getMessage() for r in caplog.records] == ["cut a truncated record off the log"]
    assert caplog.records[0].__dict__["fields"] == {"path": str(path), "bytes": 7}


def test_a_log_of_whole_records_is_not_rewritten(tmp_path: Path) -> None:
    path = tmp_path / "store.log"
    content = framed(b"one") + framed(b"two")
    path.write_bytes(content)
    RecordLog(path).close()
    assert path.read_bytes() == content


def test_a_log_without_a_path_keeps_nothing() -> None:
    log = RecordLog(None)
    log.append(b"lost")
    assert log.path is None
    assert list(log.records()) == []
    log.close()


def test_a_log_creates_its_folder(tmp_path: Path) -> None:
    path = tmp_path / "data" / "robot3" / "store.log"
    written(path, [b"x"])
    assert read_back(path) == [b"x"]


def test_a_new_log_has_no_records(tmp_path: Path) -> None:
    log = RecordLog(tmp_path / "store.log")
    assert list(log.records()) == []
    assert log.truncated_bytes == 0
    log.close()
