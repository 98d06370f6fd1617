"""A descriptor's pending stores are retried in passes: each pass reaches every slice that
was waiting when it began, a batch a round, however many wait (a lock-step mesh waits for
one after its links change, docs/mesh.md)."""

from __future__ import annotations

from pathlib import Path

from swarmrec.runtime.storage import RecordLog
from swarmrec.services.pending import PendingStores
from swarmrec.wire import messages as pb


def _slice(frame: int) -> pb.PartialDescriptor:
    return pb.PartialDescriptor(
        robot_id=1, frame_index=frame, label_lo=0, label_hi=10, label_offsets=[2], counts=[1]
    )


def test_a_pass_reaches_every_slice_waiting_when_it_began_a_batch_at_a_time() -> None:
    q = PendingStores(RecordLog(None), capacity=10)
    for f in range(1, 6):
        q.add(_slice(f))
    assert q.next_batch(2) == ([_slice(1), _slice(2)], False)
    q.done(_slice(3))  # acknowledged meanwhile: the pass skips it
    q.add(_slice(6))  # added after the pass began: the next pass's
    assert q.next_batch(2) == ([_slice(4), _slice(5)], True)
    assert q.next_batch(10) == ([_slice(f) for f in (1, 2, 4, 5, 6)], True)


def test_an_empty_queue_ends_a_pass_at_once_and_a_restart_keeps_what_waits(tmp_path: Path) -> None:
    assert PendingStores(RecordLog(None), capacity=4).next_batch(8) == ([], True)
    path = tmp_path / "pending-stores.log"
    log = RecordLog(path)
    q = PendingStores(log, capacity=4)
    q.add(_slice(1))
    q.add(_slice(2))
    q.done(_slice(1))
    log.close()
    reopened = RecordLog(path)
    try:
        assert PendingStores(reopened, capacity=4).next_batch(8) == ([_slice(2)], True)
    finally:
        reopened.close()
