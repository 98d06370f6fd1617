"""Calls between services of one robot in one process (``rpc.LocalEndpoints``): they run
in the caller's thread, with the same outcome a call over zenoh would have; calls to
another robot, or to every robot at once, still go over zenoh.

A real zenoh session (a lone peer, no router) carries the calls that are not local;
nothing answers them there, so they end as NoReply, which is what tells the two paths
apart."""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator

import pytest
import zenoh

from swarmrec.errors import ErrorCode, NoReply, RemoteError
from swarmrec.runtime.metrics import ServiceMetrics
from swarmrec.runtime.rpc import Caller, LocalEndpoints
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import decode, encode, error_reply, schema_name

KEY = "swarmrec/v1/t/verifier/3/store"


@pytest.fixture(scope="module")
def session() -> Iterator[zenoh.Session]:
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("peer"))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", "[]")
    with zenoh.open(conf) as s:
        yield s


class Served:
    """An endpoint that records the thread and bytes of each request it serves."""

    def __init__(self, ok: bool = True) -> None:
        self.ok = ok
        self.calls: list[tuple[bytes, str, int | None, str, threading.Thread]] = []

    def __call__(self, data: bytes, schema: str, robot: int | None, key: str) -> tuple[bytes, str, bool]:
        self.calls.append((data, schema, robot, key, threading.current_thread()))
        if not self.ok:
            err = error_reply(ErrorCode.ALREADY_EXISTS, "stored with other content")
            return encode(err), schema_name(err), False
        reply = pb.StoreReply(stored_frames=len(self.calls))
        return encode(reply), schema_name(reply), True


def caller(session: zenoh.Session, robot: int, local: LocalEndpoints) -> Caller:
    return Caller(
        session, robot, timeout_s=0.3, metrics=ServiceMetrics.create("descriptor", robot, "t"), local=local
    )


def test_a_call_to_its_own_robot_runs_in_the_callers_thread_on_the_bytes_it_would_send(
    session: zenoh.Session,
) -> None:
    local, served = LocalEndpoints(), Served()
    local.add(KEY, 3, served)
    request = pb.Constellation(robot_id=3, frame_index=7, labels=[1, 2, 3])
    reply = caller(session, 3, local).call(KEY, request, pb.StoreReply, target_robot=3)
    assert reply.stored_frames == 1
    [(data, schema, robot, key, thread)] = served.calls
    assert decode(data, pb.Constellation) == request
    assert (schema, robot, key) == ("swarmrec.v1.Constellation", 3, KEY)
    assert thread is threading.current_thread()


def test_a_local_endpoints_error_reply_is_the_remote_error_a_zenoh_call_raises(
    session: zenoh.Session,
) -> None:
    local = LocalEndpoints()
    local.add(KEY, 3, Served(ok=False))
    with pytest.raises(RemoteError) as raised:
        caller(session, 3, local).call(KEY, pb.Constellation(robot_id=3), pb.StoreReply, target_robot=3)
    assert raised.value.code == ErrorCode.ALREADY_EXISTS
    assert "other content" in raised.value.message


def test_a_local_reply_of_another_type_is_malformed_as_over_zenoh(session: zenoh.Session) -> None:
    local = LocalEndpoints()
    local.add(KEY, 3, Served())
    with pytest.raises(RemoteError) as raised:
        caller(session, 3, local).call(KEY, pb.Constellation(robot_id=3), pb.VerifyReply, target_robot=3)
    assert raised.value.code == ErrorCode.MALFORMED


def test_a_local_call_is_served_only_when_its_result_is_asked_for(session: zenoh.Session) -> None:
    local, served = LocalEndpoints(), Served()
    local.add(KEY, 3, served)
    pending = caller(session, 3, local).start(KEY, pb.Constellation(robot_id=3), target_robot=3)
    assert served.calls == []  # requests started after it are on their way first
    pending.result(pb.StoreReply)
    pending.result(pb.StoreReply)
    assert len(served.calls) == 1


@pytest.mark.parametrize(
    ("caller_robot", "target", "scatter"),
    [(4, 3, False), (3, 4, False), (3, None, False), (3, 3, True)],
    ids=["another-robots-caller", "another-target", "no-target", "scatter"],
)
def test_calls_between_robots_and_scatters_go_over_zenoh(
    session: zenoh.Session, caller_robot: int, target: int | None, scatter: bool
) -> None:
    local, served = LocalEndpoints(), Served()
    local.add(KEY, 3, served)
    pending = caller(session, caller_robot, local).start(
        KEY, pb.Constellation(robot_id=3), target_robot=target, scatter=scatter
    )
    with pytest.raises(NoReply):
        pending.result(pb.StoreReply)
    assert served.calls == []


def test_a_removed_endpoint_is_not_called_locally(session: zenoh.Session) -> None:
    local, served = LocalEndpoints(), Served()
    local.add(KEY, 3, served)
    local.remove(KEY)
    with pytest.raises(NoReply):
        caller(session, 3, local).call(KEY, pb.Constellation(robot_id=3), pb.StoreReply, target_robot=3)
    assert served.calls == []


def test_local_calls_count_the_bytes_in_the_robots_own_scope(session: zenoh.Session) -> None:
    local = LocalEndpoints()
    local.add(KEY, 3, Served())
    c = caller(session, 3, local)
    request = pb.Constellation(robot_id=3, frame_index=7, labels=[1, 2, 3])
    c.call(KEY, request, pb.StoreReply, target_robot=3)
    assert c.metrics is not None
    sent = c.metrics.bytes_sent.labels("Constellation", "robot")._value.get()
    received = c.metrics.bytes_received.labels("StoreReply", "robot")._value.get()
    assert sent == len(encode(request))
    assert received == len(encode(pb.StoreReply(stored_frames=1)))
