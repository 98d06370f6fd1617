"""A new service kind is one class plus one registry entry: here a package outside
swarmrec declares both (an entry point in the group ``swarmrec.services``), a local
deployment starts two of it as real processes over a real router (mutual TLS, the
router's access control computed from the registry), the client lists them by kind,
their endpoint answers, and one calls the other's, which its entry declares; an
endpoint it does not declare is denied by the router, as for a built-in kind."""

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

from swarmrec.errors import NoReply
from swarmrec.runtime import Endpoint, RequestContext, ServiceBase, ServiceContext, keys
from swarmrec.services.registry import Call, ServiceSpec
from swarmrec.wire import messages as pb


class Echo(ServiceBase):
    def __init__(self, ctx: ServiceContext) -> None:
        self.ctx = ctx
        self.robot = ctx.bus.robot

    def echo(self, req: pb.StepRequest, _ctx: RequestContext) -> pb.StepReply:
        return pb.StepReply(robot_id=self.robot, step=req.step, finished=True)

    def _ask(self, endpoint: str, req: pb.StepRequest) -> pb.StepReply:
        # The next robot's endpoint: finished=False when the router let nothing through.
        other = (self.robot + 1) % self.ctx.bus.n_robots
        try:
            key = keys.endpoint(self.ctx.bus.swarm, "echo", other, endpoint)
            return self.ctx.caller.call(key, req, pb.StepReply, target_robot=other)
        except NoReply:
            return pb.StepReply(robot_id=other, step=req.step, finished=False)

    def forward(self, req: pb.StepRequest, _ctx: RequestContext) -> pb.StepReply:
        return self._ask("echo", req)

    def forward_secret(self, req: pb.StepRequest, _ctx: RequestContext) -> pb.StepReply:
        return self._ask("secret", req)

    ENDPOINTS = (
        Endpoint("echo", pb.StepRequest, pb.StepReply, echo, "the step, back"),
        Endpoint("secret", pb.StepRequest, pb.StepReply, echo, "the step, back: no other robot calls it"),
        Endpoint("forward", pb.StepRequest, pb.StepReply, forward, "the next robot's echo of the step"),
        Endpoint("forward_secret", pb.StepRequest, pb.StepReply, forward_secret, "the next robot's secret"),
    )


# The router's access control grants what the spec names: clients may call `echo` and
# the forwards; an echo service calls the other robots' `echo`, never their `secret`.
SPEC = ServiceSpec(
    "echo",
    100,
    "echo_service:Echo",
    "answers a step with its robot's id",
    calls=(Call("echo", "echo"),),
    client_endpoints=("echo", "forward", "forward_secret"),
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

            def ask(endpoint: str) -> pb.StepReply:
                key = endpoint_key(swarm, "echo", 0, endpoint)
                return reply_of(send(client.session, key, pb.StepRequest(step=8)), pb.StepReply)

            # Robot 0's echo calls robot 1's: declared, so the router lets it through.
            forwarded = ask("forward")
            assert (forwarded.robot_id, forwarded.finished) == (1, True)
            # Robot 1's `secret` is served (a client may not call it, but robot 0 asks) only
            # if declared: it is not, so the router drops robot 0's query.
            refused = ask("forward_secret")
            assert (refused.robot_id, refused.finished) == (1, False)
        codes = swarm.stop()
    assert all(code == 0 for code in codes.values()), codes
