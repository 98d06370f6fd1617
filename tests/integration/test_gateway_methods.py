"""The gateway's full-image, SLAM and landmark RPCs against a real swarm, every link mutual TLS.

One 2-robot swarm for the module (router, gateway, and a verifier, place owner, slam and
fusion service per robot, each a process with its own certificate, the router enforcing
the access control the registry declares). The fixture drives it as the robots would:

* full-image: each robot's detector (its own certificate) sends its frames to its place
  owner's ``process``: seeded random unit descriptors, robot 1's frames near copies of
  robot 0's (with the same objects), so robot 1 closes loops; the gateway's place-report
  stream is open before, and must carry every report;
* SLAM: a simulated 2-robot world (``swarmrec slam run``'s), loaded and started as the
  operator; the gateway's estimate stream of robot 1 opened between load and solve;
* landmarks: one round started on each robot by its detector's certificate.

Expected values come from outside the code under test: the offline search (nearest
centre and nearest stored frame computed here with numpy from the centres file and the
int8 layout the owners store), the descriptor model run here on the same image, run_dgs's
estimate in this process, and each service answered directly over zenoh. The gateway is
reached with the swarm's ``client.cli`` certificate, by grpcio (the Python
``GatewayClient``) and by grpcurl, which knows the contract only through reflection.
"""

from __future__ import annotations

import json
import os
import signal
import struct
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import grpc
import numpy as np
import pytest

from swarmrec.client import ZenohClient
from swarmrec.deployments.local import LocalDeployment
from swarmrec.experiments.slam.pipeline import prepare
from swarmrec.experiments.slam.settings import LiveSlamSettings
from swarmrec.models import DESCRIPTOR_CENTRES, shipped_model
from swarmrec.runtime import keys
from swarmrec.runtime.tls import TlsFiles
from swarmrec.services.gateway import SUBSCRIBED_METADATA
from swarmrec.services.settings import PlaceSettings, SlamServiceSettings, VprSettings
from swarmrec.slam.dgs import DgsSettings, run_dgs
from swarmrec.vpr.clusters import random_assignment
from swarmrec.vpr.model import DescriptorModel
from swarmrec.wire import messages as pb
from swarmrec.wire.gen.swarmrec.v1 import gateway_pb2
from swarmrec.wire.slam import settings_to_proto
from tests.integration.conftest import running_swarm
from tests.integration.support import wait_until
from tests.integration.test_gateway import ERROR_CODE_METADATA, Collector, _grpcurl

N_ROBOTS, C, D = 2, 5, 128
K = N_ROBOTS * C
FRAMES = 10  # per robot
TABLE = random_assignment(N_ROBOTS, C, seed=0)
FLOAT32 = 1
KINDS = ("verifier", "place-owner", "slam", "fusion")


def unit(seed: int) -> np.ndarray:
    v = np.random.default_rng([seed, 91]).normal(size=D).astype(np.float32)
    return v / np.linalg.norm(v)


def int8_stored(x: np.ndarray) -> np.ndarray:
    """What an owner stores of a query sent int8 (the wire's layout, written out here):
    scale = max|x| / 127, q = round(x / scale); stored q * scale."""
    scale = np.float32(np.abs(x).max() / np.float32(127))
    q = np.clip(np.rint(x / scale), -127, 127).astype(np.int8)
    return q.astype(np.float32) * scale


def nearest_cluster(x: np.ndarray) -> int:
    with np.load(shipped_model(DESCRIPTOR_CENTRES)) as data:
        centres = np.asarray(data[f"k{K}"], np.float64)
    return int(np.argmin(((centres - x.astype(np.float64)) ** 2).sum(axis=1)))


def frame(robot: int, t: int) -> tuple[np.ndarray, pb.PlaceFrame]:
    """Robot ``robot``'s frame ``t``: robot 1's frame t is a near copy of robot 0's, same objects."""
    x = unit(t)
    if robot == 1:
        x = x + 0.01 * unit(1000 + t)
        x = (x / np.linalg.norm(x)).astype(np.float32)
    c = pb.Constellation(labels=[0, 41, 56], positions_mm=[100 * t, 20, 1500, -300, 10, 2000, 250, -40, 1800])
    msg = pb.PlaceFrame(
        robot_id=robot, frame_index=t, descriptor=x.astype("<f4").tobytes(), encoding=FLOAT32, constellation=c
    )
    return x, msg


@dataclass
class Seeded:
    robot: int
    frame: int
    x: np.ndarray
    report: pb.PlaceReport


@dataclass
class Running:
    swarm: LocalDeployment
    seeded: list[Seeded]
    streamed_reports: list[pb.PlaceReport]
    graph: Any
    streamed_estimates: list[pb.SlamEstimate]
    estimate_stream_error: grpc.RpcError | None
    tmp: Path

    @property
    def target(self) -> str:
        return self.swarm.gateway_address.removeprefix("grpc://")


def _as_robot(swarm: LocalDeployment, kind: str, robot: int) -> ZenohClient:
    """A zenoh session with robot ``robot``'s ``kind`` certificate: what that service may do."""
    assert swarm.pki_dir is not None
    tls = TlsFiles.in_dir(swarm.pki_dir, f"r{robot}.{kind}.{swarm.spec_swarm}")
    return ZenohClient([swarm.endpoint], swarm.spec_swarm, timeout_s=10.0, tls=tls)


def _seed_places(swarm: LocalDeployment) -> list[Seeded]:
    seeded = []
    for r in range(N_ROBOTS):  # robot 0's frames first: robot 1's then find them
        with _as_robot(swarm, "detector", r) as detector:
            for t in range(FRAMES):
                x, msg = frame(r, t)
                key = keys.endpoint(swarm.spec_swarm, "place-owner", r, "process")
                report = detector.call(key, msg, pb.PlaceReport, target_robot=r)
                assert report.answered, report
                seeded.append(Seeded(r, t, x, report))
    return seeded


def _solve_watching(swarm: LocalDeployment) -> tuple[list[pb.SlamEstimate], grpc.RpcError | None]:
    """Load both robots, open the gateway's estimate stream of robot 1, start the solve, and
    read the stream until it ends by itself."""
    s = swarm.spec_swarm
    with swarm.client(10.0) as operator, swarm.gateway_client(10.0) as gw:
        load = pb.SlamLoadRequest(solve_id=1, settings=settings_to_proto(DgsSettings()))
        for r in range(N_ROBOTS):
            operator.call(keys.endpoint(s, "slam", r, "load"), load, pb.SlamProblem, target_robot=None)
        stream = Collector(gw.stub.WatchSlamEstimate(gateway_pb2.WatchSlamEstimateRequest(robot_id=1)))
        stream.start()  # (its metadata comes with the first estimate: the loaded one)
        for r in range(N_ROBOTS):
            operator.call(
                keys.endpoint(s, "slam", r, "solve"),
                pb.SlamSolveRequest(solve_id=1),
                pb.SlamSolveStarted,
                target_robot=None,
            )
        stream.thread.join(120)
        assert not stream.thread.is_alive(), "the estimate stream did not end with the solve"
        return list(stream.items), stream.error


def _start_rounds(swarm: LocalDeployment) -> None:
    s = swarm.spec_swarm
    for r in range(N_ROBOTS):
        p = np.full(19, 0.02, np.float32)
        p[3 + r] = 1 - 0.02 * 18
        start = pb.FusionRoundStart(
            round_id=1, probabilities=p.tolist(), yaw_rad=0.5 * r, neighbour_robot_ids=[1 - r]
        )
        with _as_robot(swarm, "detector", r) as detector:
            detector.call(
                keys.endpoint(s, "fusion", r, "start_round"), start, pb.FusionRoundStarted, target_robot=r
            )
    with swarm.client(10.0, role="client") as client:

        def heard_all() -> bool:
            return all(
                client.call(
                    keys.endpoint(s, "fusion", r, "posterior"),
                    pb.PosteriorRequest(round_id=1),
                    pb.FusionPosterior,
                    target_robot=None,
                ).heard_all
                for r in range(N_ROBOTS)
            )

        wait_until(heard_all, 30, "every robot heard the other's output")


@pytest.fixture(scope="module")
def running(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Running]:
    tmp = tmp_path_factory.mktemp("gateway-methods")
    world = prepare(LiveSlamSettings(out=tmp / "slam", robots=N_ROBOTS, progress=False))
    parts = (
        PlaceSettings(),
        VprSettings(vpr_clusters_per_robot=C),
        SlamServiceSettings(slam_folder=world.folder.resolve(), slam_peer_timeout_s=10.0),
    )
    with running_swarm(
        tmp, "gw-methods", *parts, robots=N_ROBOTS, kinds=KINDS, request_timeout_s=3.0
    ) as swarm:
        with swarm.gateway_client(10.0) as gw:
            reports = Collector(gw.stub.WatchPlaceReports(gateway_pb2.WatchRequest())).start()
            seeded = _seed_places(swarm)
            wait_until(lambda: len(reports.items) >= len(seeded), 10, "every place report streamed")
            streamed = reports.stop()
        estimates, error = _solve_watching(swarm)
        _start_rounds(swarm)
        yield Running(swarm, seeded, streamed, world.graph, estimates, error, tmp)


def offline_match(running: Running, x: np.ndarray, exclude: int | None) -> tuple[int, int, float] | None:
    """The nearest stored frame in ``x``'s cluster (robot, frame, squared distance), computed
    here: what the owner of that cluster holds is every seeded frame routed to it, as stored."""
    cluster = nearest_cluster(x)
    held = [s for s in running.seeded if nearest_cluster(s.x) == cluster and s.robot != exclude]
    if not held:
        return None
    d = [float(((int8_stored(s.x).astype(np.float64) - x.astype(np.float64)) ** 2).sum()) for s in held]
    best = int(np.argmin(d))
    return held[best].robot, held[best].frame, d[best]


def test_a_place_query_by_descriptor_finds_what_the_offline_search_finds_and_stores_nothing(
    running: Running,
) -> None:
    with running.swarm.gateway_client(10.0) as gw, running.swarm.client(10.0, role="client") as direct:
        stored = {(m.kind, m.robot): m.stored_items for m in direct.members()}
        assert sum(v for (k, _), v in stored.items() if k == "place-owner") == N_ROBOTS * FRAMES
        for s in running.seeded:
            for exclude in (None, s.robot):
                reply = gw.place_query(s.x, exclude_robot=exclude)
                assert reply.cluster == nearest_cluster(s.x)
                assert reply.owner_robot_id == TABLE.owners[reply.cluster]
                expected = offline_match(running, s.x, exclude)
                assert expected is not None and reply.match.found
                assert (reply.match.robot_id, reply.match.frame_index) == expected[:2]
                assert reply.match.distance == pytest.approx(expected[2], abs=1e-5)
                over_zenoh = direct.place_query(s.x, exclude_robot=exclude)
                assert (over_zenoh.cluster, over_zenoh.match) == (reply.cluster, reply.match)
        assert {(m.kind, m.robot): m.stored_items for m in direct.members()} == stored


def _png(seed: int) -> tuple[bytes, np.ndarray]:
    rng = np.random.default_rng(seed)
    bgr = cv2.resize(
        rng.integers(0, 255, (12, 16, 3), dtype=np.uint8), (320, 240), interpolation=cv2.INTER_NEAREST
    )
    ok, data = cv2.imencode(".png", bgr)
    assert ok
    return data.tobytes(), bgr


def test_a_place_query_by_image_describes_it_as_the_model_does(running: Running) -> None:
    data, bgr = _png(5)
    expected = DescriptorModel().describe_frames(bgr)[0]
    with running.swarm.gateway_client(30.0) as gw:
        by_image = gw.place_query(image=data)
        by_descriptor = gw.place_query(expected)
    assert np.allclose(np.asarray(by_image.descriptor, np.float32), expected, atol=1e-5)
    assert (by_image.cluster, by_image.match) == (by_descriptor.cluster, by_descriptor.match)
    assert by_image.cluster == nearest_cluster(expected)
    assert not by_descriptor.descriptor  # only an image query says what it computed


def test_the_cluster_table_is_the_one_every_owner_answers(running: Running) -> None:
    s = running.swarm.spec_swarm
    with running.swarm.gateway_client(10.0) as gw, running.swarm.client(10.0, role="client") as direct:
        table = gw.cluster_table()
        owners = [
            direct.call(
                keys.endpoint(s, "place-owner", r, "assignment"),
                pb.AssignmentRequest(),
                pb.AssignmentReply,
                target_robot=None,
            )
            for r in range(N_ROBOTS)
        ]
    assert list(table.owners) == owners and table.agreed
    assert table.version == owners[0].version == 0
    assert json.loads(table.table_json)["owners"] == list(TABLE.owners)


def test_place_loop_closures_are_the_owners_own(running: Running) -> None:
    s = running.swarm.spec_swarm
    with running.swarm.gateway_client(10.0) as gw, running.swarm.client(10.0, role="client") as direct:
        for r in range(N_ROBOTS):
            own = direct.call(
                keys.endpoint(s, "place-owner", r, "loop_closures"),
                pb.LoopClosuresRequest(),
                pb.LoopClosureList,
                target_robot=None,
            ).loop_closures
            assert gw.place_loop_closures(r) == list(own)
        closed = gw.place_loop_closures(1)
    # Robot 1's frames are near copies of robot 0's with the same objects: they close loops.
    assert closed and {c.query_frame_index for c in closed} == {
        x.frame for x in running.seeded if x.robot == 1 and x.report.loop_closure
    }


def test_the_place_report_stream_carried_every_report(running: Running) -> None:
    got = {(r.robot_id, r.frame_index): r for r in running.streamed_reports}
    assert len(got) == len(running.streamed_reports) == len(running.seeded)
    for s in running.seeded:
        streamed = got[(s.robot, s.frame)]
        assert (streamed.cluster, streamed.match, streamed.loop_closure) == (
            s.report.cluster,
            s.report.match,
            s.report.loop_closure,
        )


def _pose_bytes(values: Any) -> bytes:
    return struct.pack(f"<{len(values)}d", *values)


def test_the_merged_map_is_run_dgs_estimate_bit_for_bit_and_the_team_is_the_robots(running: Running) -> None:
    reference = run_dgs(running.graph, DgsSettings())
    s = running.swarm.spec_swarm
    with running.swarm.gateway_client(10.0) as gw, running.swarm.client(10.0, role="client") as direct:
        merged, team = gw.slam_map(), gw.slam_team()
        statuses = [
            direct.call(
                keys.endpoint(s, "slam", r, "status"),
                pb.SlamStatusRequest(),
                pb.SlamStatus,
                target_robot=None,
            )
            for r in range(N_ROBOTS)
        ]
        estimates = [gw.slam_estimate(r) for r in range(N_ROBOTS)]
        direct_estimates = [
            direct.call(
                keys.endpoint(s, "slam", r, "estimate"),
                pb.SlamEstimateRequest(),
                pb.SlamEstimate,
                target_robot=None,
            )
            for r in range(N_ROBOTS)
        ]
    assert team == statuses and all(st.state == pb.SlamState.SLAM_STATE_DONE for st in team)
    assert estimates == direct_estimates
    assert merged.done and merged.solve_id == 1 and list(merged.robot_ids) == [0, 1]
    assert not merged.missing_robot_ids
    assert list(merged.keys) == sorted(running.graph.poses) == sorted(reference.poses)
    for i, key in enumerate(merged.keys):
        pose = reference.poses[key]
        assert (
            _pose_bytes(merged.values[12 * i : 12 * (i + 1)])
            == pose.rotation.tobytes() + pose.translation.tobytes()
        )


def test_the_estimate_stream_followed_the_solve_and_ended_with_its_final_estimate(running: Running) -> None:
    got = running.streamed_estimates
    assert running.estimate_stream_error is None, running.estimate_stream_error
    assert got[0].state == pb.SlamState.SLAM_STATE_LOADED
    positions = [(e.state, e.linearisation, e.iteration) for e in got]
    assert len(set(positions)) == len(positions) >= 2  # each estimate once, as it moved on
    with running.swarm.client(10.0, role="client") as direct:
        final = direct.call(
            keys.endpoint(running.swarm.spec_swarm, "slam", 1, "estimate"),
            pb.SlamEstimateRequest(),
            pb.SlamEstimate,
            target_robot=None,
        )
    assert got[-1] == final and final.state == pb.SlamState.SLAM_STATE_DONE


def test_a_landmark_round_is_every_robots_posterior(running: Running) -> None:
    s = running.swarm.spec_swarm
    with running.swarm.gateway_client(10.0) as gw, running.swarm.client(10.0, role="client") as direct:
        reply, latest, unknown = gw.landmark_round(1), gw.landmark_round(), gw.landmark_round(9)
        own = [
            direct.call(
                keys.endpoint(s, "fusion", r, "posterior"),
                pb.PosteriorRequest(round_id=1),
                pb.FusionPosterior,
                target_robot=None,
            )
            for r in range(N_ROBOTS)
        ]
    assert list(reply.posteriors) == own == list(latest.posteriors) and reply.not_held == 0
    assert [p.robot_id for p in own] == [0, 1] and all(p.heard_all for p in own)
    assert not unknown.posteriors and unknown.not_held == N_ROBOTS


def _code(e: grpc.RpcError) -> tuple[grpc.StatusCode, str]:
    return e.code(), dict(e.trailing_metadata() or ()).get(ERROR_CODE_METADATA, "")


INVALID = (grpc.StatusCode.INVALID_ARGUMENT, "ERROR_CODE_INVALID_ARGUMENT")
# A PNG header claiming 30000 x 30000 pixels: refused before anything is decoded.
HUGE_PNG = (
    b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IHDR" + struct.pack(">II", 30000, 30000) + bytes(5)
)


@pytest.mark.parametrize(
    ("method", "request_", "expected"),
    [
        ("PlaceQuery", gateway_pb2.PlaceQueryRequest(), INVALID),
        ("PlaceQuery", gateway_pb2.PlaceQueryRequest(descriptor=[1.0], image=b"x"), INVALID),
        ("PlaceQuery", gateway_pb2.PlaceQueryRequest(descriptor=[1.0] * 3), INVALID),
        ("PlaceQuery", gateway_pb2.PlaceQueryRequest(descriptor=[float("nan")] * D), INVALID),
        ("PlaceQuery", gateway_pb2.PlaceQueryRequest(descriptor=[1.0] * D), INVALID),  # not unit
        ("PlaceQuery", gateway_pb2.PlaceQueryRequest(image=b"not an image"), INVALID),
        (
            "PlaceQuery",
            gateway_pb2.PlaceQueryRequest(image=HUGE_PNG),
            (grpc.StatusCode.RESOURCE_EXHAUSTED, "ERROR_CODE_TOO_LARGE"),
        ),
        (
            "PlaceLoopClosures",
            gateway_pb2.RobotLoopClosuresRequest(robot_id=7),
            (grpc.StatusCode.NOT_FOUND, "ERROR_CODE_NOT_FOUND"),
        ),
        (
            "SlamRobotEstimate",
            gateway_pb2.SlamRobotRequest(robot_id=7),
            (grpc.StatusCode.NOT_FOUND, "ERROR_CODE_NOT_FOUND"),
        ),
    ],
    ids=[
        "neither",
        "both",
        "wrong-length",
        "nan",
        "not-unit",
        "not-an-image",
        "huge-image",
        "closures-of-no-robot",
        "estimate-of-no-robot",
    ],
)
def test_a_bad_request_is_answered_with_its_status_and_the_swarms_code(
    running: Running, method: str, request_: Any, expected: tuple[grpc.StatusCode, str]
) -> None:
    with running.swarm.gateway_client(10.0) as gw, pytest.raises(grpc.RpcError) as info:
        getattr(gw.stub, method)(request_, timeout=10)
    assert _code(info.value) == expected


def test_an_estimate_stream_of_no_robot_or_a_busy_interval_is_refused(running: Running) -> None:
    with running.swarm.gateway_client(10.0) as gw:
        for request_, expected in (
            (
                gateway_pb2.WatchSlamEstimateRequest(robot_id=7),
                (grpc.StatusCode.NOT_FOUND, "ERROR_CODE_NOT_FOUND"),
            ),
            (gateway_pb2.WatchSlamEstimateRequest(robot_id=0, interval_ms=1), INVALID),
        ):
            with pytest.raises(grpc.RpcError) as info:
                list(gw.stub.WatchSlamEstimate(request_, timeout=10))
            assert _code(info.value) == expected


def test_grpcurl_calls_every_new_rpc_and_gets_what_the_python_client_gets(running: Running) -> None:
    assert running.swarm.pki_dir is not None
    grpcurl = _grpcurl()
    with running.swarm.gateway_client(10.0) as gw:
        tls = gw.tls
        assert tls is not None
        base = [str(grpcurl), "-cacert", str(tls.root_ca), "-cert", str(tls.cert), "-key", str(tls.key)]

        def call(method: str, data: dict[str, Any]) -> Any:
            done = subprocess.run(
                [*base, "-d", json.dumps(data), running.target, f"swarmrec.v1.SwarmGateway/{method}"],
                capture_output=True,
                text=True,
                timeout=60,
                check=False,
            )
            assert done.returncode == 0, done.stderr
            decoder, text, out = json.JSONDecoder(), done.stdout.strip(), []
            while text:
                obj, end = decoder.raw_decode(text)
                out.append(obj)
                text = text[end:].strip()
            return out[0] if len(out) == 1 else out

        table = call("ClusterTable", {})
        assert table["table_json"] == gw.cluster_table().table_json and table["agreed"]
        s = running.seeded[3]
        answer = call("PlaceQuery", {"descriptor": s.x.tolist(), "exclude_robot_id": s.robot})
        mine = gw.place_query(s.x, exclude_robot=s.robot)
        assert answer.get("cluster", 0) == mine.cluster
        assert answer["match"].get("robot_id", 0) == mine.match.robot_id
        assert answer["match"].get("frame_index", 0) == mine.match.frame_index
        closures = call("PlaceLoopClosures", {"robot_id": 1})["loop_closures"]
        assert [c.get("query_frame_index", 0) for c in closures] == [
            c.query_frame_index for c in gw.place_loop_closures(1)
        ]
        team = call("SlamTeam", {})["robots"]
        assert [t["state"] for t in team] == ["SLAM_STATE_DONE"] * N_ROBOTS
        merged = call("SlamMap", {})
        expected_map = gw.slam_map()
        assert [int(k) for k in merged["keys"]] == list(expected_map.keys)
        assert merged["values"] == list(expected_map.values)
        estimate = call("SlamRobotEstimate", {"robot_id": 1})
        assert [int(k) for k in estimate["keys"]] == list(gw.slam_estimate(1).keys)
        # The solve has ended: the stream sends the final estimate and ends by itself.
        streamed = call("WatchSlamEstimate", {"robot_id": 1})
        assert streamed["state"] == "SLAM_STATE_DONE" and streamed["values"] == estimate["values"]
        landmarks = call("LandmarkRound", {"round_id": 1})["posteriors"]
        assert [p["posterior"] for p in landmarks] == [
            list(p.posterior) for p in gw.landmark_round(1).posteriors
        ]


def test_a_place_query_whose_owner_is_frozen_past_the_deadline_is_deadline_exceeded(running: Running) -> None:
    s = running.seeded[0]
    owner = TABLE.owners[nearest_cluster(s.x)]
    proc = running.swarm.find("place-owner", owner).proc
    os.kill(proc.pid, signal.SIGSTOP)
    try:
        with running.swarm.gateway_client(10.0) as gw:
            request_ = gateway_pb2.PlaceQueryRequest(descriptor=s.x.tolist())
            with pytest.raises(grpc.RpcError) as info:
                gw.stub.PlaceQuery(request_, timeout=0.5)
            assert info.value.code() == grpc.StatusCode.DEADLINE_EXCEEDED
    finally:
        os.kill(proc.pid, signal.SIGCONT)


def test_the_stream_metadata_says_subscribed(running: Running) -> None:
    with running.swarm.gateway_client(10.0) as gw:
        call = gw.stub.WatchPlaceReports(gateway_pb2.WatchRequest())
        try:
            assert dict(call.initial_metadata()).get(SUBSCRIBED_METADATA) == "1"
        finally:
            call.cancel()


def _cli(running: Running, *args: str, connect: str) -> subprocess.CompletedProcess[str]:
    """``python -m swarmrec <args> --json`` as a separate process, to the gateway or the router."""
    return subprocess.run(
        [sys.executable, "-m", "swarmrec", *args, "--json", "--connect", connect,
         "--swarm", running.swarm.spec_swarm, "--pki-dir", str(running.swarm.pki_dir)],
        capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip


@pytest.mark.parametrize("transport", ["gateway", "zenoh"])
def test_the_cli_asks_every_method_through_either_transport(running: Running, transport: str) -> None:
    connect = running.swarm.gateway_address if transport == "gateway" else running.swarm.endpoint
    s = running.seeded[4]
    np.save(running.tmp / "x.npy", s.x)
    png, _bgr = _png(5)
    (running.tmp / "view.png").write_bytes(png)
    answers = {
        "clusters": _cli(running, "clusters", connect=connect),
        "place": _cli(running, "place-query", "--descriptor", str(running.tmp / "x.npy"), "--exclude-robot",
                      str(s.robot), connect=connect),
        "image": _cli(running, "place-query", "--image", str(running.tmp / "view.png"), connect=connect),
        "closures": _cli(running, "loop-closures", "1", "--method", "dvpr", connect=connect),
        "team": _cli(running, "slam-team", connect=connect),
        "estimate": _cli(running, "slam-estimate", "1", "--watch", connect=connect),
        "map": _cli(running, "slam-map", connect=connect),
        "round": _cli(running, "landmark-round", "1", connect=connect),
    }  # fmt: skip
    for name, done in answers.items():
        assert done.returncode == 0, (name, done.stderr)
    out = {name: done.stdout for name, done in answers.items()}
    with running.swarm.gateway_client(10.0) as gw:
        assert json.loads(out["clusters"])["table_json"] == gw.cluster_table().table_json
        match = json.loads(out["place"])["match"]
        expected = offline_match(running, s.x, s.robot)
        assert (
            expected is not None and (match.get("robot_id", 0), match.get("frame_index", 0)) == expected[:2]
        )
        described = DescriptorModel().describe_frames(_bgr)[0]
        assert np.allclose(json.loads(out["image"])["descriptor"], described, atol=1e-5)
        closures = json.loads(out["closures"])
        assert [c["query_frame"] for c in closures] == [
            c.query_frame_index for c in gw.place_loop_closures(1)
        ]
        assert [t["state"] for t in json.loads(out["team"])] == ["SLAM_STATE_DONE"] * N_ROBOTS
        # The solve has ended: --watch prints the final estimate and ends.
        assert [json.loads(line)["state"] for line in out["estimate"].splitlines()] == ["SLAM_STATE_DONE"]
        assert [int(k) for k in json.loads(out["map"])["keys"]] == list(gw.slam_map().keys)
        posteriors = json.loads(out["round"])["posteriors"]
        assert [p["posterior"] for p in posteriors] == [
            list(p.posterior) for p in gw.landmark_round(1).posteriors
        ]
