"""Algorithm 1 (multi-hop flooding) as a state machine and in the synchronous simulator."""

from __future__ import annotations

from collections import deque

import numpy as np
import pytest

from swarmrec.errors import ConfigError
from swarmrec.fusion.flooding import (
    FloodingNode,
    FloodMessage,
    FloodResult,
    Outcome,
    Rejection,
    simulate_flooding,
)

UNIFORM3 = [1 / 3, 1 / 3, 1 / 3]


def graph(n: int, edges: list[tuple[int, int]]) -> np.ndarray:
    adj = np.zeros((n, n), bool)
    for i, j in edges:
        adj[i, j] = adj[j, i] = True
    return adj


def line(n: int) -> np.ndarray:
    return graph(n, [(i, i + 1) for i in range(n - 1)])


def flood(adj: np.ndarray, r_max: int | None = None) -> FloodResult:
    n = adj.shape[0]
    likelihoods = np.full((n, 3), 1 / 3)
    return simulate_flooding(adj, likelihoods, np.zeros(n), r_max=r_max)


def bfs(adj: np.ndarray, source: int) -> dict[int, int]:
    """Shortest path lengths, written here independently of the code under test."""
    dist = {source: 0}
    queue = deque([source])
    while queue:
        u = queue.popleft()
        for v in range(adj.shape[0]):
            if adj[u, v] and v not in dist:
                dist[v] = dist[u] + 1
                queue.append(v)
    return dist


def test_on_a_line_each_robot_hears_the_others_at_their_exact_hop_distance() -> None:
    result = flood(line(5))
    assert result.order(0) == [(1, 1), (2, 2), (3, 3), (4, 4)]
    assert result.order(2) == [(1, 1), (3, 1), (0, 2), (4, 2)]
    assert result.order(4) == [(3, 1), (2, 2), (1, 3), (0, 4)]


def test_recorded_hops_are_shortest_path_lengths_on_any_connected_graph() -> None:
    # A triangle 0-1-2 with a tail 2-3-4-5 and a branch 3-6.
    adj = graph(7, [(0, 1), (1, 2), (2, 0), (2, 3), (3, 4), (4, 5), (3, 6)])
    result = flood(adj)
    for robot in range(7):
        expected = bfs(adj, robot)
        del expected[robot]
        assert dict(result.order(robot)) == expected
        hops = [h for _, h in result.order(robot)]
        assert hops == sorted(hops)  # nearer robots are incorporated first


def test_a_robot_never_hears_a_non_neighbour_directly() -> None:
    adj = graph(6, [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (1, 4)])
    result = flood(adj)
    assert all(adj[sender, receiver] for _, sender, receiver, _ in result.deliveries)
    for robot in range(6):
        for heard in result.heard[robot]:
            assert adj[heard.sender, robot]
            assert (heard.hops == 1) == bool(adj[heard.origin, robot])
            if heard.hops == 1:
                assert heard.sender == heard.origin


def test_every_copy_of_an_origin_after_the_first_is_a_counted_duplicate() -> None:
    # Each robot of a line broadcasts 5 messages (its own and 4 forwards), so robot i
    # receives 5 * degree(i) copies, of which 4 are new.
    adj = line(5)
    result = flood(adj)
    assert result.duplicates == tuple(5 * int(adj[i].sum()) - 4 for i in range(5))
    assert len(result.deliveries) == 5 * int(adj.sum())


def test_r_max_stops_messages_after_that_many_hops() -> None:
    result = flood(line(5), r_max=2)
    assert result.order(0) == [(1, 1), (2, 2)]
    assert result.order(2) == [(1, 1), (3, 1), (0, 2), (4, 2)]


def test_the_flooded_vectors_and_yaws_are_those_of_the_origin() -> None:
    likelihoods = np.array([[0.7, 0.2, 0.1], [0.1, 0.8, 0.1], [0.2, 0.2, 0.6]])
    result = simulate_flooding(line(3), likelihoods, [0.1, 0.2, 0.3])
    for heard in result.heard[0]:
        assert np.array_equal(heard.likelihood, likelihoods[heard.origin])
        assert heard.yaw == [0.1, 0.2, 0.3][heard.origin]


def test_simulator_rejects_a_directed_or_self_looped_graph() -> None:
    directed = np.zeros((3, 3), bool)
    directed[0, 1] = True
    with pytest.raises(ConfigError):
        simulate_flooding(directed, np.full((3, 3), 1 / 3), np.zeros(3))
    with pytest.raises(ConfigError):
        simulate_flooding(np.eye(3, dtype=bool), np.full((3, 3), 1 / 3), np.zeros(3))


def started_node() -> FloodingNode:
    node = FloodingNode(1, 4, n_classes=3)
    node.start_round(7, UNIFORM3, 0.0)
    return node


def test_node_records_a_new_origin_and_forwards_it_one_hop_further() -> None:
    node = started_node()
    result = node.receive(FloodMessage(7, origin=3, sender=2, hops=1, yaw=0.5, likelihood=[0.2, 0.3, 0.5]))
    assert result.outcome is Outcome.ACCEPTED
    assert result.heard is not None and (result.heard.origin, result.heard.hops) == (3, 2)
    assert result.forward is not None
    assert (result.forward.origin, result.forward.sender, result.forward.hops) == (3, 1, 2)
    assert result.forward.yaw == 0.5 and result.forward.round_id == 7


def test_start_round_broadcasts_the_own_measurement_with_hop_count_zero() -> None:
    node = FloodingNode(2, 4, n_classes=3)
    message = node.start_round(5, [0.2, 0.3, 0.5], 1.25)
    assert (message.round_id, message.origin, message.sender, message.hops, message.yaw) == (5, 2, 2, 0, 1.25)
    assert not node.heard and not node.heard_all


def test_node_ignores_and_counts_a_second_copy_of_an_origin_and_its_own_echo() -> None:
    node = started_node()
    node.receive(FloodMessage(7, 3, 3, 0, 0.0, UNIFORM3))
    again = node.receive(FloodMessage(7, 3, 2, 1, 0.0, UNIFORM3))
    echo = node.receive(FloodMessage(7, 1, 0, 1, 0.0, UNIFORM3))
    assert again.outcome is echo.outcome is Outcome.DUPLICATE
    assert again.forward is None and node.duplicates == 2
    assert [h.origin for h in node.heard] == [3]


@pytest.mark.parametrize(
    ("message", "reason"),
    [
        (FloodMessage(7, 3, 3, 0, 0.0, [0.5, 0.5]), Rejection.WRONG_LENGTH),
        (FloodMessage(7, 3, 3, 0, 0.0, [0.5, float("nan"), 0.5]), Rejection.NOT_FINITE),
        (FloodMessage(7, 3, 3, 0, 0.0, [0.5, float("inf"), 0.5]), Rejection.NOT_FINITE),
        (FloodMessage(7, 3, 3, 0, 0.0, [0.6, -0.1, 0.5]), Rejection.NEGATIVE),
        (FloodMessage(7, 3, 3, 0, 0.0, [0.2, 0.2, 0.2]), Rejection.NOT_NORMALISED),
        (FloodMessage(7, 3, 3, 0, 0.0, "abc"), Rejection.NOT_NUMERIC),
        (FloodMessage(7, 3, 3, 0, 0.0, None), Rejection.NOT_NUMERIC),
        (FloodMessage(7, 3, 3, 0, 0.0, 1.0), Rejection.NOT_NUMERIC),
        (FloodMessage(7, 3, 3, 0, 0.0, [[0.5, 0.5, 0.0]]), Rejection.NOT_NUMERIC),
        (FloodMessage(7, 3, 3, 0, 0.0, [[0.5], [0.5, 0.0]]), Rejection.NOT_NUMERIC),
        (FloodMessage(7, 3, 3, -1, 0.0, UNIFORM3), Rejection.BAD_HOPS),
        (FloodMessage(7, 3, 3, 4, 0.0, UNIFORM3), Rejection.BAD_HOPS),  # 4 hops in a swarm of 4
        (FloodMessage(7, 3, 3, 1.5, 0.0, UNIFORM3), Rejection.BAD_HOPS),  # type: ignore[arg-type]  # deliberately malformed
        (FloodMessage(7, 3, 3, True, 0.0, UNIFORM3), Rejection.BAD_HOPS),
        (FloodMessage(7, 9, 3, 0, 0.0, UNIFORM3), Rejection.BAD_ORIGIN),
        (FloodMessage(7, 3, -2, 0, 0.0, UNIFORM3), Rejection.BAD_SENDER),
        (FloodMessage(7, 3, 3, 0, float("nan"), UNIFORM3), Rejection.BAD_YAW),
        (FloodMessage(7, 3, 3, 0, "north", UNIFORM3), Rejection.BAD_YAW),  # type: ignore[arg-type]  # deliberately malformed
        (FloodMessage(6, 3, 3, 0, 0.0, UNIFORM3), Rejection.UNKNOWN_ROUND),
    ],
)
def test_node_rejects_and_counts_malformed_messages_without_raising(
    message: FloodMessage, reason: Rejection
) -> None:
    node = started_node()
    result = node.receive(message)
    assert (result.outcome, result.reason) == (Outcome.REJECTED, reason)
    assert result.forward is None and not node.heard
    assert node.rejected == {reason: 1}
    # The origin was not recorded, so a good copy afterwards still gets through.
    assert node.receive(FloodMessage(7, 3, 3, 0, 0.0, UNIFORM3)).outcome is Outcome.ACCEPTED


def test_a_probability_vector_a_little_off_one_is_accepted() -> None:
    node = started_node()
    assert node.receive(FloodMessage(7, 3, 3, 0, 0.0, [0.3334, 0.3334, 0.3334])).outcome is Outcome.ACCEPTED


def test_a_node_rejects_everything_before_its_first_round() -> None:
    node = FloodingNode(0, 3, n_classes=3)
    assert node.receive(FloodMessage(0, 1, 1, 0, 0.0, UNIFORM3)).reason is Rejection.UNKNOWN_ROUND


def test_a_new_round_forgets_the_previous_one() -> None:
    node = started_node()
    node.receive(FloodMessage(7, 3, 3, 0, 0.0, UNIFORM3))
    node.receive(FloodMessage(7, 3, 3, 0, 0.0, UNIFORM3))
    node.receive(FloodMessage(7, 3, 3, 0, 0.0, [1.0]))
    node.start_round(8, UNIFORM3, 0.0)
    assert not node.heard and node.duplicates == 0 and not node.rejected
    assert node.receive(FloodMessage(7, 2, 2, 0, 0.0, UNIFORM3)).reason is Rejection.UNKNOWN_ROUND
    assert node.receive(FloodMessage(8, 3, 3, 0, 0.0, UNIFORM3)).outcome is Outcome.ACCEPTED


def test_a_node_with_r_max_records_but_does_not_forward_the_last_hop() -> None:
    node = FloodingNode(0, 6, n_classes=3, r_max=2)
    node.start_round(0, UNIFORM3, 0.0)
    at_two = node.receive(FloodMessage(0, 3, 2, 1, 0.0, UNIFORM3))
    assert at_two.outcome is Outcome.ACCEPTED and at_two.forward is None
    beyond = node.receive(FloodMessage(0, 4, 2, 2, 0.0, UNIFORM3))
    assert beyond.reason is Rejection.BEYOND_R_MAX


def test_heard_all_once_every_origin_arrived() -> None:
    node = FloodingNode(0, 3, n_classes=3)
    node.start_round(0, UNIFORM3, 0.0)
    node.receive(FloodMessage(0, 1, 1, 0, 0.0, UNIFORM3))
    assert not node.heard_all
    node.receive(FloodMessage(0, 2, 1, 1, 0.0, UNIFORM3))
    assert node.heard_all
