"""The simulated street: landmark geometry, sightings and swarm configurations."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from swarmrec.errors import ConfigError
from swarmrec.fusion.street import (
    FORMATIONS,
    StreetSettings,
    SwarmConfiguration,
    communication_graph,
    default_street,
    generate_configuration,
    generate_configurations,
    is_connected,
)

STREET = (
    default_street()
)  # 14 m wide; north facades k at [14k, 14k + 12], south 10 + k at [7 + 14k, 19 + 14k]


@pytest.fixture(scope="module")
def configs() -> list[SwarmConfiguration]:
    return generate_configurations(118, seed=0)


def reachable_everywhere(adj: np.ndarray) -> bool:
    """Connectivity by matrix powers, independent of the code under test."""
    n = adj.shape[0]
    reach = np.linalg.matrix_power(np.eye(n, dtype=np.int64) + adj.astype(np.int64), n - 1)
    return bool(np.all(reach > 0))


def test_the_street_has_19_landmarks_ten_north_nine_south_without_overlap() -> None:
    assert sorted(f.landmark for f in STREET.facades) == list(range(19))
    assert sum(f.side == 1 for f in STREET.facades) == 10
    for side in (1, -1):
        spans = sorted((f.x0, f.x1) for f in STREET.facades if f.side == side)
        assert all(a[1] < b[0] for a, b in itertools.pairwise(spans))


def test_a_robot_facing_a_facade_head_on_sees_it_at_the_half_width() -> None:
    sighting = STREET.sight(6.0, 0.0, math.pi / 2)
    assert sighting is not None
    assert (sighting.landmark, sighting.distance, sighting.view_angle, sighting.offset) == pytest.approx(
        (0, 7.0, 0.0, 0.0)
    )


def test_an_oblique_sighting_has_its_distance_angle_and_offset() -> None:
    # From (6, 0) towards (10, 7) on facade 0: distance sqrt(65), turned atan(4 / 7) towards
    # the facade's right (+x on the north side), hit 4 m right of the centre: offset 1/3.
    sighting = STREET.sight(6.0, 0.0, math.atan2(7.0, 4.0))
    assert sighting is not None and sighting.landmark == 0
    assert sighting.distance == pytest.approx(math.sqrt(65))
    assert sighting.view_angle == pytest.approx(math.atan(4 / 7))
    assert sighting.offset == pytest.approx(1 / 3)


def test_on_the_south_side_the_facade_right_is_towards_minus_x() -> None:
    # Facing south, turned 0.3 rad clockwise (towards -x): the hit is 7 tan 0.3 m west of x = 14,
    # right of facade 10's centre (x = 13) as seen from the street.
    sighting = STREET.sight(14.0, 0.0, -math.pi / 2 - 0.3)
    assert sighting is not None and sighting.landmark == 10
    assert sighting.view_angle == pytest.approx(0.3)
    assert sighting.offset == pytest.approx(-(14.0 - 7.0 * math.tan(0.3) - 13.0) / 12.0)
    assert sighting.distance == pytest.approx(7.0 / math.cos(0.3))


def test_rays_through_a_gap_along_the_street_or_too_far_see_nothing() -> None:
    assert STREET.sight(6.0, 0.0, math.pi / 4) is None  # hits x = 13, the gap between facades 0 and 1
    assert STREET.sight(6.0, 0.0, 0.0) is None
    assert STREET.sight(6.0, 0.0, math.pi / 2, max_view=5.0) is None


def test_communication_graph_links_robots_within_radio_range() -> None:
    adj = communication_graph([(0.0, 0.0), (5.0, 0.0), (11.0, 0.0)], radio_range=7.0)
    assert adj.tolist() == [[False, True, False], [True, False, True], [False, True, False]]
    assert is_connected(adj)
    assert not is_connected(communication_graph([(0.0, 0.0), (5.0, 0.0), (20.0, 0.0)], radio_range=7.0))


def test_every_configuration_has_a_connected_undirected_radio_graph(
    configs: list[SwarmConfiguration],
) -> None:
    settings = StreetSettings()
    for c in configs:
        adj = c.adjacency
        assert np.array_equal(adj, adj.T) and not np.any(np.diag(adj))
        dist = np.hypot(*(c.positions[:, None, :] - c.positions[None, :, :]).transpose(2, 0, 1))
        assert np.array_equal(adj, (dist <= settings.radio_range) & ~np.eye(c.n_robots, dtype=bool))
        assert reachable_everywhere(adj)


def test_configurations_are_ten_robots_in_clusters_and_formations(configs: list[SwarmConfiguration]) -> None:
    assert len(configs) == 118
    for c in configs:
        assert c.n_robots == 10
        n_clusters = len(c.cluster_landmarks)
        assert 2 <= n_clusters <= 4 and len(set(c.cluster_landmarks)) == n_clusters
        assert sorted(set(c.clusters.tolist())) == list(range(n_clusters))
        assert min(np.bincount(c.clusters)) >= 2
        assert set(c.formations) <= set(FORMATIONS)
    assert {f for c in configs for f in c.formations} == set(FORMATIONS)


def test_each_robot_sees_what_its_position_and_yaw_point_at(configs: list[SwarmConfiguration]) -> None:
    half = STREET.width / 2
    for c in configs[:30]:
        for i in range(c.n_robots):
            x, y = c.positions[i]
            assert abs(y) < half and -math.pi <= c.yaws[i] <= math.pi
            sighting = STREET.sight(x, y, c.yaws[i])
            assert sighting is not None
            assert (
                sighting.landmark,
                sighting.distance,
                sighting.view_angle,
                sighting.offset,
            ) == pytest.approx((c.landmarks[i], c.distances[i], c.view_angles[i], c.offsets[i]))


def test_configurations_cover_every_landmark_and_mostly_see_their_cluster_landmark(
    configs: list[SwarmConfiguration],
) -> None:
    seen = np.concatenate([c.landmarks for c in configs])
    assert set(seen.tolist()) == set(range(19))
    intended = np.concatenate([np.asarray(c.cluster_landmarks)[c.clusters] for c in configs])
    assert np.mean(seen == intended) > 0.9


def test_configurations_are_reproducible_and_independent_of_the_count(
    configs: list[SwarmConfiguration],
) -> None:
    again = generate_configuration(5, seed=0)
    assert np.array_equal(again.positions, configs[5].positions)
    assert np.array_equal(again.yaws, configs[5].yaws)
    assert not np.array_equal(generate_configuration(5, seed=1).positions, configs[5].positions)


def test_street_settings_are_validated() -> None:
    with pytest.raises(ConfigError, match="min_clusters"):
        StreetSettings(min_clusters=1)
    with pytest.raises(ConfigError, match="radio_range"):
        StreetSettings(radio_range=0.0)


def test_an_impossible_radio_range_fails_with_a_clear_message() -> None:
    with pytest.raises(ConfigError, match="no connected configuration"):
        generate_configuration(0, settings=StreetSettings(radio_range=0.01, max_attempts=5))
