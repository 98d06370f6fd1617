"""When a run stops waiting for its index to settle (ZenohClient.wait_index_settled): at once
when settled, at the timeout when something still moves, and with ``stall_s`` sooner when the
only thing missing is stores owed that no shard acknowledges any more (their shard died as its
group's only owner). The client's state reads are replaced by a scripted sequence: this is the
waiting logic alone; tests/integration/test_robot_failure.py runs it against a real swarm."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator

import pytest

from swarmrec.client import IndexState, ZenohClient
from swarmrec.core.placement import Placement

SETTLED = Placement(version=3, groups=((0, 5), (5, 10)), owners=((0,), (1,)), members=(0, 1), replicas=1)
MOVING = Placement(
    version=4, groups=((0, 5), (5, 10)), owners=((0,), (1,)), members=(0, 1), replicas=1, learners=((1,), ())
)


def client_seeing(states: Iterator[IndexState]) -> ZenohClient:
    client = object.__new__(ZenohClient)  # no session: only index_state is asked
    last: list[IndexState] = []

    def index_state(**_: object) -> IndexState:
        with contextlib.suppress(StopIteration):  # past the end: the last state, from then on
            last[:] = [next(states)]
        return last[0]

    client.index_state = index_state  # type: ignore[method-assign]
    return client


def forever(state: IndexState) -> Iterator[IndexState]:
    while True:
        yield state


def timed(client: ZenohClient, **kwargs: float) -> tuple[IndexState, float]:
    t0 = time.monotonic()
    state = client.wait_index_settled(poll_s=0.01, **kwargs)
    return state, time.monotonic() - t0


def test_a_settled_index_returns_at_once() -> None:
    state, took = timed(client_seeing(forever(IndexState(SETTLED, {0: 3, 1: 3}, 0))), timeout_s=5.0)
    assert state.settled and took < 1.0


def test_stores_owed_to_no_one_who_answers_stop_the_wait_after_the_stall() -> None:
    owed = IndexState(SETTLED, {0: 3}, 140)  # shard 1 gone, its stores still owed
    state, took = timed(client_seeing(forever(owed)), timeout_s=30.0, stall_s=0.3)
    assert not state.settled and state.pending == 140
    assert 0.3 <= took < 5.0
    # Without a stall it waits the whole timeout.
    _, took = timed(client_seeing(forever(owed)), timeout_s=0.6)
    assert took >= 0.6


def test_stores_still_draining_are_waited_for_past_the_stall() -> None:
    # The count goes down by one every poll until none is owed: never stalled, then settled.
    draining = (IndexState(SETTLED, {0: 3, 1: 3}, n) for n in range(60, -1, -1))
    state, _ = timed(client_seeing(draining), timeout_s=30.0, stall_s=0.2)
    assert state.settled and state.pending == 0


@pytest.mark.parametrize(
    "unsettled",
    [
        IndexState(MOVING, {0: 4, 1: 4}, 5),  # a handoff under way
        IndexState(SETTLED, {0: 3, 1: 2}, 5),  # a shard on another version
    ],
    ids=["handoff", "versions differ"],
)
def test_a_placement_still_moving_is_waited_for_until_the_timeout_whatever_the_stall(
    unsettled: IndexState,
) -> None:
    state, took = timed(client_seeing(forever(unsettled)), timeout_s=0.8, stall_s=0.1)
    assert not state.settled and took >= 0.8
