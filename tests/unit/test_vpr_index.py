"""One owner's index: query-then-store, own frames excluded, restart, bad input, threads."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest

from swarmrec.errors import ConfigError
from swarmrec.vpr.errors import DescriptorError, StateFileError
from swarmrec.vpr.index import Match, OwnerIndex


def unit(*values: float) -> np.ndarray:
    v = np.array(values, np.float32)
    return v / np.linalg.norm(v)


def test_a_query_sees_only_what_arrived_before_it_and_is_then_stored() -> None:
    index = OwnerIndex(3)
    assert index.query_then_store(unit(1, 0, 0), robot=0, frame=10) is None  # nothing stored yet
    assert len(index) == 1
    # The second query finds the first: squared distance |(0.6, 0.8, 0) - (1, 0, 0)|^2 = 0.16 + 0.64.
    match = index.query_then_store(unit(0.6, 0.8, 0), robot=1, frame=20)
    assert match is not None and (match.robot, match.frame) == (0, 10)
    assert match.distance == pytest.approx(0.8, abs=1e-6)
    # A third one is nearer to the second than to the first.
    third = index.query_then_store(unit(0, 1, 0), robot=2, frame=30)
    assert third is not None and (third.robot, third.frame) == (1, 20)
    assert third.distance == pytest.approx(0.36 + 0.04, abs=1e-6)


def test_a_robot_never_gets_its_own_frames_back() -> None:
    index = OwnerIndex(2)
    index.query_then_store(unit(1, 0), robot=4, frame=0)
    index.query_then_store(unit(0, 1), robot=5, frame=0)
    # Identical to robot 4's frame, but robot 4 asks: the answer is robot 5's, 2 apart.
    match = index.search(unit(1, 0), robot=4)
    assert match == Match(pytest.approx(2.0, abs=1e-6), 5, 0)  # type: ignore[arg-type]
    only_own = OwnerIndex(2)
    only_own.query_then_store(unit(1, 0), robot=1, frame=0)
    assert only_own.query_then_store(unit(1, 0), robot=1, frame=1) is None


def test_a_query_delivered_twice_is_stored_once() -> None:
    index = OwnerIndex(2)
    index.query_then_store(unit(1, 0), robot=0, frame=1)
    index.query_then_store(unit(1, 0), robot=0, frame=1)
    assert len(index) == 1
    assert index.store(unit(0, 1), robot=0, frame=1) is False


def test_get_gives_back_exactly_what_was_stored_and_none_for_a_frame_never_stored(tmp_path: Path) -> None:
    index = OwnerIndex(3)
    first = np.array([0.6, 0.8, 0.0], np.float32)
    index.query_then_store(first, robot=2, frame=5)
    index.store(unit(0, 0, 1), robot=1, frame=5)
    stored = index.get(2, 5)
    assert stored is not None and stored.dtype == np.float32
    np.testing.assert_array_equal(stored, first)
    assert index.get(2, 6) is None and index.get(0, 5) is None
    index.save(tmp_path / "owner.npz")
    again = OwnerIndex.load(tmp_path / "owner.npz").get(1, 5)
    assert again is not None
    np.testing.assert_array_equal(again, unit(0, 0, 1))


def test_a_restarted_owner_answers_exactly_as_before(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    x = rng.normal(size=(50, 8)).astype(np.float32)
    index = OwnerIndex(8)
    for i, v in enumerate(x):
        index.query_then_store(v, robot=i % 3, frame=i)
    index.save(tmp_path / "owner.npz")
    restored = OwnerIndex.load(tmp_path / "owner.npz")
    assert len(restored) == 50 and restored.dimension == 8
    robots, frames, vectors = restored.export()
    assert frames.tolist() == list(range(50)) and robots.tolist() == [i % 3 for i in range(50)]
    np.testing.assert_array_equal(vectors, x)
    for q in rng.normal(size=(10, 8)).astype(np.float32):
        assert restored.search(q, robot=1) == index.search(q, robot=1)


def test_an_unreadable_index_file_is_refused(tmp_path: Path) -> None:
    (tmp_path / "junk.npz").write_bytes(b"junk")
    with pytest.raises(StateFileError, match="not a saved owner index"):
        OwnerIndex.load(tmp_path / "junk.npz")
    np.savez(tmp_path / "other.npz", index=np.zeros(3, np.uint8), meta=np.array('{"format": "x"}'))
    with pytest.raises(StateFileError, match="expected format"):
        OwnerIndex.load(tmp_path / "other.npz")
    np.savez(tmp_path / "cut.npz", index=np.zeros(3, np.uint8),
             meta=np.array('{"format": "swarmrec.vpr.index/1", "dimension": 4}'))  # fmt: skip
    with pytest.raises(StateFileError, match="does not load"):
        OwnerIndex.load(tmp_path / "cut.npz")


def test_bad_descriptors_and_ids_are_refused() -> None:
    index = OwnerIndex(4)
    with pytest.raises(DescriptorError, match="length 4"):
        index.query_then_store(np.zeros(5, np.float32), robot=0, frame=0)
    with pytest.raises(DescriptorError, match="NaN or inf"):
        index.query_then_store(np.array([0, np.nan, 0, 0], np.float32), robot=0, frame=0)
    with pytest.raises(DescriptorError, match="NaN or inf"):
        index.query_then_store(np.array([1e300, 0, 0, 0]), robot=0, frame=0)  # inf as float32
    with pytest.raises(ConfigError, match="robot must be"):
        index.query_then_store(np.zeros(4, np.float32), robot=-1, frame=0)
    assert len(index) == 0


def test_concurrent_queries_each_store_once_and_each_sees_a_consistent_index() -> None:
    index = OwnerIndex(4)
    rng = np.random.default_rng(1)
    x = rng.normal(size=(400, 4)).astype(np.float32)
    answers: dict[int, Match | None] = {}

    def worker(robot: int) -> None:
        for i in range(robot, 400, 4):
            answers[i] = index.query_then_store(x[i], robot=robot, frame=i)

    threads = [threading.Thread(target=worker, args=(r,)) for r in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(index) == 400
    assert sorted(index.export()[1].tolist()) == list(range(400))
    assert len(answers) == 400
    # Whatever the interleaving, no answer is the querier's own frame, and every answer is a
    # frame that was queried (so stored) by another thread.
    assert all(a is None or (a.robot != i % 4 and a.frame % 4 == a.robot) for i, a in answers.items())


def test_entries_handed_to_another_owner_are_exported_then_removed() -> None:
    index = OwnerIndex(2)
    for frame, v in enumerate([unit(1, 0), unit(0, 1), unit(1, 1)]):
        index.query_then_store(v, robot=frame, frame=frame)
    robots, frames, vectors = index.export()
    np.testing.assert_allclose(vectors[2], unit(1, 1))
    assert index.remove(robots[:2], frames[:2]) == 2
    assert index.remove([0], [0]) == 0  # already gone
    assert index.export()[1].tolist() == [2] and len(index) == 1
    match = index.search(unit(1, 0), robot=9)
    assert match is not None and match.frame == 2
