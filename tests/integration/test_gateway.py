"""The gRPC gateway of a real swarm: every process real, every zenoh link mutual TLS.

One 2-robot places swarm for the module (router, gateway, and detector,
descriptor, index-shard and verifier per robot, each a process with its own
certificate, the router enforcing the access control). Before the lock-step
replay the fixture opens the gateway's loop-closure and query-report streams
(waiting for their ``swarmrec-subscribed`` metadata), so the streams must carry
every event of the run. The gateway is reached over TLS with the swarm's
``client.cli`` certificate, as a client outside the swarm would; the last test
stops the gateway, so the tests run in file order.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import grpc
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection_pb2, reflection_pb2_grpc

from swarmrec.client import ERROR_CODE_METADATA, GatewayClient, channel_credentials
from swarmrec.core.types import Constellation
from swarmrec.datasets.constellations import read_constellations
from swarmrec.deployments.identities import client_tls
from swarmrec.deployments.local import LocalDeployment
from swarmrec.errors import ReplyTimeout
from swarmrec.runtime import keys
from swarmrec.runtime.tls import TlsFiles
from swarmrec.security.identity import Identity
from swarmrec.security.pki import PkiSettings, ensure_identity, init_pki
from swarmrec.services.gateway import SERVICE_NAME, SERVICE_STREAMS, SUBSCRIBED_METADATA
from swarmrec.services.settings import DetectorSettings, GatewaySettings, PlaceSettings
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import constellation_to_proto
from swarmrec.wire.gen.swarmrec.v1 import gateway_pb2, gateway_pb2_grpc
from tests.integration.conftest import running_swarm
from tests.integration.support import wait_until, write_office

N_ROBOTS, STEPS = 2, 60
KINDS = ("detector", "descriptor", "index-shard", "verifier")
GRPCURL_VERSION = "v1.9.3"
ROOT = Path(__file__).resolve().parents[2]


class Collector:
    """Reads one server stream in a thread, keeping every message in order."""

    def __init__(self, call: Any) -> None:
        self.call, self.items, self.error = call, [], None
        self.thread = threading.Thread(target=self._read, daemon=True)

    def start(self) -> Collector:
        # The gateway sends this metadata once its zenoh subscriber is declared.
        assert dict(self.call.initial_metadata()).get(SUBSCRIBED_METADATA) == "1"
        self.thread.start()
        return self

    def _read(self) -> None:
        try:
            for msg in self.call:
                self.items.append(msg)
        except grpc.RpcError as e:
            self.error = e

    def stop(self) -> list[Any]:
        self.call.cancel()
        self.thread.join(10)
        return list(self.items)


@dataclass
class Running:
    swarm: LocalDeployment
    dataset: Path
    reports: list[pb.QueryReport]
    streamed_closures: list[pb.LoopClosure]
    streamed_reports: list[pb.QueryReport]
    tmp: Path
    extra: dict[str, Any] = field(default_factory=dict)

    def gateway(self, timeout_s: float = 10.0) -> GatewayClient:
        return self.swarm.gateway_client(timeout_s)

    @property
    def target(self) -> str:
        return self.swarm.gateway_address.removeprefix("grpc://")

    @property
    def tls(self) -> TlsFiles:
        assert self.swarm.pki_dir is not None
        return client_tls(self.swarm.pki_dir, self.swarm.spec_swarm, "client")

    def channel(self, tls: TlsFiles | None = None) -> grpc.Channel:
        return grpc.secure_channel(self.target, channel_credentials(tls or self.tls))


@pytest.fixture(scope="module")
def running(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Running]:
    tmp = tmp_path_factory.mktemp("gateway")
    dataset = write_office(tmp / "dataset", n_frames=200)
    parts = (PlaceSettings(lockstep=True, loop_closure_min_score=0.2), DetectorSettings(dataset=str(dataset)))
    with running_swarm(tmp, "gw-swarm", *parts, robots=N_ROBOTS, request_timeout_s=2.0) as swarm:
        with swarm.gateway_client(10.0) as gw, swarm.client(10.0) as operator:
            closures = Collector(gw.stub.WatchLoopClosures(gateway_pb2.WatchRequest())).start()
            reports_stream = Collector(gw.stub.WatchQueryReports(gateway_pb2.WatchRequest())).start()
            reports: list[pb.QueryReport] = []
            for t in range(STEPS):
                replies = operator.step(t, timeout_s=10)
                assert all(isinstance(r, pb.StepReply) for r in replies), replies
                reports += [r.report for r in replies if isinstance(r, pb.StepReply)]
            expected = sum(len(operator.loop_closures(r)) for r in range(N_ROBOTS))
            wait_until(lambda: len(closures.items) >= expected, 10, f"{expected} loop closures streamed")
            wait_until(lambda: len(reports_stream.items) >= len(reports), 10, "every report streamed")
            streamed, streamed_reports = closures.stop(), reports_stream.stop()
        yield Running(swarm, dataset, reports, streamed, streamed_reports, tmp)


def _frame(running: Running) -> Constellation:
    """A constellation one robot replayed (it is stored: the query finds it with score 1)."""
    seq = read_constellations(running.dataset)
    return max(seq.constellations[:STEPS], key=len)


def test_reflection_lists_the_gateway_health_and_reflection_services(running: Running) -> None:
    with running.channel() as channel:
        stub = reflection_pb2_grpc.ServerReflectionStub(channel)
        answers = list(
            stub.ServerReflectionInfo(iter([reflection_pb2.ServerReflectionRequest(list_services="")]))
        )
    names = {s.name for s in answers[0].list_services_response.service}
    assert names == {
        "swarmrec.v1.SwarmGateway",
        "grpc.health.v1.Health",
        "grpc.reflection.v1alpha.ServerReflection",
    }


def test_only_this_swarms_clients_and_operators_are_served(running: Running) -> None:
    pki, swarm = running.swarm.pki_dir, running.swarm.spec_swarm
    assert pki is not None
    # Certificates the swarm's CA signed, held by what is not one of its clients: a robot's
    # service, and a client of another swarm (signed with the same CA, as a careless operator might).
    same_ca = running.tmp / "same-ca"
    shutil.copytree(pki, same_ca, dirs_exist_ok=True)
    ensure_identity(same_ca, Identity.client("elsewhere", "cli"))
    outsiders = {
        "a service": TlsFiles.in_dir(pki, f"r0.verifier.{swarm}"),
        "another swarm's client": TlsFiles.in_dir(same_ca, "client.cli.elsewhere"),
    }
    for who, tls in outsiders.items():
        with running.channel(tls) as channel:
            with pytest.raises(grpc.RpcError) as info:
                gateway_pb2_grpc.SwarmGatewayStub(channel).Members(gateway_pb2.MembersRequest(), timeout=5)
            assert info.value.code() == grpc.StatusCode.PERMISSION_DENIED, who
            assert "clients and operators" in (info.value.details() or ""), who
            with pytest.raises(grpc.RpcError) as info:
                next(reflection_pb2_grpc.ServerReflectionStub(channel).ServerReflectionInfo(
                    iter([reflection_pb2.ServerReflectionRequest(list_services="")]), timeout=5))  # fmt: skip
            assert info.value.code() == grpc.StatusCode.PERMISSION_DENIED, who
    for role in ("client", "operator"):
        with running.channel(client_tls(pki, swarm, role)) as channel:
            reply = gateway_pb2_grpc.SwarmGatewayStub(channel).Members(
                gateway_pb2.MembersRequest(), timeout=5
            )
            assert reply.members, role


def test_idle_reflection_streams_are_bounded_and_never_starve_the_health_check(running: Running) -> None:
    release = threading.Event()

    def requests() -> Iterator[reflection_pb2.ServerReflectionRequest]:
        yield reflection_pb2.ServerReflectionRequest(list_services="")
        release.wait(30)  # then idle, holding its stream open

    channels = [running.channel() for _ in range(SERVICE_STREAMS + 1)]
    held = []
    try:
        for channel in channels[:SERVICE_STREAMS]:
            stream = reflection_pb2_grpc.ServerReflectionStub(channel).ServerReflectionInfo(requests())
            next(stream)  # answered: the stream holds its slot
            held.append(stream)
        extra = reflection_pb2_grpc.ServerReflectionStub(channels[-1]).ServerReflectionInfo(requests())
        with pytest.raises(grpc.RpcError) as info:
            next(extra)
        assert info.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        with running.channel() as channel:
            answer = health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(), timeout=5)
        assert answer.status == health_pb2.HealthCheckResponse.SERVING
    finally:
        release.set()
        for stream in held:
            stream.cancel()
        for channel in channels:
            channel.close()


def test_health_answers_serving_for_the_server_and_the_gateway_service(running: Running) -> None:
    with running.channel() as channel:
        stub = health_pb2_grpc.HealthStub(channel)
        for name in ("", SERVICE_NAME):
            reply = stub.Check(health_pb2.HealthCheckRequest(service=name), timeout=5)
            assert reply.status == health_pb2.HealthCheckResponse.SERVING


def test_members_through_the_gateway_are_the_members_over_zenoh(running: Running) -> None:
    with running.gateway() as gw, running.swarm.client(role="client") as direct:
        via_gateway, over_zenoh = gw.members(), direct.members()
    assert [(m.kind, m.robot, m.label_range) for m in via_gateway] == [
        (m.kind, m.robot, m.label_range) for m in over_zenoh
    ]
    assert {(m.kind, m.robot) for m in via_gateway} == {("router", 0), ("gateway", 0)} | {
        (k, r) for k in KINDS for r in range(N_ROBOTS)
    }


def test_a_query_through_the_gateway_equals_the_query_over_zenoh_and_stores_nothing(running: Running) -> None:
    frame = _frame(running)
    with running.gateway() as gw, running.swarm.client(role="client") as direct:
        stored = {(m.kind, m.robot): m.stored_items for m in direct.members()}
        first, again, over_zenoh = gw.query(frame), gw.query(frame), direct.query(frame)
        assert {(m.kind, m.robot): m.stored_items for m in direct.members()} == stored
    assert first.matches and first.matches[0].score == 1.0
    assert list(first.matches) == list(again.matches) == list(over_zenoh.matches)
    assert first.complete and first.n_candidates == over_zenoh.n_candidates


def test_loop_closures_through_the_gateway_are_the_robots_own(running: Running) -> None:
    with running.gateway() as gw, running.swarm.client() as direct:
        for r in range(N_ROBOTS):
            assert list(gw.loop_closures(r)) == list(direct.loop_closures(r))


def test_the_stream_delivered_every_loop_closure_of_the_lockstep_run_in_order(running: Running) -> None:
    with running.swarm.client() as direct:
        per_robot = {r: list(direct.loop_closures(r)) for r in range(N_ROBOTS)}
    assert sum(map(len, per_robot.values())) > 0, "the run found no loop closure: nothing to check"
    for r in range(N_ROBOTS):
        assert [c for c in running.streamed_closures if c.query_robot_id == r] == per_robot[r]
    assert len(running.streamed_closures) == sum(map(len, per_robot.values()))
    # Lock-step: every event of step t arrives before any of step t + 1.
    steps = [
        c.query_frame_index - min(c.query_frame_index for c in running.streamed_closures)
        for c in running.streamed_closures
    ]
    frames = [(c.query_robot_id, c.query_frame_index) for c in running.streamed_closures]
    assert len(set(frames)) == len(frames)
    assert steps == sorted(steps) or _in_step_order(running)


def _in_step_order(running: Running) -> bool:
    """Each robot's frames are its own block's: compare by the step (the frame's report order)."""
    order = {(r.robot_id, r.frame_index): i // N_ROBOTS for i, r in enumerate(running.reports)}
    ranks = [order[(c.query_robot_id, c.query_frame_index)] for c in running.streamed_closures]
    return ranks == sorted(ranks)


def test_the_report_stream_carried_every_query_report(running: Running) -> None:
    key = lambda r: (r.robot_id, r.frame_index)  # noqa: E731
    assert sorted(map(key, running.streamed_reports)) == sorted(map(key, running.reports))
    by_key = {key(r): r for r in running.reports}
    for r in running.streamed_reports:
        assert list(r.matches) == list(by_key[key(r)].matches)


def _code(e: grpc.RpcError) -> tuple[grpc.StatusCode, str]:
    return e.code(), dict(e.trailing_metadata() or ()).get(ERROR_CODE_METADATA, "")


def _query(running: Running, request: gateway_pb2.QueryRequest, timeout: float = 10) -> Any:
    with running.gateway() as gw:
        return gw.stub.Query(request, timeout=timeout)


@pytest.mark.parametrize(
    ("request_", "status", "code"),
    [
        (gateway_pb2.QueryRequest(), grpc.StatusCode.INVALID_ARGUMENT, "ERROR_CODE_INVALID_ARGUMENT"),
        (
            gateway_pb2.QueryRequest(constellation=pb.Constellation(labels=[200], positions_m=[0, 0, 1])),
            grpc.StatusCode.INVALID_ARGUMENT,
            "ERROR_CODE_UNKNOWN_LABEL",
        ),
        (
            gateway_pb2.QueryRequest(constellation=pb.Constellation(labels=[1], positions_m=[0, 0])),
            grpc.StatusCode.INVALID_ARGUMENT,
            "ERROR_CODE_INVALID_ARGUMENT",
        ),
        (
            gateway_pb2.QueryRequest(
                constellation=pb.Constellation(labels=[1], positions_m=[0, 0, 1]), preset="nope"
            ),
            grpc.StatusCode.INVALID_ARGUMENT,
            "ERROR_CODE_INVALID_ARGUMENT",
        ),
    ],
    ids=["no-constellation", "unknown-label", "wrong-coordinates", "unknown-preset"],
)
def test_a_bad_query_is_answered_with_its_status_and_the_swarms_code(
    running: Running, request_: gateway_pb2.QueryRequest, status: grpc.StatusCode, code: str
) -> None:
    with pytest.raises(grpc.RpcError) as info:
        _query(running, request_)
    assert _code(info.value) == (status, code)


def test_a_request_over_the_size_limit_is_resource_exhausted(running: Running) -> None:
    n = 50_000  # 1.2 MB of coordinates, over max_message_bytes (1 MiB)
    big = pb.Constellation(labels=[1] * n, positions_m=[0.5] * (3 * n))
    with pytest.raises(grpc.RpcError) as info:
        _query(running, gateway_pb2.QueryRequest(constellation=big))
    assert info.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED


def test_loop_closures_of_a_robot_that_is_not_there_is_not_found(running: Running) -> None:
    with running.gateway() as gw, pytest.raises(grpc.RpcError) as info:
        gw.stub.LoopClosures(gateway_pb2.RobotLoopClosuresRequest(robot_id=7), timeout=10)
    assert _code(info.value) == (grpc.StatusCode.NOT_FOUND, "ERROR_CODE_NOT_FOUND")


def test_the_grpc_port_refuses_a_client_without_a_certificate_or_with_another_cas(running: Running) -> None:
    other = running.tmp / "other-pki"
    init_pki(PkiSettings(swarm=running.swarm.spec_swarm, robots=1, out=other))
    foreign = TlsFiles.in_dir(other, f"client.cli.{running.swarm.spec_swarm}")
    no_cert = grpc.ssl_channel_credentials(root_certificates=running.tls.root_ca.read_bytes())
    for creds in (no_cert, channel_credentials(foreign)):
        with grpc.secure_channel(running.target, creds) as channel:
            stub = health_pb2_grpc.HealthStub(channel)
            with pytest.raises(grpc.RpcError) as info:
                stub.Check(health_pb2.HealthCheckRequest(), timeout=5)
            assert info.value.code() == grpc.StatusCode.UNAVAILABLE
    with pytest.raises(grpc.RpcError), grpc.insecure_channel(running.target) as plain:
        health_pb2_grpc.HealthStub(plain).Check(health_pb2.HealthCheckRequest(), timeout=5)


def test_a_deadline_shorter_than_the_work_is_deadline_exceeded(running: Running) -> None:
    frame = _frame(running)
    with running.gateway() as gw:
        before = gw.query(frame)
    # The verifier that checks the frame's candidates: stopped, the work waits for it.
    assert before.verified_robots, before
    victim = before.verified_robots[0]
    verifier = running.swarm.find("verifier", victim)
    os.kill(verifier.proc.pid, signal.SIGSTOP)  # the work now takes request_timeout_s (2 s)
    try:
        with running.gateway() as gw:
            with pytest.raises(grpc.RpcError) as info:
                gw.stub.Query(
                    gateway_pb2.QueryRequest(constellation=constellation_to_proto(frame, 0, 0, exact=True)),
                    timeout=0.5,
                )
            assert info.value.code() == grpc.StatusCode.DEADLINE_EXCEEDED
            # The same failure as the Python client sees it.
            with pytest.raises(ReplyTimeout):
                GatewayClient(
                    running.swarm.gateway_address, running.swarm.spec_swarm, timeout_s=0.5, tls=running.tls
                ).__enter__().query(frame)
            # Without a deadline the gateway's own timeout ends the wait: a partial answer.
            result = gw.query(frame)
            assert victim in result.failed_verifiers and not result.matches
    finally:
        os.kill(verifier.proc.pid, signal.SIGCONT)


def _grpcurl() -> Path:
    """grpcurl built from its Go module once, cached under the project's own .cache/."""
    binary = ROOT / ".cache" / "tools" / f"grpcurl-{GRPCURL_VERSION}" / "grpcurl"
    if not binary.exists():
        binary.parent.mkdir(parents=True, exist_ok=True)
        env = dict(os.environ, GOBIN=str(binary.parent), GOFLAGS="-mod=mod")
        done = subprocess.run(
            ["go", "install", f"github.com/fullstorydev/grpcurl/cmd/grpcurl@{GRPCURL_VERSION}"],
            env=env, capture_output=True, text=True, timeout=1200, check=False, cwd=binary.parent.parent,
        )  # fmt: skip
        assert done.returncode == 0, done.stderr[-2000:]
    return binary


def test_grpcurl_lists_by_reflection_calls_members_and_query_and_reads_a_stream(running: Running) -> None:
    grpcurl, tls = _grpcurl(), running.tls
    base = [str(grpcurl), "-cacert", str(tls.root_ca), "-cert", str(tls.cert), "-key", str(tls.key)]

    def call(*args: str, data: str | None = None) -> subprocess.CompletedProcess[str]:
        extra = ["-d", data] if data is not None else []
        return subprocess.run(
            [*base, *extra, running.target, *args], capture_output=True, text=True, timeout=60, check=False
        )

    listed = call("list")
    assert listed.returncode == 0, listed.stderr
    assert "swarmrec.v1.SwarmGateway" in listed.stdout.split()
    members = call("swarmrec.v1.SwarmGateway/Members", data="{}")
    assert members.returncode == 0, members.stderr
    # grpcurl prints the schema's field names and leaves out default values (robot 0).
    listed_members = json.loads(members.stdout)["members"]
    kinds = {(m.get("kind"), m.get("robot_id", 0)) for m in listed_members}
    assert {("SERVICE_KIND_INDEX_SHARD", 1), ("SERVICE_KIND_GATEWAY", 0), ("SERVICE_KIND_ROUTER", 0)} <= kinds
    assert len(listed_members) == 2 + len(KINDS) * N_ROBOTS
    frame = _frame(running)
    query = {
        "constellation": {"labels": frame.labels.tolist(), "positionsM": frame.positions.ravel().tolist()}
    }
    answered = call("swarmrec.v1.SwarmGateway/Query", data=json.dumps(query))
    assert answered.returncode == 0, answered.stderr
    best = json.loads(answered.stdout)["matches"][0]
    assert best["score"] == 1.0
    stream = subprocess.run(
        [*base, "-d", "{}", "-max-time", "3", running.target, "swarmrec.v1.SwarmGateway/WatchMembership"],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    decoder = json.JSONDecoder()
    changes, text = [], stream.stdout.strip()
    while text:
        obj, end = decoder.raw_decode(text)
        changes.append(obj)
        text = text[end:].strip()
    alive = {(c["kind"], c.get("robot_id", 0)) for c in changes if c.get("alive")}
    assert {(k, r) for k in KINDS for r in range(N_ROBOTS)} <= alive, stream.stdout + stream.stderr


def test_one_caller_cannot_hold_every_event_stream(running: Running) -> None:
    """``grpc_max_streams_per_caller`` (4 of the 8 by default): the fifth event stream of
    one certificate is refused RESOURCE_EXHAUSTED while another identity's is served, and
    a stream closed frees its caller's slot."""
    per_caller = GatewaySettings().grpc_max_streams_per_caller
    assert per_caller < GatewaySettings().grpc_max_streams
    pki, swarm = running.swarm.pki_dir, running.swarm.spec_swarm
    assert pki is not None
    with (
        running.channel(client_tls(pki, swarm, "client")) as mine,
        running.channel(client_tls(pki, swarm, "operator")) as theirs,
    ):
        stub, other = gateway_pb2_grpc.SwarmGatewayStub(mine), gateway_pb2_grpc.SwarmGatewayStub(theirs)
        held = [stub.WatchLoopClosures(gateway_pb2.WatchRequest()) for _ in range(per_caller)]
        try:
            for call in held:
                assert dict(call.initial_metadata()).get(SUBSCRIBED_METADATA) == "1"  # open
            with pytest.raises(grpc.RpcError) as info:
                next(stub.WatchLoopClosures(gateway_pb2.WatchRequest(), timeout=10))
            assert info.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
            assert "grpc_max_streams_per_caller" in (info.value.details() or "")
            theirs_open = other.WatchLoopClosures(gateway_pb2.WatchRequest())
            assert dict(theirs_open.initial_metadata()).get(SUBSCRIBED_METADATA) == "1"
            theirs_open.cancel()
            held.pop().cancel()

            def reopened() -> bool:
                call = stub.WatchLoopClosures(gateway_pb2.WatchRequest())
                served = dict(call.initial_metadata()).get(SUBSCRIBED_METADATA) == "1"
                (held.append(call) if served else call.cancel())
                return served

            wait_until(reopened, 10, "the closed stream's slot free again")
        finally:
            for call in held:
                call.cancel()


def test_health_turns_not_serving_when_the_gateway_stops(running: Running) -> None:
    gateway = running.swarm.find("gateway", 0)
    with running.channel() as channel:
        watch = health_pb2_grpc.HealthStub(channel).Watch(
            health_pb2.HealthCheckRequest(service=SERVICE_NAME), timeout=30
        )
        statuses = [next(watch).status]
        assert statuses == [health_pb2.HealthCheckResponse.SERVING]
        gateway.proc.send_signal(signal.SIGTERM)
        with contextlib.suppress(grpc.RpcError):  # the stream may end right after the update
            statuses.append(next(watch).status)
    assert gateway.proc.wait(30) == 0
    assert statuses == [health_pb2.HealthCheckResponse.SERVING, health_pb2.HealthCheckResponse.NOT_SERVING]


def test_an_event_claiming_another_robot_than_its_key_is_not_streamed(tmp_path: Path) -> None:
    # Plaintext, so this test may publish as any robot (under mutual TLS the router lets a
    # robot's services publish on their own robot's keys only, which is what makes the key
    # the publisher's): robot 3's key, a payload claiming robot 2.
    with (
        running_swarm(tmp_path, "gw-forged", robots=4, kinds=(), security="insecure") as swarm,
        swarm.gateway_client(10.0) as gw,
        swarm.client(5.0) as publisher,
    ):
        closures = Collector(gw.stub.WatchLoopClosures(gateway_pb2.WatchRequest())).start()
        forged = pb.LoopClosure(query_robot_id=2, query_frame_index=7, match_robot_id=0, score=1.0)
        genuine = pb.LoopClosure(query_robot_id=3, query_frame_index=8, match_robot_id=0, score=1.0)
        key = keys.event(swarm.spec_swarm, "loop_closure", 3)
        publisher.session.put(key, forged.SerializeToString())
        publisher.session.put(key, genuine.SerializeToString())
        wait_until(lambda: len(closures.items) >= 1, 10, "the genuine closure streamed")
        time.sleep(0.5)  # (anything after it would have come by now)
        got = closures.stop()
    assert [(c.query_robot_id, c.query_frame_index) for c in got] == [(3, 8)]
