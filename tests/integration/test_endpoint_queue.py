"""An endpoint fed from a queue (``dispatch = "queue"``, what a process hosting many robots
uses) holds at most ``ENDPOINT_CAPACITY`` requests for its workers: the next one is
answered UNAVAILABLE at once, and every request it took is still answered.

The real runner hosts a small service whose one endpoint waits on a gate, over a real
zenoh session; a second session sends it requests (two peers, no router: what is tested
is the runner's hand-over, not the routing)."""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from dataclasses import dataclass

import pytest
import zenoh

from swarmrec.runtime import Endpoint, RequestContext, ServiceBase, ServiceContext, keys
from swarmrec.runtime.runner import ENDPOINT_CAPACITY, Hosted, run_services
from swarmrec.runtime.settings import BusSettings, Config, SecuritySettings
from swarmrec.wire import messages as pb
from tests.integration.support import bound_locators, protobuf, wait_until

KEY = keys.endpoint("gated", "gate", 0, "step")


class Gate(ServiceBase):
    """Answers a step once the test opens the gate; counts the requests being served."""

    opened = threading.Event()
    entered = threading.Semaphore(0)

    def __init__(self, ctx: ServiceContext) -> None:
        self.robot = ctx.bus.robot

    def step(self, req: pb.StepRequest, _ctx: RequestContext) -> pb.StepReply:
        Gate.entered.release()
        Gate.opened.wait(timeout=30)
        return pb.StepReply(robot_id=self.robot, step=req.step)

    ENDPOINTS = (Endpoint("step", pb.StepRequest, pb.StepReply, step, "a step, once the gate opens"),)


@dataclass
class Hosting:
    session: zenoh.Session
    stop: threading.Event


@pytest.fixture
def gated() -> Iterator[Hosting]:
    # The test's session listens on a port the OS gives it; the host dials it.
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("peer"))
    conf.insert_json5("listen/endpoints", json.dumps(["tcp/127.0.0.1:0"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("adminspace/enabled", "true")
    stop = threading.Event()
    host: threading.Thread | None = None
    try:
        with zenoh.open(conf) as session:
            bus = BusSettings(
                swarm="gated",
                mode="peer",
                connect=tuple(bound_locators(session)),
                listen=(),
                metrics_port=-1,
                workers=1,
                dispatch="queue",
            )
            config = Config.of(bus, SecuritySettings(security="insecure"))
            host = threading.Thread(
                target=run_services, args=([Hosted(config, "gate", 99, Gate)],), kwargs={"stop": stop}
            )
            Gate.opened.clear()
            host.start()
            liveliness = session.liveliness()
            wait_until(
                lambda: bool(list(liveliness.get(keys.alive("gated", "gate", 0), timeout=1.0))),
                30,
                "the host",
            )
            yield Hosting(session, stop)
    finally:
        Gate.opened.set()
        stop.set()
        if host is not None:
            host.join(timeout=30)


def _send(session: zenoh.Session, step: int) -> zenoh.Handler[zenoh.Reply]:
    payload = pb.StepRequest(step=step).SerializeToString()
    return session.get(KEY, payload=payload, encoding=protobuf("swarmrec.v1.StepRequest"), timeout=30.0)


def test_a_full_endpoint_queue_answers_unavailable_at_once_and_loses_no_request_it_took(
    gated: Hosting,
) -> None:
    first = _send(gated.session, 0)
    assert Gate.entered.acquire(timeout=30), "the one worker never took the first request"
    # The worker is held at the gate: these wait in the queue, which they fill.
    queued = [_send(gated.session, step) for step in range(1, ENDPOINT_CAPACITY + 1)]
    [over] = list(_send(gated.session, ENDPOINT_CAPACITY + 1))
    assert over.err is not None, "a request beyond the queue was taken"
    error = pb.ErrorReply.FromString(over.err.payload.to_bytes())
    assert error.code == pb.ErrorCode.ERROR_CODE_UNAVAILABLE
    assert "requests waiting" in error.message
    Gate.opened.set()
    answered = []
    for pending in [first, *queued]:
        [reply] = list(pending)
        assert reply.ok is not None, reply.err.payload.to_bytes() if reply.err else reply
        answered.append(pb.StepReply.FromString(reply.ok.payload.to_bytes()).step)
    assert answered == list(range(ENDPOINT_CAPACITY + 1))  # every one, in the order sent
