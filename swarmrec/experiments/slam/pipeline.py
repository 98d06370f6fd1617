"""The live distributed solve through a swarm: the pipeline behind ``swarmrec slam run``.

``main(settings, deployment)`` wires the stages and knows nothing of where the swarm runs::

    prepare   the robot folder (or a simulated world written as one: out/input/<r>.g2o)
    deploy    one slam service per robot on the deployment given (the CLI's: local
              processes), each reading only its own <r>.g2o
    solve     as the operator: load every robot, start every robot, then only watch
              (status): the robots take their turns and talk to each other on their own
    collect   each robot's status, estimate and the estimates it sent; the services'
              counters (bytes per link, floats by the 9/6 model)
    report    iterations per stage, cost, ATE*/ARE* against gtsam's centralized
              Gauss-Newton, bytes measured against the model, the check that every
              message, report and estimate equals run_dgs's in one process, g2o files
              and the Fig. 4-style map (:mod:`.report`)

A robot that vanishes mid-solve (killed, or silent for ``peer_timeout_s``) ends
the solve: the survivors agree on the last position every robot completed and
answer with their estimates there; the report says so and checks those
estimates against run_dgs's estimate after that very iteration.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

# protobuf ships no type stubs (see swarmrec/runtime/runner.py for the two codes).
from google.protobuf.message import Message  # type: ignore[import-untyped, unused-ignore]
from tqdm import tqdm

from swarmrec.client import ZenohClient
from swarmrec.deployments.base import Deployment, DeploymentError, SwarmSpec, running
from swarmrec.errors import CallError
from swarmrec.experiments.slam.report import LiveRecord, LiveSlamSummary, RobotResult, write_report
from swarmrec.experiments.slam.settings import LiveSlamSettings
from swarmrec.runtime import keys
from swarmrec.runtime.settings import BusSettings
from swarmrec.services.registry import WORKLOADS
from swarmrec.services.settings import SlamServiceSettings
from swarmrec.slam.g2o import read_robot_folder, robot_file_name, write_g2o
from swarmrec.slam.graph import PoseGraph
from swarmrec.slam.lie import Pose
from swarmrec.slam.scenarios import Scenario, generate_scenario
from swarmrec.wire import messages as pb
from swarmrec.wire.slam import settings_to_proto

__all__ = ["TERMINAL", "Prepared", "main", "prepare", "solve_live", "swarm_spec"]

#: States a robot's solve ends in.
TERMINAL = frozenset(
    {pb.SlamState.SLAM_STATE_DONE, pb.SlamState.SLAM_STATE_ABORTED, pb.SlamState.SLAM_STATE_FAILED}
)
_POLL_S = 0.2


@dataclass(frozen=True, eq=False)
class Prepared:
    """The robot folder the services read, the team's graph, and the world's truth when simulated."""

    folder: Path
    graph: PoseGraph
    truth: dict[int, Pose] | None
    scenario: Scenario | None


def prepare(settings: LiveSlamSettings) -> Prepared:
    """The robot folder: ``settings.folder``, or the simulated world written to ``out/input``."""
    if settings.folder is not None:
        return Prepared(settings.folder, read_robot_folder(settings.folder).graph, None, None)
    scenario = generate_scenario(settings.scenario())
    folder = settings.out / "input"
    folder.mkdir(parents=True, exist_ok=True)
    for old in folder.glob("*.g2o"):
        old.unlink()
    graph = scenario.graph
    for robot in graph.robots:
        write_g2o(
            folder / robot_file_name(robot),
            graph,
            keys=graph.robot_keys(robot),
            edges=graph.robot_edges(robot),
        )
    # Read back as the robots will: 17 significant digits give every float64 back exactly.
    return Prepared(folder, read_robot_folder(folder).graph, scenario.truth, scenario)


def swarm_spec(settings: LiveSlamSettings, folder: Path, robots: int) -> SwarmSpec:
    """One slam service per robot, all reading the same folder (each only its own file), and
    the swarm's gateway (its live view draws the team's solve as it runs)."""
    bus = BusSettings(swarm=settings.swarm, n_robots=robots, request_timeout_s=settings.request_timeout_s)
    parts = (SlamServiceSettings(slam_folder=folder.resolve(), slam_peer_timeout_s=settings.peer_timeout_s),)
    return SwarmSpec(bus, WORKLOADS["slam"], parts, workload="slam")


M = TypeVar("M", bound=Message)


def _call(client: ZenohClient, swarm: str, robot: int, endpoint: str, request: Message, reply: type[M]) -> M:
    return client.call(keys.endpoint(swarm, "slam", robot, endpoint), request, reply, target_robot=None)


def solve_live(
    client: ZenohClient,
    settings: LiveSlamSettings,
    robots: int,
    *,
    on_status: Callable[[dict[int, pb.SlamStatus | None]], None] | None = None,
) -> tuple[int, dict[int, RobotResult], float]:
    """Load and start every robot, watch until each has ended (or is gone); the solve id, what each
    robot answered at the end, and the wall time of the solve. ``on_status`` sees every poll."""
    swarm = settings.swarm
    team = range(robots)
    before = [_call(client, swarm, r, "status", pb.SlamStatusRequest(), pb.SlamStatus) for r in team]
    solve_id = max(s.solve_id for s in before) + 1
    load = pb.SlamLoadRequest(solve_id=solve_id, settings=settings_to_proto(settings.solver))
    for r in team:
        _call(client, swarm, r, "load", load, pb.SlamProblem)
    t0 = time.perf_counter()
    for r in team:
        _call(client, swarm, r, "solve", pb.SlamSolveRequest(solve_id=solve_id), pb.SlamSolveStarted)
    deadline = time.monotonic() + settings.solve_timeout_s
    statuses: dict[int, pb.SlamStatus | None] = {}
    with tqdm(
        # (tqdm puts ", " before the postfix: "solving, rotation stage, iteration 3; 0:running, ...")
        desc="solving",
        disable=not settings.progress,
        leave=False,
        bar_format="{desc}{postfix}",
    ) as bar:
        while True:
            for r in team:
                try:
                    statuses[r] = _call(client, swarm, r, "status", pb.SlamStatusRequest(), pb.SlamStatus)
                except CallError:
                    statuses[r] = None  # gone (killed) or not answering
            if on_status is not None:
                on_status(statuses)
            live = [s for s in statuses.values() if s is not None]
            if live:
                slowest = min(live, key=lambda s: (s.linearisation, s.iteration))
                stage = (
                    "rotation stage"
                    if slowest.linearisation == 0
                    else f"pose stage (linearisation {slowest.linearisation})"
                )
                bar.set_postfix_str(
                    f"{stage}, iteration {slowest.iteration}; "
                    + ", ".join(
                        f"{r}:{pb.SlamState.Name(s.state)[11:].lower()}" for r, s in statuses.items() if s
                    )
                )
            if live and all(s.state in TERMINAL for s in live):
                break
            if not live:
                raise DeploymentError("no slam service answers any more")
            if time.monotonic() > deadline:
                raise DeploymentError(
                    f"the solve did not end within {settings.solve_timeout_s:g} s (solve_timeout_s)"
                )
            time.sleep(_POLL_S)
    wall = time.perf_counter() - t0
    results: dict[int, RobotResult] = {}
    for r in team:
        status = statuses.get(r)
        if status is None:
            continue
        estimate = _call(client, swarm, r, "estimate", pb.SlamEstimateRequest(), pb.SlamEstimate)
        steps: list[pb.SlamStep] = []
        while True:
            page = _call(client, swarm, r, "sent", pb.SlamSentRequest(offset=len(steps)), pb.SlamSentPage)
            steps.extend(page.steps)
            if len(steps) >= page.total or not page.steps:
                break
        results[r] = RobotResult(r, status, estimate, steps)
    return solve_id, results, wall


def main(
    settings: LiveSlamSettings,
    deployment: Deployment,
    *,
    on_status: Callable[[dict[int, pb.SlamStatus | None]], None] | None = None,
    swarm_hook: Callable[[Deployment], None] | None = None,
) -> LiveSlamSummary:
    """Prepare, deploy, solve live, collect, report; returns the summary (``swarmrec slam run``).

    ``on_status`` sees every poll of the robots' status and ``swarm_hook`` the swarm once it
    is up (tests use them to kill a robot mid-solve and to send it bad messages)."""
    t_start = time.perf_counter()
    out = settings.out
    out.mkdir(parents=True, exist_ok=True)
    prepared = prepare(settings)
    robots = len(prepared.graph.robots)
    spec = swarm_spec(settings, prepared.folder, robots)
    timings = {"prepare_s": time.perf_counter() - t_start}
    with running(deployment, spec, progress=settings.progress, timings=timings) as session:
        if swarm_hook is not None:
            swarm_hook(deployment)
        with deployment.client(settings.request_timeout_s) as client:
            solve_id, results, timings["solve_s"] = solve_live(client, settings, robots, on_status=on_status)
        t0 = time.perf_counter()
        metrics = deployment.metrics()
        timings["scrape_s"] = time.perf_counter() - t0
    exit_codes = session.exit_codes
    record = LiveRecord(
        settings=settings,
        folder=str(prepared.folder),
        graph=prepared.graph,
        truth=prepared.truth,
        scenario=prepared.scenario,
        solve_id=solve_id,
        results=results,
        metrics=metrics,
        exit_codes=exit_codes,
        deployment=deployment.description,
        timings=timings,
    )
    return write_report(record, t_start)
