"""The live team protocol (swarmrec.slam.live) without a bus: a transport that delivers in any order.

The reference is run_dgs in one process: a team of TeamRobots, each built from its
own g2o file, must send exactly its messages and reports and end at exactly its
estimate, bit for bit, however the transport orders the deliveries; a robot that
vanishes leaves the others at run_dgs's estimate after the last iteration every robot
completed; every message that does not fit is refused and changes nothing.
"""

from __future__ import annotations

import math
import random
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from swarmrec.slam.agent import LocalProblem
from swarmrec.slam.dgs import DgsSettings, run_dgs
from swarmrec.slam.errors import GraphError, TurnRejected
from swarmrec.slam.g2o import read_robot_folder, robot_file_name, write_g2o
from swarmrec.slam.graph import PoseGraph
from swarmrec.slam.keys import pose_key
from swarmrec.slam.lie import Pose
from swarmrec.slam.live import Abort, Hello, Phase, TeamRobot, Turn
from swarmrec.slam.messages import DgsMessage
from swarmrec.wire.slam import turn_from_proto, turn_to_proto
from tests.conftest import SHARED_DATA, shared
from tests.slam_graphs import make_graph

SOLVE = 7
Item = Hello | Turn | Abort


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three robots' own g2o files (written from a known graph, read back as each robot reads them)."""
    graph, _ = make_graph(3, 5, sigma_r=0.05, sigma_t=0.1, seed=4, initial_noise=0.2)
    out = tmp_path_factory.mktemp("team")
    for r in graph.robots:
        write_g2o(out / robot_file_name(r), graph, keys=graph.robot_keys(r), edges=graph.robot_edges(r))
    return out


def team_of(folder: Path, settings: DgsSettings, solve: int = SOLVE) -> dict[int, TeamRobot]:
    files = sorted(folder.glob("[0-9]*.g2o"))
    team = range(len(files))
    return {
        r: TeamRobot(LocalProblem.from_robot_file(folder / robot_file_name(r), r), team, settings, solve)
        for r in team
    }


def run_team(
    robots: dict[int, TeamRobot],
    seed: int,
    *,
    kill: tuple[int, int] | None = None,
    inject: Callable[[dict[int, TeamRobot], int], None] | None = None,
) -> list[str]:
    """Deliver in a seeded random order until nothing moves; ``kill = (robot, after n steps)``
    removes a robot and tells the others. Returns the reasons of refused deliveries."""
    rng = random.Random(seed)
    queue: list[Item] = []
    for robot in robots.values():
        queue += robot.start()
    alive = set(robots)
    refused: list[str] = []
    steps = 0
    while True:
        moved = False
        if queue:
            item = queue.pop(rng.randrange(len(queue)))
            moved = True
            if item.receiver in alive:
                target = robots[item.receiver]
                try:
                    if isinstance(item, Hello):
                        target.receive_hello(item)
                    elif isinstance(item, Turn):
                        target.receive_turn(item)
                    else:
                        queue += target.receive_abort(item)
                except TurnRejected as e:
                    refused.append(e.reason)
        for r in rng.sample(sorted(alive), len(alive)):
            robot = robots[r]
            while robot.advance():
                pass
            if robot.ready():
                queue += robot.step()
                steps += 1
                moved = True
                while robot.advance():
                    pass
                if inject is not None:
                    inject(robots, steps)
                if kill is not None and steps == kill[1]:
                    alive.discard(kill[0])
                    for s in sorted(alive):
                        queue += robots[s].vanish([kill[0]], "killed by the test")
        if not moved:
            return refused


def bits(poses: dict[int, Pose]) -> dict[int, bytes]:
    return {k: p.rotation.tobytes() + p.translation.tobytes() for k, p in poses.items()}


@pytest.mark.parametrize(
    ("mode", "seed"), [("gauss-seidel", 0), ("gauss-seidel", 1), ("jacobi", 2), ("gauss-seidel", 3)]
)
def test_team_sends_run_dgs_messages_and_ends_at_its_estimate_in_any_delivery_order(
    folder: Path, mode: str, seed: int
) -> None:
    settings = DgsSettings(mode=mode, eta_rotation=1e-3, eta_pose=1e-3)  # type: ignore[arg-type]
    reference = run_dgs(read_robot_folder(folder).graph, settings)
    robots = team_of(folder, settings)
    assert run_team(robots, seed) == []
    for r, robot in robots.items():
        assert robot.phase is Phase.DONE and robot.converged
        assert robot.order == reference.order
        assert robot.sent == [m for m in reference.messages if m.sender == r]
        assert robot.reports == [x for x in reference.reports if x.robot == r]
        assert [
            (s.stage, s.linearisation, s.iterations, s.converged, s.max_change) for s in robot.stages
        ] == [(s.stage, s.linearisation, s.iterations, s.converged, s.max_change) for s in reference.stages]
        position, estimate = robot.estimate()
        assert position == (settings.pose_linearisations, reference.stages[-1].iterations)
        assert bits(estimate) == bits({k: reference.poses[k] for k in estimate})


def test_blocks_world_robots_built_from_their_own_files_match_the_shared_graph() -> None:
    # Each robot file lists its separators in its own order; the agents must still build
    # exactly the systems of the partitioned team graph.
    folder = shared(SHARED_DATA / "dgs_blocks_world" / "4robots")
    graph = read_robot_folder(folder).graph
    reference = run_dgs(graph, DgsSettings())
    robots = team_of(folder, DgsSettings())
    assert run_team(robots, 5) == []
    assert reference.order == (0, 2, 1, 3)
    for r, robot in robots.items():
        assert robot.sent == [m for m in reference.messages if m.sender == r]
        assert bits(robot.estimate()[1]) == bits({k: reference.poses[k] for k in graph.robot_keys(r)})


@pytest.mark.parametrize("after", [1, 9, 40, 75])
def test_survivors_of_a_vanished_robot_end_at_run_dgs_estimate_after_the_last_complete_iteration(
    folder: Path, after: int
) -> None:
    settings = DgsSettings(eta_rotation=1e-3, eta_pose=1e-3)
    graph = read_robot_folder(folder).graph
    reference = run_dgs(graph, settings, trace=True)
    trace = {(t.linearisation, t.iteration): t.poses for t in reference.trace}
    robots = team_of(folder, settings)
    run_team(robots, 11, kill=(1, after))
    survivors = [robots[0], robots[2]]
    positions = {robot.estimate()[0] for robot in survivors}
    assert len(positions) == 1  # they agreed
    (position,) = positions
    for robot in survivors:
        assert robot.phase is Phase.ABORTED
        assert robot.vanished == {1}
        assert "killed by the test" in robot.reason and f"iteration {position[1]}" in robot.reason
        expected = graph.poses if position == (0, 0) else trace[position]
        _, estimate = robot.estimate()
        assert bits(estimate) == bits({k: expected[k] for k in estimate})
    # The next iteration was not complete for some survivor: the earliest one named wins.
    following = min(p for p in trace if p > position)
    assert any(len(robot._reports.get(following, {})) < 3 for robot in survivors)
    if after > 2:
        assert position > (0, 0)


def test_a_robot_declared_gone_by_a_survivor_ends_with_the_others(folder: Path) -> None:
    # Robot 2 was only slow: robot 0 declares it gone; robot 2's own answer is to end too.
    settings = DgsSettings()
    robots = team_of(folder, settings)
    for robot in robots.values():
        robot.start()
    for r, robot in robots.items():
        for s, other in robots.items():
            if s != r:
                robot.receive_hello(Hello(SOLVE, s, r, other.separator_counts()))
    aborts = robots[0].vanish([2], "robot 2 silent for 10 s")
    assert {a.receiver for a in aborts} == {1}
    replies = robots[1].receive_abort(aborts[0])
    assert {a.receiver for a in replies} == {0}
    robots[0].receive_abort(replies[0])
    assert robots[0].phase is robots[1].phase is Phase.ABORTED
    told = robots[2].receive_abort(Abort(SOLVE, 0, 2, (2,), (0, 0), "robot 2 silent for 10 s"))
    assert {a.receiver for a in told} == {0, 1}  # it tells the others, who are finished already
    with pytest.raises(TurnRejected) as refused:
        robots[0].receive_abort(told[0])
    assert refused.value.reason == "finished"


def hostile_turns(robots: dict[int, TeamRobot]) -> list[tuple[Turn, str]]:
    """Turns robot 0 can be sent now (before any step), each wrong in one way, and the reason."""
    zero = robots[0]
    shared_keys = zero.agent.expected_keys(1)
    rotation = {k: tuple(np.eye(3).ravel()) for k in shared_keys}
    good = DgsMessage(1, 0, "rotation", 0, 1, rotation)
    other = next(k for k in robots[1].problem.poses if k not in shared_keys)
    strange = DgsMessage(1, 0, "rotation", 0, 1, {**rotation, other: tuple(np.eye(3).ravel())})
    pose = DgsMessage(1, 0, "pose", 1, 1, {k: (0.0,) * 6 for k in shared_keys})
    fewer = DgsMessage(1, 0, "rotation", 0, 1, dict(list(rotation.items())[:1]))
    not_neighbour = [r for r in robots if r != 0 and not zero.agent.expected_keys(r)]
    turns = [
        (Turn(SOLVE + 1, 1, 0, 0, 1, True, 0.5, good), "other_solve"),
        (Turn(SOLVE, 9, 0, 0, 1, True, 0.5, None), "not_in_team"),
        (Turn(SOLVE, 1, 2, 0, 1, True, 0.5, None), "not_in_team"),
        (Turn(SOLVE, 1, 0, 1, 1, True, 0.5, pose), "wrong_stage"),
        (Turn(SOLVE, 1, 0, 0, 5, True, 0.5, replace(good, iteration=5)), "out_of_turn"),
        (Turn(SOLVE, 1, 0, 0, 1, True, math.nan, good), "bad_report"),
        (Turn(SOLVE, 1, 0, 0, 1, False, 0.5, None), "bad_report"),
        (Turn(SOLVE, 1, 0, 0, 1, True, 0.5, strange), "not_shared"),
        (Turn(SOLVE, 1, 0, 0, 1, True, 0.5, fewer), "missing_estimates"),
        (Turn(SOLVE, 1, 0, 0, 1, True, 0.5, None), "missing_estimates"),
    ]
    if not_neighbour:
        n = not_neighbour[0]
        turns.append(
            (Turn(SOLVE, n, 0, 0, 1, True, 0.5, DgsMessage(n, 0, "rotation", 0, 1, rotation)), "not_shared")
        )
    return turns


def test_turns_that_do_not_fit_are_refused_with_their_reason_and_change_nothing(folder: Path) -> None:
    settings = DgsSettings(eta_rotation=1e-3, eta_pose=1e-3)
    reference = run_dgs(read_robot_folder(folder).graph, settings)
    robots = team_of(folder, settings)
    reasons = []
    for turn, reason in hostile_turns(robots):
        with pytest.raises(TurnRejected) as refused:
            robots[0].receive_turn(turn)
        assert refused.value.reason == reason, (turn, refused.value)
        reasons.append(reason)
    assert robots[0]._reports == {} and robots[0]._inbox == {}
    # A duplicate of a real turn, during the solve: refused, and the solve is still run_dgs's.
    duplicates: list[str] = []

    def duplicate_first_turn(team: dict[int, TeamRobot], steps: int) -> None:
        if steps == 3:
            sender = next(r for r in team if team[r].sent)
            m = team[sender].sent[0]
            report = team[sender].reports[0]
            try:
                team[m.receiver].receive_turn(Turn(SOLVE, sender, m.receiver, 0, 1, True, report.change, m))
            except TurnRejected as e:
                duplicates.append(e.reason)

    assert run_team(robots, 3, inject=duplicate_first_turn) == []
    assert duplicates == ["duplicate"]
    for r, robot in robots.items():
        assert robot.sent == [m for m in reference.messages if m.sender == r]
        assert bits(robot.estimate()[1]) == bits({k: reference.poses[k] for k in robot.problem.poses})


def test_hellos_that_contradict_a_robots_own_file_are_refused(folder: Path) -> None:
    robots = team_of(folder, DgsSettings())
    zero = robots[0]
    zero.start()
    counts = robots[1].separator_counts()
    for wrong, reason in [
        (Hello(SOLVE, 1, 0, {**counts, 0: counts.get(0, 0) + 1}), "bad_hello"),
        (Hello(SOLVE, 1, 0, {**counts, 5: 1}), "bad_hello"),
        (Hello(SOLVE + 1, 1, 0, counts), "other_solve"),
    ]:
        with pytest.raises(TurnRejected) as refused:
            zero.receive_hello(wrong)
        assert refused.value.reason == reason
    zero.receive_hello(Hello(SOLVE, 1, 0, counts))
    with pytest.raises(TurnRejected) as refused:
        zero.receive_hello(Hello(SOLVE, 1, 0, counts))
    assert refused.value.reason == "duplicate"


def test_a_team_that_its_separators_do_not_connect_fails_with_a_clear_reason(tmp_path: Path) -> None:
    graph, _ = make_graph(3, 4, sigma_r=0.05, sigma_t=0.1, seed=1, initial_noise=0.1)
    # Robot 2 keeps its chain but loses its separators: nobody reaches it from robot 0.
    cut = PoseGraph(
        graph.poses,
        tuple(
            e
            for e in graph.edges
            if 2 not in {graph.robot_of(k) for k in e.keys} or not graph.is_separator(e)
        ),
    )
    for r in cut.robots:
        write_g2o(tmp_path / robot_file_name(r), cut, keys=cut.robot_keys(r), edges=cut.robot_edges(r))
    robots = team_of(tmp_path, DgsSettings())
    run_team(robots, 0)
    for robot in robots.values():
        assert robot.phase is Phase.FAILED
        assert robot.reason == "robots [2] share no chain of separators with robot 0, the anchor's"


def test_only_robot_zero_holds_the_anchor(folder: Path) -> None:
    problem = LocalProblem.from_robot_file(folder / robot_file_name(1), 1, anchor_robot=1)
    with pytest.raises(GraphError, match="robot 0 and only it"):
        TeamRobot(problem, range(3), DgsSettings(), SOLVE)
    assert LocalProblem.from_robot_file(folder / robot_file_name(0), 0).anchor == pose_key(0, 0)


def test_turns_cross_the_wire_bit_for_bit_and_bad_values_are_refused() -> None:
    keys = [pose_key(1, 3), pose_key(1, 0)]
    values = {k: tuple(np.random.default_rng(k % 7).normal(size=9)) for k in keys}
    turn = Turn(SOLVE, 1, 0, 0, 4, True, 0.125, DgsMessage(1, 0, "rotation", 0, 4, values))
    back = turn_from_proto(turn_to_proto(turn))
    assert back == turn
    assert list(turn_to_proto(turn).keys) == sorted(keys)
    unsolved = Turn(SOLVE, 1, 0, 1, 2, False, math.inf, None)
    assert turn_from_proto(turn_to_proto(unsolved)) == unsolved
    for mutate, reason in [
        (lambda m: m.values.__setitem__(3, math.nan), "bad_values"),
        (lambda m: m.values.append(1.0), "bad_values"),
        (lambda m: m.keys.__setitem__(1, m.keys[0]), "bad_values"),
        (lambda m: setattr(m, "linearisation", 1), "wrong_stage"),
        (lambda m: setattr(m, "stage", 0), "wrong_stage"),
        (lambda m: setattr(m, "iteration", 0), "wrong_stage"),
    ]:
        msg = turn_to_proto(turn)
        mutate(msg)
        with pytest.raises(TurnRejected) as refused:
            turn_from_proto(msg)
        assert refused.value.reason == reason
