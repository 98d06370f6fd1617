"""Cells, owners and routing: hand-made centres and tables."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from swarmrec.errors import ConfigError
from swarmrec.vpr.clusters import (
    Assignment,
    Router,
    load_centres,
    nearest_centre,
    random_assignment,
    save_centres,
    train_centres,
)
from swarmrec.vpr.errors import DescriptorError, StateFileError

#: Three centres on the plane: left, right, top.
CENTRES = np.array([[-1.0, 0.0], [1.0, 0.0], [0.0, 2.0]], np.float32)


def test_a_query_goes_to_the_owner_of_the_nearest_centre_by_squared_l2() -> None:
    router = Router(CENTRES, Assignment((2, 0, 1), 3))
    # (0.1, 0): 1.21 to the left, 0.81 to the right, 4.01 to the top -> cluster 1, owned by robot 0.
    route = router.route(np.array([0.1, 0.0]))
    assert (route.cluster, route.owner) == (1, 0)
    # (0, 1.2): 2.44 to the left and right, 0.64 to the top -> cluster 2, robot 1.
    assert router.route(np.array([0.0, 1.2])).cluster == 2
    clusters, owners = router.route_many(np.array([[-3.0, 0.0], [0.1, 0.0], [0.0, 5.0]]))
    assert clusters.tolist() == [0, 1, 2] and owners.tolist() == [2, 0, 1]


def test_a_tie_between_centres_goes_to_the_lower_cluster() -> None:
    # (0, 0.5) is 1.25 from both the left and the right centre and 2.25 from the top.
    assert nearest_centre(CENTRES, np.array([[0.0, 0.5]])).tolist() == [0]


def test_random_assignment_gives_every_robot_exactly_c_clusters_and_depends_on_the_seed() -> None:
    table = random_assignment(5, 4, seed=3)
    assert table.n_clusters == 20
    assert table.clusters_per_robot().tolist() == [4, 4, 4, 4, 4]
    assert all(len(table.clusters_of(r)) == 4 for r in range(5))
    assert random_assignment(5, 4, seed=3) == table
    assert random_assignment(5, 4, seed=4).owners != table.owners


def test_the_assignment_table_survives_json(tmp_path: Path) -> None:
    table = random_assignment(3, 2, seed=7)
    path = tmp_path / "assignment.json"
    table.save(path)
    data = json.loads(path.read_text())
    assert data["format"] == "swarmrec.vpr.assignment/1" and data["owners"] == list(table.owners)
    assert Assignment.load(path) == table


def test_the_table_version_travels_in_the_json_and_an_older_table_reads_as_version_0(tmp_path: Path) -> None:
    table = Assignment((1, 0, 1), 2, version=3)
    table.save(tmp_path / "t.json")
    assert json.loads((tmp_path / "t.json").read_text())["version"] == 3
    assert Assignment.load(tmp_path / "t.json").version == 3
    older = {"format": "swarmrec.vpr.assignment/1", "n_robots": 2, "owners": [1, 0, 1]}
    assert Assignment.from_json(older).version == 0
    with pytest.raises(ConfigError, match="version must be an integer >= 0"):
        Assignment((0,), 1, version=-1)


def test_a_bad_assignment_is_refused() -> None:
    with pytest.raises(ConfigError, match="owners must be robots"):
        Assignment((0, 3), 3)
    with pytest.raises(StateFileError, match="not an assignment table"):
        Assignment.from_json({"owners": [0]})
    with pytest.raises(StateFileError, match="bad assignment"):
        Assignment.from_json({"format": "swarmrec.vpr.assignment/1", "owners": [0]})
    with pytest.raises(ConfigError, match="3 centres but the assignment has 2"):
        Router(CENTRES, Assignment((0, 1), 2))


def test_routing_refuses_a_descriptor_of_the_wrong_length_or_not_finite() -> None:
    router = Router(CENTRES, Assignment((0, 1, 2), 3))
    with pytest.raises(DescriptorError, match="length 2"):
        router.route(np.zeros(3))
    with pytest.raises(DescriptorError, match="NaN or inf"):
        router.route(np.array([np.nan, 0.0]))
    with pytest.raises(DescriptorError, match="NaN or inf"):
        router.route_many(np.array([[0.0, np.inf]]))
    with pytest.raises(DescriptorError, match="real-valued"):
        router.route(np.array(["a", "b"]))


def test_k_means_finds_two_obvious_blobs() -> None:
    rng = np.random.default_rng(0)
    blobs = np.concatenate([rng.normal((5, 5), 0.1, (200, 2)), rng.normal((-5, 0), 0.1, (200, 2))])
    centres = train_centres(blobs.astype(np.float32), 2, seed=1)
    found = sorted(map(tuple, np.round(centres, 0).tolist()))
    assert found == [(-5.0, 0.0), (5.0, 5.0)]
    with pytest.raises(ConfigError, match="k must be"):
        train_centres(blobs.astype(np.float32), 401, seed=1)


def test_centres_for_several_k_live_in_one_file(tmp_path: Path) -> None:
    path = tmp_path / "centres.npz"
    save_centres(path, {3: CENTRES, 1: CENTRES[:1]}, {"data": "hand-made"})
    np.testing.assert_array_equal(load_centres(path, 3), CENTRES)
    with pytest.raises(StateFileError, match=r"no centres for k=2 \(it has k in \[1, 3\]\)"):
        load_centres(path, 2)
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(StateFileError, match="cannot read centres"):
        load_centres(tmp_path / "junk.npz", 3)
