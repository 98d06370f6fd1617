"""The distributed Gauss-Seidel as slam services: a real router, one process per robot.

The reference is run_dgs in this process on the same robot folder (the shared
blocks world, 4 robots, read by each service from its own file only):

* the live solve sends exactly its messages (per sender, in order, every float bit for
  bit), reports exactly its reports and ends at exactly its estimate; the bytes each
  robot counts per peer are the protobuf sizes of those messages, built here by hand;
  an operator's put on a robot's inbox is stopped by the router's access control;
* a robot killed mid-solve: the others end, agree on the last iteration every robot
  completed, answer run_dgs's estimate after that very iteration, and say so;
* bad input on a robot's inbox and endpoints (insecure mode, so the attacks reach it):
  every message is refused and counted by reason, every bad request answered with its
  code, and the solve that follows is still run_dgs's, bit for bit.
"""

from __future__ import annotations

import math
import os
import signal
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
import zenoh

from swarmrec.deployments.local import LocalDeployment
from swarmrec.experiments.slam.pipeline import solve_live
from swarmrec.experiments.slam.report import RobotResult, check_against_reference
from swarmrec.experiments.slam.settings import LiveSlamSettings
from swarmrec.runtime import keys
from swarmrec.services.settings import SlamServiceSettings
from swarmrec.slam.dgs import DgsSettings, DistributedResult, run_dgs
from swarmrec.slam.g2o import read_robot_folder
from swarmrec.slam.graph import PoseGraph
from swarmrec.slam.lie import Pose
from swarmrec.slam.messages import DgsMessage, StepReport
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import schema_name
from tests.conftest import SHARED_DATA, shared
from tests.integration.conftest import running_swarm, swarm_name
from tests.integration.support import endpoint_key, metric, metrics_url, protobuf, request, wait_until

ROBOTS = 4
STAGE = {"rotation": pb.SlamStage.SLAM_STAGE_ROTATION, "pose": pb.SlamStage.SLAM_STAGE_POSE}
STEP = schema_name(pb.SlamStep)


@dataclass(frozen=True)
class Team:
    folder: Path
    graph: PoseGraph


@pytest.fixture(scope="module")
def team() -> Team:
    folder = shared(SHARED_DATA / "dgs_blocks_world" / "4robots")
    return Team(folder, read_robot_folder(folder).graph)


@pytest.fixture
def slam_swarm(request: pytest.FixtureRequest, tmp_path: Path, team: Team) -> Iterator[LocalDeployment]:
    security = "insecure" if "bad_input" in request.node.name else "mtls"
    parts = SlamServiceSettings(slam_folder=team.folder, slam_peer_timeout_s=4.0)
    with running_swarm(
        tmp_path,
        swarm_name(request),
        parts,
        robots=ROBOTS,
        kinds=["slam"],
        swarm_kinds=(),
        security=security,  # type: ignore[arg-type]
        request_timeout_s=5.0,
    ) as swarm:
        yield swarm


def floats(step: pb.SlamStep) -> dict[int, bytes]:
    """A SlamStep's estimates by key, each key's doubles as raw bytes."""
    size = len(step.values) // max(len(step.keys), 1)
    return {
        k: struct.pack(f"<{size}d", *step.values[i * size : (i + 1) * size]) for i, k in enumerate(step.keys)
    }


def reference_floats(message: DgsMessage) -> dict[int, bytes]:
    return {k: struct.pack(f"<{len(v)}d", *v) for k, v in message.estimates.items()}


def pose_bytes(values: list[float]) -> bytes:
    return struct.pack(f"<{len(values)}d", *values)


def expected_pose_bytes(pose: Pose) -> bytes:
    return pose.rotation.tobytes() + pose.translation.tobytes()


def assert_is_reference(
    results: dict[int, RobotResult], reference: DistributedResult, graph: PoseGraph
) -> None:
    """Every robot's messages, reports and final estimate equal run_dgs's, bit for bit (compared
    field by field here, not through the report's own check)."""
    for r, res in results.items():
        assert res.status.state == pb.SlamState.SLAM_STATE_DONE and res.status.converged
        mine = [m for m in reference.messages if m.sender == r]
        changes = {(x.linearisation, x.iteration): x.change for x in reference.reports if x.robot == r}
        assert len(res.sent) == len(mine)
        for step, m in zip(res.sent, mine, strict=True):
            head = (
                step.sender_robot_id,
                step.receiver_robot_id,
                step.stage,
                step.linearisation,
                step.iteration,
            )
            assert head == (m.sender, m.receiver, STAGE[m.stage], m.linearisation, m.iteration)
            assert floats(step) == reference_floats(m)
            assert step.solved
            assert struct.pack("<d", step.change) == struct.pack(
                "<d", changes[(m.linearisation, m.iteration)]
            )
        reports = [x for x in reference.reports if x.robot == r]
        assert [(x.stage, x.linearisation, x.iteration, x.solved) for x in res.status.reports] == [
            (STAGE[x.stage], x.linearisation, x.iteration, x.solved) for x in reports
        ]
        assert [struct.pack("<d", x.change) for x in res.status.reports] == [
            struct.pack("<d", x.change) for x in reports
        ]
        assert list(res.estimate.keys) == list(graph.robot_keys(r))
        values = list(res.estimate.values)
        for i, key in enumerate(res.estimate.keys):
            assert pose_bytes(values[12 * i : 12 * (i + 1)]) == expected_pose_bytes(reference.poses[key])


def wire_size(message: DgsMessage, report: StepReport, solve_id: int) -> int:
    """The payload of the SlamStep that carries ``message``, built here with protobuf directly."""
    keys_sorted = sorted(message.estimates)
    step = pb.SlamStep(
        solve_id=solve_id,
        sender_robot_id=message.sender,
        receiver_robot_id=message.receiver,
        stage=STAGE[message.stage],  # type: ignore[arg-type]
        linearisation=message.linearisation,
        iteration=message.iteration,
        solved=report.solved,
        change=report.change,
        keys=keys_sorted,
        values=[v for k in keys_sorted for v in message.estimates[k]],
    )
    return len(step.SerializeToString())


def test_the_live_solve_sends_run_dgs_messages_bit_for_bit_and_counts_their_bytes(
    slam_swarm: LocalDeployment, team: Team, tmp_path: Path
) -> None:
    settings = LiveSlamSettings(
        out=tmp_path / "out", folder=team.folder, swarm=slam_swarm.spec_swarm, progress=False
    )
    reference = run_dgs(team.graph, DgsSettings())
    with slam_swarm.client(10.0) as client:
        # The operator may drive solves but never speak for a robot: the router drops this.
        client.session.put(
            keys.endpoint(slam_swarm.spec_swarm, "slam", 0, "inbox/1"),
            pb.SlamStep(solve_id=1, sender_robot_id=1, receiver_robot_id=0).SerializeToString(),
            encoding=protobuf(STEP),
        )
        solve_id, results, _wall = solve_live(client, settings, ROBOTS)
    assert sorted(results) == list(range(ROBOTS))
    assert_is_reference(results, reference, team.graph)
    statuses = [res.status for res in results.values()]
    assert {tuple(s.order) for s in statuses} == {reference.order}
    assert {s.rejected for s in statuses} == {0}
    # Bytes per peer and stage as each robot counted them: the sizes of exactly those messages.
    reports = {(x.robot, x.linearisation, x.iteration): x for x in reference.reports}
    for r in range(ROBOTS):
        url = metrics_url(slam_swarm.find("slam", r))
        for peer in sorted({m.receiver for m in reference.messages if m.sender == r}):
            for stage in ("rotation", "pose"):
                sent = [m for m in reference.messages if (m.sender, m.receiver, m.stage) == (r, peer, stage)]
                expected = sum(
                    wire_size(m, reports[(r, m.linearisation, m.iteration)], solve_id) for m in sent
                )
                labels = {"peer": str(peer), "stage": stage, "carries": "estimates"}
                assert metric(url, "swarmrec_slam_sent_bytes_total", **labels) == expected
                assert metric(url, "swarmrec_slam_sent_messages_total", **labels) == len(sent)
                # The model: 9 floats a shared key in the rotation stage, 6 in a pose stage.
                n_keys = len({k for m in sent for k in m.estimates})
                assert (
                    metric(url, "swarmrec_slam_sent_floats_total", peer=str(peer), stage=stage)
                    == len(sent) * (9 if stage == "rotation" else 6) * n_keys
                )
        assert metric(url, "swarmrec_slam_rejected_total") == 0
    # The report's own check and summary agree with what was compared above.
    check = check_against_reference(results, reference, team.graph)
    assert check.identical and check.messages_live == len(reference.messages)


def test_a_robot_killed_mid_solve_leaves_the_others_at_the_last_consistent_estimate(
    slam_swarm: LocalDeployment, team: Team, tmp_path: Path
) -> None:
    solver = DgsSettings(eta_rotation=1e-4, eta_pose=1e-4)
    settings = LiveSlamSettings(
        out=tmp_path / "out", folder=team.folder, swarm=slam_swarm.spec_swarm, progress=False, solver=solver
    )
    reference = run_dgs(team.graph, solver, trace=True)
    trace = {(t.linearisation, t.iteration): t.poses for t in reference.trace}
    victim = slam_swarm.find("slam", 2)
    killed_at: list[tuple[int, int]] = []

    def kill_in_the_first_pose_stage(statuses: dict[int, pb.SlamStatus | None]) -> None:
        zero = statuses.get(0)
        if not killed_at and zero is not None and (zero.linearisation, zero.iteration) >= (1, 5):
            killed_at.append((zero.linearisation, zero.iteration))
            os.kill(victim.proc.pid, signal.SIGKILL)

    with slam_swarm.client(10.0) as client:
        _, results, wall = solve_live(client, settings, ROBOTS, on_status=kill_in_the_first_pose_stage)
    assert killed_at, "the solve ended before the robot could be killed"
    assert sorted(results) == [0, 1, 3]
    # Its liveliness token went away at once: the survivors did not wait for the 4 s peer timeout
    # (their reasons name the token), let alone hang.
    assert wall < 30.0
    assert all("liveliness" in res.status.reason for res in results.values()), [
        res.status.reason for res in results.values()
    ]
    positions = {(res.estimate.linearisation, res.estimate.iteration) for res in results.values()}
    assert len(positions) == 1, positions
    (position,) = positions
    last = (reference.stages[-1].linearisation, reference.stages[-1].iterations)
    assert (1, 1) <= position < last  # ended early, in the pose stages
    for r, res in results.items():
        status = res.status
        assert status.state == pb.SlamState.SLAM_STATE_ABORTED
        assert list(status.vanished_robot_ids) == [2]
        assert (status.consistent_linearisation, status.consistent_iteration) == position
        assert (
            "robots [2]" in status.reason
            and f"linearisation {position[0]}, iteration {position[1]}" in status.reason
        )
        values = list(res.estimate.values)
        for i, key in enumerate(res.estimate.keys):
            assert pose_bytes(values[12 * i : 12 * (i + 1)]) == expected_pose_bytes(trace[position][key]), (
                r,
                key,
            )
        # What it sent before the end is run_dgs's, message for message.
        mine = [m for m in reference.messages if m.sender == r]
        assert all(floats(s) == reference_floats(m) for s, m in zip(res.sent, mine, strict=False))
        assert len(res.sent) <= len(mine)
    check = check_against_reference(results, reference, team.graph)
    assert check.identical, check.differences


def put_step(session: zenoh.Session, swarm: str, sender_key: int, payload: bytes, schema: str = STEP) -> None:
    session.put(
        keys.endpoint(swarm, "slam", 0, f"inbox/{sender_key}"),
        payload,
        encoding=protobuf(schema),
        congestion_control=zenoh.CongestionControl.BLOCK,
    )


def test_bad_input_is_refused_and_counted_and_the_solve_is_still_run_dgs(
    slam_swarm: LocalDeployment, team: Team, tmp_path: Path
) -> None:
    swarm = slam_swarm.spec_swarm
    url = metrics_url(slam_swarm.find("slam", 0))
    reference = run_dgs(team.graph, DgsSettings())
    with_zero = [e for e in team.graph.separators() if 0 in {team.graph.robot_of(k) for k in e.keys}]
    shared_keys = sorted({k for e in with_zero for k in e.keys if team.graph.robot_of(k) == 1})
    other_key = next(k for k in team.graph.robot_keys(1) if k not in shared_keys)
    settings = LiveSlamSettings(out=tmp_path / "out", folder=team.folder, swarm=swarm, progress=False)
    with slam_swarm.client(10.0) as client:
        session = client.session

        def answer(robot: int, endpoint: str, msg: object) -> str:
            return request(session, endpoint_key(slam_swarm, "slam", robot, endpoint), msg).code  # type: ignore[arg-type]

        # Endpoints: a clear error reply for each bad request.
        assert answer(0, "estimate", pb.SlamEstimateRequest()) == "ERROR_CODE_NOT_FOUND"
        assert answer(0, "load", pb.SlamLoadRequest(solve_id=0)) == "ERROR_CODE_INVALID_ARGUMENT"
        bad_gamma = pb.SlamLoadRequest(solve_id=1, settings=pb.SlamSolverSettings(gamma=2.5))
        assert answer(0, "load", bad_gamma) == "ERROR_CODE_INVALID_ARGUMENT"
        huge = pb.SlamLoadRequest(solve_id=1, settings=pb.SlamSolverSettings(max_iterations=10**9))
        assert answer(0, "load", huge) == "ERROR_CODE_INVALID_ARGUMENT"
        assert answer(
            0, "load", pb.SlamLoadRequest(solve_id=1, settings=pb.SlamSolverSettings(mode="x"))
        ) == ("ERROR_CODE_INVALID_ARGUMENT")
        assert answer(0, "solve", pb.SlamSolveRequest(solve_id=9)) == "ERROR_CODE_NOT_FOUND"
        assert answer(0, "load", pb.SlamLoadRequest(solve_id=1)) == ""  # a good one, for the puts below
        assert (
            answer(0, "load", pb.SlamLoadRequest(solve_id=1)) == "ERROR_CODE_INVALID_ARGUMENT"
        )  # same id again
        assert answer(0, "sent", pb.SlamSentRequest(offset=5)) == "ERROR_CODE_INVALID_ARGUMENT"

        # Inbox: every kind of bad message, from "robot 1", for solve 1 at its first iteration.
        def step(**fields: object) -> bytes:
            base: dict[str, object] = {
                "solve_id": 1,
                "sender_robot_id": 1,
                "receiver_robot_id": 0,
                "stage": pb.SlamStage.SLAM_STAGE_ROTATION,
                "linearisation": 0,
                "iteration": 1,
                "solved": True,
                "change": 0.5,
                "keys": shared_keys,
                "values": [0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0] * len(shared_keys),
            }
            return bytes(pb.SlamStep(**(base | fields)).SerializeToString())  # type: ignore[arg-type]

        eye = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
        attacks = [
            (step(keys=[*shared_keys, other_key], values=eye * (len(shared_keys) + 1)), "not_shared"),
            (
                step(
                    stage=pb.SlamStage.SLAM_STAGE_POSE, linearisation=1, values=[0.0] * 6 * len(shared_keys)
                ),
                "wrong_stage",
            ),
            (step(values=[math.nan] + eye[1:] + eye * (len(shared_keys) - 1)), "bad_values"),
            (step(values=eye * (len(shared_keys) * 1000)), "bad_values"),  # a huge count of values
            (step(keys=[*shared_keys, *shared_keys], values=eye * 2 * len(shared_keys)), "bad_values"),
            (step(iteration=7), "out_of_turn"),
            (step(solve_id=2), "other_solve"),
            (step(sender_robot_id=3), "not_in_team"),  # put on inbox/1 but claims robot 3
            (step(change=math.nan), "bad_report"),
            (step(keys=[], values=[]), "missing_estimates"),
        ]
        for payload, _reason in attacks:
            put_step(session, swarm, 1, payload)
        put_step(session, swarm, 1, b"\x0a\xff\xff", STEP)  # does not decode
        put_step(session, swarm, 1, b"\x00" * (1 << 21), STEP)  # above max_message_bytes
        put_step(session, swarm, 1, step(), schema_name(pb.SlamControl))  # another schema
        expected: dict[str, int] = {}
        for _payload, reason in attacks:
            expected[reason] = expected.get(reason, 0) + 1

        def counted() -> bool:
            by_reason = all(
                metric(url, "swarmrec_slam_rejected_total", reason=reason) == n
                for reason, n in expected.items()
            )
            codes = (
                metric(
                    url, "swarmrec_rejected_requests_total", endpoint="inbox/*", code="ERROR_CODE_MALFORMED"
                )
                == 1
                and metric(
                    url, "swarmrec_rejected_requests_total", endpoint="inbox/*", code="ERROR_CODE_TOO_LARGE"
                )
                == 1
                and metric(
                    url,
                    "swarmrec_rejected_requests_total",
                    endpoint="inbox/*",
                    code="ERROR_CODE_INVALID_ARGUMENT",
                )
                == len(attacks) + 1
            )
            return by_reason and codes

        wait_until(counted, 15.0, "every bad message refused and counted by reason")
        status = pb.SlamStatus.FromString(
            request(session, endpoint_key(slam_swarm, "slam", 0, "status"), pb.SlamStatusRequest()).ok or b""
        )
        assert (status.state, status.rejected) == (pb.SlamState.SLAM_STATE_LOADED, len(attacks))

        # Nothing changed: a solve now (solve 2, every robot loaded afresh) is run_dgs's, bit for bit.
        _, results, _ = solve_live(client, settings, ROBOTS)
    assert_is_reference(results, reference, team.graph)
