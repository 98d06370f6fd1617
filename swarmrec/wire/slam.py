"""Conversion between the live distributed Gauss-Seidel (:mod:`swarmrec.slam.live`) and the v1 slam messages.

Estimates travel as float64 (``repeated double``, packed): both ends of a
separator must linearise at bit-identical values, so nothing is rounded on
the way. Keys are gtsam Symbols as ``fixed64`` (a Symbol's top byte is its
character, so a varint would take 9 or 10 bytes). A received message is
checked here as far as its own content goes (its stage, each key once, 9 or 6
finite doubles per key) and refused with :class:`~swarmrec.slam.errors.TurnRejected`;
whether it fits the receiving robot (team, turn, shared keys) is
:class:`~swarmrec.slam.live.TeamRobot`'s to say.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping

import numpy as np

from swarmrec.errors import ConfigError
from swarmrec.slam.dgs import DgsSettings, StageSummary
from swarmrec.slam.errors import MessageError, TurnRejected
from swarmrec.slam.lie import Pose
from swarmrec.slam.live import Abort, Hello, Position, Turn, stage_of
from swarmrec.slam.messages import FLOATS_PER_ESTIMATE, DgsMessage, Stage, StepReport
from swarmrec.wire import messages as pb

__all__ = [
    "POSE_FLOATS",
    "abort_to_proto",
    "control_from_proto",
    "estimate_from_proto",
    "estimate_to_proto",
    "hello_to_proto",
    "report_from_proto",
    "report_to_proto",
    "settings_from_proto",
    "settings_to_proto",
    "stage_summary_from_proto",
    "stage_summary_to_proto",
    "stage_to_proto",
    "turn_from_proto",
    "turn_to_proto",
]

#: Doubles per pose in a SlamEstimate: the rotation row by row, then the translation.
POSE_FLOATS = 12

_STAGES: dict[Stage, int] = {
    "rotation": pb.SlamStage.SLAM_STAGE_ROTATION,
    "pose": pb.SlamStage.SLAM_STAGE_POSE,
}


def stage_to_proto(stage: Stage) -> int:
    return _STAGES[stage]


def _stage_from_proto(value: int, linearisation: int) -> Stage:
    for stage, wire in _STAGES.items():
        if wire == value:
            if stage != stage_of(linearisation):
                raise TurnRejected(
                    "wrong_stage",
                    f"a {stage} message at linearisation {linearisation} "
                    "(0 is the rotation stage, 1, 2, ... the pose stages)",
                )
            return stage
    raise TurnRejected("wrong_stage", f"stage {value} is neither rotation nor pose")


# --- between robots ---------------------------------------------------------------------


def turn_to_proto(turn: Turn) -> pb.SlamStep:
    """The wire form of a turn; the estimates' keys ascending, their floats packed in that order."""
    msg = pb.SlamStep(
        solve_id=turn.solve_id,
        sender_robot_id=turn.sender,
        receiver_robot_id=turn.receiver,
        stage=stage_to_proto(turn.stage),  # type: ignore[arg-type]  # an enum value
        linearisation=turn.linearisation,
        iteration=turn.iteration,
        solved=turn.solved,
        change=turn.change,
    )
    if turn.message is not None:
        keys = sorted(turn.message.estimates)
        msg.keys.extend(keys)
        msg.values.extend(v for k in keys for v in turn.message.estimates[k])
    return msg


def turn_from_proto(msg: pb.SlamStep) -> Turn:
    """A received SlamStep as a :class:`Turn`; TurnRejected when its own content is bad."""
    stage = _stage_from_proto(msg.stage, msg.linearisation)
    if msg.iteration < 1:
        raise TurnRejected("wrong_stage", f"iteration {msg.iteration}: iterations count from 1")
    message = None
    if msg.keys or msg.values:
        size = FLOATS_PER_ESTIMATE[stage]
        keys = list(msg.keys)
        if len(set(keys)) != len(keys):
            raise TurnRejected("bad_values", f"{len(keys) - len(set(keys))} keys appear more than once")
        if len(msg.values) != size * len(keys):
            raise TurnRejected(
                "bad_values",
                f"{len(msg.values)} values for {len(keys)} keys of the {stage} stage ({size} a key expected)",
            )
        values = list(msg.values)
        estimates = {k: tuple(values[i * size : (i + 1) * size]) for i, k in enumerate(keys)}
        try:
            message = DgsMessage(
                msg.sender_robot_id, msg.receiver_robot_id, stage, msg.linearisation, msg.iteration, estimates
            )
        except MessageError as e:
            raise TurnRejected("bad_values", str(e)) from None
    return Turn(
        msg.solve_id,
        msg.sender_robot_id,
        msg.receiver_robot_id,
        msg.linearisation,
        msg.iteration,
        msg.solved,
        msg.change,
        message,
    )


def _counts(counts: Mapping[int, int]) -> list[pb.SeparatorCount]:
    return [pb.SeparatorCount(robot_id=r, separators=n) for r, n in sorted(counts.items())]


def hello_to_proto(hello: Hello) -> pb.SlamControl:
    return pb.SlamControl(
        solve_id=hello.solve_id,
        sender_robot_id=hello.sender,
        receiver_robot_id=hello.receiver,
        hello=pb.SlamHello(separators=_counts(hello.separators)),
    )


def abort_to_proto(abort: Abort) -> pb.SlamControl:
    return pb.SlamControl(
        solve_id=abort.solve_id,
        sender_robot_id=abort.sender,
        receiver_robot_id=abort.receiver,
        abort=pb.SlamAbort(
            vanished_robot_ids=list(abort.vanished),
            consistent_linearisation=abort.consistent[0],
            consistent_iteration=abort.consistent[1],
            reason=abort.reason,
        ),
    )


def control_from_proto(msg: pb.SlamControl) -> Hello | Abort:
    """A received SlamControl; TurnRejected for one that says nothing or counts a robot twice."""
    body = msg.WhichOneof("body")
    if body == "hello":
        robots = [c.robot_id for c in msg.hello.separators]
        if len(set(robots)) != len(robots):
            raise TurnRejected("bad_hello", "a hello names a robot twice")
        counts = {c.robot_id: c.separators for c in msg.hello.separators}
        return Hello(msg.solve_id, msg.sender_robot_id, msg.receiver_robot_id, counts)
    if body == "abort":
        a = msg.abort
        return Abort(
            msg.solve_id,
            msg.sender_robot_id,
            msg.receiver_robot_id,
            tuple(sorted(set(a.vanished_robot_ids))),
            (a.consistent_linearisation, a.consistent_iteration),
            a.reason[:500],
        )
    raise TurnRejected("bad_hello", "a control message with neither hello nor abort")


# --- the operator's view ------------------------------------------------------------------


def settings_to_proto(settings: DgsSettings) -> pb.SlamSolverSettings:
    msg = pb.SlamSolverSettings(
        mode=settings.mode,
        order=settings.order,
        eta_rotation=settings.eta_rotation,
        eta_pose=settings.eta_pose,
        max_iterations=settings.max_iterations,
        pose_linearisations=settings.pose_linearisations,
    )
    if settings.gamma is not None:
        msg.gamma = settings.gamma
    return msg


def settings_from_proto(msg: pb.SlamSolverSettings) -> DgsSettings:
    """The solver's settings; ConfigError names what is wrong."""
    default = DgsSettings()
    gamma = msg.gamma if msg.HasField("gamma") else None
    values = {
        "eta_rotation": msg.eta_rotation if msg.HasField("eta_rotation") else default.eta_rotation,
        "eta_pose": msg.eta_pose if msg.HasField("eta_pose") else default.eta_pose,
    }
    if not all(math.isfinite(v) for v in values.values()) or (gamma is not None and not math.isfinite(gamma)):
        raise ConfigError("gamma and the etas must be finite numbers")
    return DgsSettings(
        mode=msg.mode or default.mode,  # type: ignore[arg-type]  # checked by DgsSettings
        order=msg.order or default.order,  # type: ignore[arg-type]  # checked by DgsSettings
        gamma=gamma,
        eta_rotation=values["eta_rotation"],
        eta_pose=values["eta_pose"],
        max_iterations=msg.max_iterations if msg.HasField("max_iterations") else default.max_iterations,
        pose_linearisations=msg.pose_linearisations
        if msg.HasField("pose_linearisations")
        else default.pose_linearisations,
    )


def report_to_proto(report: StepReport) -> pb.SlamReport:
    return pb.SlamReport(
        stage=stage_to_proto(report.stage),  # type: ignore[arg-type]  # an enum value
        linearisation=report.linearisation,
        iteration=report.iteration,
        solved=report.solved,
        change=report.change,
    )


def report_from_proto(robot: int, msg: pb.SlamReport) -> StepReport:
    """A robot's own step as its status reports it (without the messages it sent)."""
    stage = _stage_from_proto(msg.stage, msg.linearisation)
    return StepReport(robot, stage, msg.linearisation, msg.iteration, msg.solved, msg.change, ())


def stage_summary_to_proto(summary: StageSummary) -> pb.SlamStageSummary:
    return pb.SlamStageSummary(
        stage=stage_to_proto(summary.stage),  # type: ignore[arg-type]  # an enum value
        linearisation=summary.linearisation,
        iterations=summary.iterations,
        converged=summary.converged,
        max_change=list(summary.max_change),
        floats=summary.floats,
    )


def stage_summary_from_proto(msg: pb.SlamStageSummary) -> StageSummary:
    stage = _stage_from_proto(msg.stage, msg.linearisation)
    return StageSummary(
        stage, msg.linearisation, msg.iterations, msg.converged, tuple(msg.max_change), msg.floats
    )


def estimate_to_proto(
    robot: int, solve_id: int, state: int, position: Position, poses: Mapping[int, Pose]
) -> pb.SlamEstimate:
    keys = sorted(poses)
    msg = pb.SlamEstimate(
        robot_id=robot,
        solve_id=solve_id,
        state=state,  # type: ignore[arg-type]  # an enum value
        linearisation=position[0],
        iteration=position[1],
        keys=keys,
    )
    msg.values.extend(_pose_values(poses[k] for k in keys))
    return msg


def _pose_values(poses: Iterable[Pose]) -> list[float]:
    out: list[float] = []
    for pose in poses:
        out.extend(pose.rotation.ravel().tolist())
        out.extend(pose.translation.tolist())
    return out


def estimate_from_proto(msg: pb.SlamEstimate) -> dict[int, Pose]:
    """The poses of a SlamEstimate, bit for bit what the robot holds."""
    keys = list(msg.keys)
    if len(msg.values) != POSE_FLOATS * len(keys) or len(set(keys)) != len(keys):
        raise MessageError(f"an estimate of {len(keys)} keys carries {len(msg.values)} values")
    values = np.asarray(msg.values, dtype=np.float64).reshape(-1, POSE_FLOATS)
    return {k: Pose(v[:9].reshape(3, 3).copy(), v[9:].copy()) for k, v in zip(keys, values, strict=True)}
