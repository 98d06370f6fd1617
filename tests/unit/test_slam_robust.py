"""Rejecting wrong inter-robot associations: maximum clique, PCM and gtsam GNC on known outliers."""

from __future__ import annotations

import numpy as np
import pytest

from swarmrec.slam import robust
from swarmrec.slam.centralized import solve_centralized, to_gtsam_pose
from swarmrec.slam.lie import Pose, so3_exp
from swarmrec.slam.robust import PcmSettings, gnc, max_clique, pcm
from swarmrec.slam.scenarios import Scenario, ScenarioSettings, generate_scenario


def adjacency(n: int, edges: list[tuple[int, int]]) -> np.ndarray:
    m = np.eye(n, dtype=bool)
    for a, b in edges:
        m[a, b] = m[b, a] = True
    return m


def test_max_clique_finds_the_largest_mutually_consistent_set() -> None:
    # {1, 2, 4, 5} is the only clique of 4; {0, 1, 2} and {3, 4, 5} are cliques of 3.
    graph = adjacency(6, [(0, 1), (0, 2), (1, 2), (1, 4), (1, 5), (2, 4), (2, 5), (4, 5), (3, 4), (3, 5)])
    assert max_clique(graph) == [1, 2, 4, 5]
    assert max_clique(adjacency(3, [])) == [0]
    assert max_clique(np.zeros((0, 0), dtype=bool)) == []


def test_large_candidate_sets_fall_back_to_a_greedy_clique(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(robust, "EXACT_CLIQUE_LIMIT", 3)
    graph = adjacency(6, [(0, 1), (0, 2), (1, 2), (1, 4), (1, 5), (2, 4), (2, 5), (4, 5), (3, 4), (3, 5)])
    clique = max_clique(graph)
    assert all(graph[a, b] for a in clique for b in clique)
    assert clique == [1, 2, 4, 5]  # degree order reaches it here: 1, 2, 4, 5 have degree 4


@pytest.mark.parametrize("seed", [0, 1])
def test_adjoint_moves_a_perturbation_across_a_pose_as_gtsam_does(seed: int) -> None:
    rng = np.random.default_rng(seed)
    pose = Pose(so3_exp(rng.normal(size=3)), rng.normal(size=3))
    assert robust._adjoint(pose) == pytest.approx(to_gtsam_pose(pose).AdjointMap(), abs=1e-12)


@pytest.fixture(scope="module")
def with_outliers() -> Scenario:
    return generate_scenario(ScenarioSettings(world="chairs", robots=3, seed=4, outliers=3))


def wrong(scenario: Scenario) -> set[tuple[int, int]]:
    return {s.edge.keys for s in scenario.separators if not s.correct}


def test_pcm_rejects_exactly_the_injected_wrong_associations(with_outliers: Scenario) -> None:
    assert len(wrong(with_outliers)) == 3
    result = pcm(with_outliers.graph)
    assert {e.keys for e in result.rejected} == wrong(with_outliers)
    assert len(result.kept) == len(with_outliers.separators) - 3
    cleaned = result.graph(with_outliers.graph)
    assert len(cleaned.edges) == len(with_outliers.graph.edges) - 3


def test_pcm_with_an_impossible_gate_keeps_one_separator_per_pair(with_outliers: Scenario) -> None:
    # A gate of confidence ~0 makes every pair inconsistent: each pair's clique is a single separator.
    result = pcm(with_outliers.graph, PcmSettings(confidence=1e-12))
    assert len(result.kept) == len(with_outliers.graph.separator_counts())


def test_gnc_rejects_the_injected_wrong_associations(with_outliers: Scenario) -> None:
    result = gnc(with_outliers.graph)
    assert {e.keys for e in result.rejected} == wrong(with_outliers)
    assert all(
        w > 0.5
        for n, w in result.weights.items()
        if with_outliers.graph.edges[n].keys not in wrong(with_outliers)
    )
    # Its estimate is the outlier-free graph's optimum.
    clean = with_outliers.graph.with_edges(
        e for e in with_outliers.graph.edges if e.keys not in wrong(with_outliers)
    )
    reference = solve_centralized(clean).poses
    worst = max(
        float(np.linalg.norm(result.poses[k].translation - reference[k].translation)) for k in clean.keys
    )
    assert worst < 0.05
