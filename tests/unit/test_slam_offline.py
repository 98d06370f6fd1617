"""The offline job on a folder of robot g2o files, its settings, and the package's public surface."""

from __future__ import annotations

import doctest
import json
from pathlib import Path

import pytest

import swarmrec.slam as slam
from swarmrec.errors import ConfigError
from swarmrec.slam.centralized import solve_centralized
from swarmrec.slam.dgs import DgsSettings
from swarmrec.slam.g2o import read_g2o, write_g2o
from swarmrec.slam.graph import PoseGraph
from swarmrec.slam.metrics import ate_star
from swarmrec.slam.offline import SlamSettings, main, solve_folder
from tests.slam_graphs import make_graph


@pytest.fixture
def team(tmp_path: Path) -> tuple[Path, PoseGraph]:
    graph, _ = make_graph(3, 5, sigma_r=0.05, sigma_t=0.1, seed=4, initial_noise=0.2)
    folder = tmp_path / "team"
    for robot in graph.robots:
        write_g2o(
            folder / f"{robot}.g2o", graph, keys=graph.robot_keys(robot), edges=graph.robot_edges(robot)
        )
    return folder, graph


def test_solve_folder_writes_estimates_and_a_summary(team: tuple[Path, PoseGraph], tmp_path: Path) -> None:
    folder, graph = team
    out = tmp_path / "out"
    summary = solve_folder(SlamSettings(folder, out))
    assert sorted(p.name for p in out.iterdir()) == [
        "0.g2o",
        "1.g2o",
        "2.g2o",
        "centralized.g2o",
        "merged.g2o",
        "summary.json",
    ]
    merged = read_g2o(out / "merged.g2o")
    reference = solve_centralized(graph).poses
    assert ate_star(merged.poses, reference, graph.keys) < 0.05
    assert summary.accuracy.ate_poses == pytest.approx(
        ate_star(merged.poses, reference, graph.keys), abs=1e-9
    )
    assert summary.accuracy.cost == pytest.approx(graph.cost(merged.poses), rel=1e-9)
    # Robot 1's file: its five vertices and every edge touching them (4 chain + 4 separators).
    lines = (out / "1.g2o").read_text().splitlines()
    assert (
        sum(line.startswith("VERTEX") for line in lines) == 5
        and sum(line.startswith("EDGE") for line in lines) == 8
    )
    data = json.loads((out / "summary.json").read_text())
    assert data["robots"] == 3 and data["separators"] == 4 and data["order"] == [0, 1, 2]
    assert data["rotation_iterations"] == summary.rotation_iterations == data["stages"][0]["iterations"]
    assert data["accuracy"]["ate_landmarks"] is None  # no object in this graph
    # The 9/6-float model: two separator keys per directed link, four directed links.
    expected = 4 * 2 * (9 * summary.rotation_iterations + 6 * sum(summary.pose_iterations))
    assert data["total_floats"] == expected == sum(link["floats"] for link in data["links"])
    assert data["total_bytes"] == 8 * expected


def test_main_prints_a_short_report(
    team: tuple[Path, PoseGraph], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder, _ = team
    main(SlamSettings.paper(folder, tmp_path / "paper"))
    printed = capsys.readouterr().out
    assert "3 robots, 15 vertices" in printed and "iterations: rotation" in printed and "ATE*" in printed


def test_settings_refuse_what_cannot_work(team: tuple[Path, PoseGraph], tmp_path: Path) -> None:
    folder, _ = team
    with pytest.raises(ConfigError, match="not a directory"):
        SlamSettings(tmp_path / "nowhere", tmp_path / "out")
    with pytest.raises(ConfigError, match="bytes_per_float"):
        SlamSettings(folder, tmp_path / "out", bytes_per_float=3)
    with pytest.raises(ConfigError, match="gamma"):
        SlamSettings(folder, tmp_path / "out", solver=DgsSettings(gamma=2.5))
    with pytest.raises(ConfigError, match="centralized"):
        SlamSettings(folder, tmp_path / "out", centralized="dogleg")  # type: ignore[arg-type]
    solve_folder(SlamSettings(folder, tmp_path / "out"))
    with pytest.raises(ConfigError, match="add --overwrite"):
        SlamSettings(folder, tmp_path / "out")
    assert SlamSettings(folder, tmp_path / "out", overwrite=True).solver.over_relaxation == 1.9
    jacobi = SlamSettings(folder, tmp_path / "j", solver=DgsSettings(mode="jacobi"))
    assert jacobi.solver.over_relaxation == 1.0


def test_public_names_exist_once() -> None:
    assert sorted(slam.__all__) == sorted(set(slam.__all__))
    for name in slam.__all__:
        assert hasattr(slam, name), name


def test_package_example_runs() -> None:
    failures, tried = doctest.testmod(slam, verbose=False)
    assert tried > 0 and failures == 0
