"""The distributed two-stage Gauss-Seidel: fixed point, stopping rule, messages, ordering, agent protocol."""

from __future__ import annotations

import numpy as np
import pytest

from swarmrec.errors import ConfigError
from swarmrec.slam.agent import DgsAgent, LocalProblem
from swarmrec.slam.centralized import solve_centralized, solve_two_stage
from swarmrec.slam.dgs import DgsSettings, make_agents, solve_distributed, stage_converged
from swarmrec.slam.errors import GraphError, MessageError
from swarmrec.slam.graph import PoseGraph
from swarmrec.slam.keys import pose_key
from swarmrec.slam.messages import DgsMessage, StepReport
from swarmrec.slam.ordering import order_robots
from tests.slam_graphs import make_graph


@pytest.fixture(scope="module")
def two_robots() -> PoseGraph:
    graph, _ = make_graph(2, 5, sigma_r=0.05, sigma_t=0.1, seed=1, initial_noise=0.2)
    return graph


@pytest.fixture(scope="module")
def three_robots() -> PoseGraph:
    graph, _ = make_graph(3, 4, sigma_r=0.05, sigma_t=0.1, seed=2, initial_noise=0.2)
    return graph


def max_difference(a: dict, b: dict) -> float:  # type: ignore[type-arg]
    return max(float(np.abs(a[k].translation - b[k].translation).max()) for k in a)


@pytest.mark.parametrize("mode", ["gauss-seidel", "jacobi"])
def test_distributed_estimate_equals_the_centralized_two_stage_solve(
    two_robots: PoseGraph, mode: str
) -> None:
    result = solve_distributed(
        two_robots, mode=mode, eta_rotation=1e-10, eta_pose=1e-10, pose_linearisations=1
    )
    assert result.converged
    assert max_difference(result.poses, solve_two_stage(two_robots).poses) < 1e-8


def test_relinearised_distributed_estimate_reaches_gtsam_gauss_newton(two_robots: PoseGraph) -> None:
    gn = solve_centralized(two_robots).poses
    one = solve_distributed(two_robots, eta_rotation=1e-10, eta_pose=1e-10, pose_linearisations=1)
    three = solve_distributed(two_robots, eta_rotation=1e-10, eta_pose=1e-10, pose_linearisations=3)
    assert max_difference(three.poses, gn) < 1e-5
    assert max_difference(one.poses, gn) > 1e-4  # the single linearisation is not Gauss-Newton's optimum


def test_over_relaxation_converges_to_the_same_estimate(three_robots: PoseGraph) -> None:
    plain = solve_distributed(three_robots, eta_rotation=1e-10, eta_pose=1e-10)
    relaxed = solve_distributed(three_robots, eta_rotation=1e-10, eta_pose=1e-10, gamma=1.5)
    assert max_difference(plain.poses, relaxed.poses) < 1e-8


def test_each_stage_stops_at_the_first_iteration_whose_largest_change_is_below_eta(
    two_robots: PoseGraph,
) -> None:
    eta = 1e-3
    result = solve_distributed(two_robots, eta_rotation=eta, eta_pose=eta, pose_linearisations=2)
    assert [s.linearisation for s in result.stages] == [0, 1, 2]
    for stage in result.stages:
        assert stage.converged and len(stage.max_change) == stage.iterations
        first_allowed = 0 if stage.linearisation > 1 else 1  # no stop after a flagged stage's first iteration
        assert stage.max_change[-1] < eta
        assert all(change >= eta for change in stage.max_change[first_allowed:-1])
        last = [
            r
            for r in result.reports
            if (r.stage, r.linearisation, r.iteration) == (stage.stage, stage.linearisation, stage.iterations)
        ]
        assert len(last) == 2 and max(r.change for r in last) == stage.max_change[-1]


def report(robot: int, iteration: int, change: float, solved: bool = True) -> StepReport:
    return StepReport(robot, "rotation", 0, iteration, solved, change, ())


def test_stopping_rule_needs_every_robot_solved_and_below_eta() -> None:
    assert stage_converged([report(0, 2, 0.05), report(1, 2, 0.0999)], 0.1, min_iterations=2)
    assert not stage_converged([report(0, 2, 0.05), report(1, 2, 0.1)], 0.1, min_iterations=2)
    assert not stage_converged([report(0, 1, 0.0), report(1, 1, 0.0)], 0.1, min_iterations=2)
    assert stage_converged([report(0, 1, 0.0), report(1, 1, 0.0)], 0.1, min_iterations=1)
    assert not stage_converged(
        [report(0, 3, 0.0), report(1, 3, float("inf"), solved=False)], 0.1, min_iterations=2
    )


def test_stage_that_hits_max_iterations_is_reported_unconverged(two_robots: PoseGraph) -> None:
    result = solve_distributed(two_robots, eta_rotation=1e-12, eta_pose=1e-12, max_iterations=3)
    assert [s.iterations for s in result.stages] == [3, 3, 3]
    assert not result.converged


def test_floats_per_link_follow_the_nine_and_six_float_model(three_robots: PoseGraph) -> None:
    # Separators a0-b0, a3-b3, b0-c0, b3-c3: every directed link carries 2 keys.
    result = solve_distributed(three_robots, eta_rotation=1e-2, eta_pose=1e-2, pose_linearisations=1)
    assert result.order == (0, 1, 2)
    per_iteration = result.floats_per_iteration()
    both_ways = {(0, 1), (1, 0), (1, 2), (2, 1)}
    assert per_iteration[0] == {link: 18 for link in both_ways}  # Gauss-Seidel: all solve in iteration 1
    assert per_iteration[result.rotation_iterations] == {link: 12 for link in both_ways}
    expected_total = 4 * (18 * result.rotation_iterations + 12 * sum(result.pose_iterations))
    assert result.total_floats == expected_total == sum(result.floats_per_link().values())


def test_jacobi_starts_from_the_anchor_and_spreads_one_link_per_iteration(three_robots: PoseGraph) -> None:
    result = solve_distributed(three_robots, mode="jacobi", eta_rotation=1e-2, eta_pose=1e-2)
    first, second = result.floats_per_iteration()[:2]
    assert first == {(0, 1): 18}
    assert second == {(0, 1): 18, (1, 0): 18, (1, 2): 18}


def test_recorded_messages_replay_exactly_on_fresh_agents(three_robots: PoseGraph) -> None:
    # What a transport must reproduce: same inputs in the same order give the same messages, bit for bit.
    result = solve_distributed(three_robots, eta_rotation=1e-3, eta_pose=1e-3, gamma=1.2)
    agents = make_agents(three_robots, gamma=1.2)
    queues: dict[int, list[DgsMessage]] = {r: [] for r in agents}
    stage = ("rotation", 0)
    for recorded in result.reports:
        if (recorded.stage, recorded.linearisation) != stage:
            # A stage ends only once its last messages are in: deliver them, then move on.
            for robot, agent in agents.items():
                for message in queues[robot]:
                    agent.receive(message)
                queues[robot] = []
                agent.begin_pose_stage()
            stage = (recorded.stage, recorded.linearisation)
        inbox, queues[recorded.robot] = queues[recorded.robot], []
        replayed = agents[recorded.robot].step(recorded.iteration, inbox)
        assert replayed == recorded
        for message in replayed.messages:
            queues[message.receiver].append(message)
    merged = {k: p for a in agents.values() for k, p in a.estimate().items()}
    assert max_difference(merged, result.poses) == 0.0


def test_robot_order_follows_the_public_flagged_rule() -> None:
    counts = {(0, 1): 3, (0, 2): 3, (1, 3): 5, (2, 3): 1, (3, 4): 2}
    robots = range(6)  # robot 5 has no separator
    # {0}: robots 1 and 2 both have 3 links -> both appended, the higher number first.
    assert order_robots(robots, counts, first=0, method="flagged") == (0, 2, 1, 3, 4, 5)
    # one at a time: 1 (3, lower number on ties), then 3 (5), then 2 (3 + 1), then 4.
    assert order_robots(robots, counts, first=0, method="greedy") == (0, 1, 3, 2, 4, 5)
    assert order_robots(robots, counts, first=3, method="natural") == (3, 0, 1, 2, 4, 5)
    assert order_robots([0, 1], {}, first=0) == (0, 1)
    with pytest.raises(ConfigError, match="first robot 7"):
        order_robots(robots, counts, first=7)


def test_agent_without_anchor_or_estimated_neighbour_waits(two_robots: PoseGraph) -> None:
    agent = DgsAgent(LocalProblem.from_graph(two_robots, 1, anchor=two_robots.anchor_key()))
    waiting = agent.step(1)
    assert (waiting.solved, waiting.change, waiting.messages) == (False, float("inf"), ())
    with pytest.raises(GraphError, match="never solved"):
        agent.begin_pose_stage()


def test_agents_refuse_messages_that_do_not_fit(three_robots: PoseGraph) -> None:
    agents = make_agents(three_robots)
    sent = agents[0].step(1).messages[0]
    assert (sent.sender, sent.receiver, sent.floats) == (0, 1, 18)
    with pytest.raises(MessageError, match="addressed to robot 1"):
        agents[2].receive(sent)
    from_2 = DgsMessage(2, 0, "rotation", 0, 1, {pose_key(2, 0): tuple(np.eye(3).ravel())})
    with pytest.raises(MessageError, match="robot 2 shares no separator with robot 0"):
        agents[0].receive(from_2)
    missing = DgsMessage(0, 1, "rotation", 0, 1, {pose_key(0, 0): tuple(np.eye(3).ravel())})
    with pytest.raises(MessageError, match=r"missing \['a3'\]"):
        agents[1].receive(missing)
    pose_stage = DgsMessage(0, 1, "pose", 1, 1, {k: (0.0,) * 6 for k in sent.estimates})
    with pytest.raises(MessageError, match="in the rotation stage"):
        agents[1].receive(pose_stage)
    assert agents[1].receive(DgsMessage(0, 1, "rotation", 0, 3, sent.estimates))
    assert not agents[1].receive(sent)  # iteration 1 after iteration 3: stale, ignored


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"stage": "rotation", "linearisation": 0, "estimates": {1: (0.0,) * 6}}, "has 6 floats, expected 9"),
        ({"stage": "pose", "linearisation": 1, "estimates": {1: (float("nan"),) * 6}}, "not finite"),
        ({"stage": "pose", "linearisation": 0, "estimates": {}}, "does not fit the pose stage"),
        ({"stage": "map", "linearisation": 0, "estimates": {}}, "unknown stage"),
    ],
)
def test_messages_validate_themselves(kwargs: dict, message: str) -> None:  # type: ignore[type-arg]
    with pytest.raises(MessageError, match=message):
        DgsMessage(0, 1, iteration=1, **kwargs)


def test_graphs_the_team_cannot_solve_are_refused() -> None:
    graph, _ = make_graph(2, 3, separators=[])
    with pytest.raises(GraphError, match="not connected"):
        solve_distributed(graph)
    plain = PoseGraph({0: graph.poses[pose_key(0, 0)], 1: graph.poses[pose_key(0, 1)]}, ())
    with pytest.raises(GraphError, match="needs robot keys"):
        solve_distributed(plain)


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("gamma", 2.0, "gamma"),
        ("eta_pose", 0.0, "eta_pose must be positive"),
        ("mode", "async", "mode must be one of"),
        ("order", "random", "order must be one of"),
        ("max_iterations", 0, "max_iterations"),
        ("pose_linearisations", 0, "pose_linearisations"),
    ],
)
def test_settings_are_validated(field: str, value: object, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        DgsSettings(**{field: value})  # type: ignore[arg-type]


def test_default_over_relaxation_depends_on_the_mode_and_paper_settings_are_plain() -> None:
    assert DgsSettings().over_relaxation == 1.9
    assert DgsSettings(mode="jacobi").over_relaxation == 1.0
    assert DgsSettings(gamma=1.3, mode="jacobi").over_relaxation == 1.3
    paper = DgsSettings.paper()
    assert (paper.over_relaxation, paper.eta_rotation, paper.eta_pose, paper.pose_linearisations) == (
        1.0,
        0.1,
        0.1,
        1,
    )
