"""A new service kind is one class plus one registry entry: here a package outside
swarmrec declares both (an entry point in the group ``swarmrec.services``), a local
deployment starts two of it as real processes over a real router, the client lists
them by kind, and their endpoint answers."""

from __future__ import annotations

import os
import textwrap
from collections.abc import Iterator
from pathlib import Path

import pytest

from swarmrec.services import registry
from swarmrec.wire import messages as pb
from tests.integration.conftest import running_swarm, swarm_name
from tests.integration.support import endpoint_key, reply_of
from tests.integration.support import request as send

SERVICE = '''
"""A service another package brings: it answers a step with the robot's id."""

from swarmrec.runtime import Endpoint, RequestContext, ServiceBase, ServiceContext
from swarmrec.services.registry import ServiceSpec
from swarmrec.wire import messages as pb


class Echo(ServiceBase):
    def __init__(self, ctx: ServiceContext) -> None:
        self.robot = ctx.bus.robot

    def echo(self, req: pb.StepRequest, _ctx: RequestContext) -> pb.StepReply:
        return pb.StepReply(robot_id=self.robot, step=req.step, finished=True)

    ENDPOINTS = (Endpoint("echo", pb.StepRequest, pb.StepReply, echo, "the step, back"),)


# Clients may call its endpoint: the router's access control grants what the spec names.
SPEC = ServiceSpec(
    "echo", 100, "echo_service:Echo", "answers a step with its robot's id", client_endpoints=("echo",)
)
'''


@pytest.fixture
def echo_plugin(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """An installed-looking package with the service and its entry point, on the path of
    this process and of the processes it starts."""
    site = tmp_path / "site"
    (site / "echo_service-1.0.dist-info").mkdir(parents=True)
    (site / "echo_service.py").write_text(textwrap.dedent(SERVICE))
    (site / "echo_service-1.0.dist-info" / "METADATA").write_text(
        "Metadata-Version: 2.1\nName: echo-service\nVersion: 1.0\n"
    )
    (site / "echo_service-1.0.dist-info" / "entry_points.txt").write_text(
        "[swarmrec.services]\necho = echo_service:SPEC\n"
    )
    monkeypatch.syspath_prepend(str(site))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(site), os.environ.get("PYTHONPATH")])))
    try:
        yield site
    finally:
        registry.REGISTRY.pop("echo", None)


def test_a_service_added_by_another_package_runs_in_a_local_swarm_and_the_client_lists_it(
    echo_plugin: Path, tmp_path: Path, request: pytest.FixtureRequest
) -> None:
    assert registry.load_plugins() == ["echo"]
    assert registry.spec("echo").wire == 100
    with running_swarm(tmp_path, swarm_name(request), kinds=["echo"]) as swarm:
        with swarm.client(5.0) as client:
            members = {(m.kind, m.robot) for m in client.members()}
            assert {("echo", 0), ("echo", 1), ("router", 0), ("gateway", 0)} == members
            reply = reply_of(
                send(client.session, endpoint_key(swarm, "echo", 1, "echo"), pb.StepRequest(step=7)),
                pb.StepReply,
            )
            assert (reply.robot_id, reply.step, reply.finished) == (1, 7, True)
        codes = swarm.stop()
    assert all(code == 0 for code in codes.values()), codes
