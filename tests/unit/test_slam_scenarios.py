"""Simulated object-based scenarios: the model (Eq. 1-2), association, rendezvous, determinism, outliers."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from swarmrec.errors import ConfigError
from swarmrec.slam.graph import is_landmark_key
from swarmrec.slam.keys import pose_key
from swarmrec.slam.scenarios import (
    _HOUSE_LAYOUT,
    PAPER_NOISE_LEVELS,
    ScenarioSettings,
    generate_scenario,
)

QUIET = {"sigma_rotation_deg": 1e-7, "sigma_translation": 1e-7}


@pytest.mark.parametrize("world", ["chairs", "house"])
def test_noise_free_measurements_are_the_true_relative_poses(world: str) -> None:
    scenario = generate_scenario(ScenarioSettings(world=world, robots=3, **QUIET))  # type: ignore[arg-type]
    truth = scenario.truth
    for edge in scenario.graph.edges:
        expected = truth[edge.source].between(truth[edge.target])  # x_i^-1 o_k (Eq. 1), identity for Eq. 2
        assert edge.measurement.translation == pytest.approx(expected.translation, abs=1e-5)
        assert edge.measurement.rotation == pytest.approx(expected.rotation, abs=1e-5)
    # Robot 0's first pose is known exactly, so dead reckoning starts there.
    first = scenario.graph.poses[pose_key(0, 0)]
    assert first.translation == pytest.approx(truth[pose_key(0, 0)].translation)


def test_the_chairs_world_is_the_papers_25_chairs_on_a_grid() -> None:
    scenario = generate_scenario(ScenarioSettings(world="chairs", robots=2))
    positions = np.array([o.pose.translation[:2] for o in scenario.objects])
    assert len(scenario.objects) == 25 and {o.label for o in scenario.objects} == {"chair"}
    assert sorted(set(np.round(positions[:, 0], 6))) == [-6.0, -3.0, 0.0, 3.0, 6.0]
    yaws = [math.atan2(o.pose.rotation[1, 0], o.pose.rotation[0, 0]) for o in scenario.objects]
    assert len({round(y, 6) for y in yaws}) == 25  # each chair at its own random angle


def test_house_objects_of_one_label_are_farther_apart_than_the_gate_allows_confusing() -> None:
    closest = min(
        math.dist(a[1:3], b[1:3]) for a, b in itertools.combinations(_HOUSE_LAYOUT, 2) if a[0] == b[0]
    )
    assert closest >= 2.5 > 2 * ScenarioSettings().association_gate


@pytest.mark.parametrize(("world", "robots"), [("chairs", 2), ("chairs", 6), ("house", 4)])
def test_shared_objects_are_the_same_physical_objects_and_join_the_team(world: str, robots: int) -> None:
    scenario = generate_scenario(ScenarioSettings(world=world, robots=robots, seed=3))  # type: ignore[arg-type]
    graph = scenario.graph
    assert graph.is_connected()
    assert scenario.intra_association_errors == 0 and scenario.wrong_separators == 0
    assert len(scenario.separators) >= robots - 1
    for separator in scenario.separators:
        a, b = separator.edge.source, separator.edge.target
        assert is_landmark_key(a) and is_landmark_key(b) and graph.robot_of(a) != graph.robot_of(b)
        assert scenario.landmark_objects[a] == scenario.landmark_objects[b]
        assert separator.edge.measurement.translation == pytest.approx(np.zeros(3))
    # Every pair of robots met at the start (all together) and again on the way back.
    assert {(a, b) for a, b, _ in scenario.meetings} == set(itertools.combinations(range(robots), 2))
    assert {step for _, _, step in scenario.meetings} - {0} != set()


def test_the_same_settings_give_the_same_scenario() -> None:
    settings = ScenarioSettings(world="house", robots=3, seed=5, outliers=2)
    one, two = generate_scenario(settings), generate_scenario(settings)
    assert one.graph.keys == two.graph.keys
    for a, b in zip(one.graph.edges, two.graph.edges, strict=True):
        assert a.keys == b.keys and np.array_equal(a.measurement.matrix(), b.measurement.matrix())
    other = generate_scenario(ScenarioSettings(world="house", robots=3, seed=6))
    assert not np.array_equal(
        other.graph.edges[0].measurement.matrix(), one.graph.edges[0].measurement.matrix()
    )


def test_injected_outliers_are_wrong_associations_between_robots_that_met() -> None:
    scenario = generate_scenario(ScenarioSettings(world="chairs", robots=4, seed=2, outliers=5))
    injected = [s for s in scenario.separators if s.injected]
    assert len(injected) == 5 and not any(s.correct for s in injected)
    met = {(a, b) for a, b, _ in scenario.meetings}
    for s in injected:
        pair = tuple(sorted(scenario.graph.robot_of(k) for k in s.edge.keys))
        assert pair in met


def test_noise_levels_are_the_papers_table_2() -> None:
    assert PAPER_NOISE_LEVELS == ((1.0, 0.1), (5.0, 0.1), (10.0, 0.2), (15.0, 0.3))
    scenario = generate_scenario(ScenarioSettings(robots=2, sigma_rotation_deg=10.0, sigma_translation=0.2))
    odometry = scenario.graph.edges[0]
    assert np.diag(odometry.information) == pytest.approx([math.radians(10.0) ** -2] * 3 + [0.2**-2] * 3)


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"robots": 7}, "robots must be 2 to 6"),
        ({"world": "moon"}, "world"),
        ({"step": 0.0}, "step"),
        ({"outliers": -1}, "outliers"),
    ],
)
def test_settings_are_validated(changes: dict, message: str) -> None:  # type: ignore[type-arg]
    with pytest.raises(ConfigError, match=message):
        ScenarioSettings(**changes)
