"""The README's ``swarmrec slam`` commands, run as a user runs them (the CLI in process, real swarms).

* ``slam solve`` on the shared blocks world: within the authors' 0.1 m of gtsam;
* ``slam run`` on a simulated world: one slam service per robot over mutual TLS, the
  report's every field a user reads (outcome, iterations, the check against the
  in-process solve, bytes against the model, accuracy against gtsam and the world);
* ``swarmrec run`` then ``slam merge``: the place-recognition swarm's own loop closures
  become inter-robot constraints and one merged map, solved live, compared with the
  synthetic world's camera poses.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from swarmrec.cli import main as cli
from tests.conftest import SHARED_DATA, shared


def summary_of(folder: Path) -> dict[str, Any]:
    data: dict[str, Any] = json.loads((folder / "summary.json").read_text(encoding="utf-8"))
    return data


def test_slam_solve_on_the_blocks_world_is_within_the_authors_tolerance(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = shared(SHARED_DATA / "dgs_blocks_world" / "2robots")
    assert cli(["slam", "solve", str(folder), "--out", str(tmp_path)]) == 0
    s = summary_of(tmp_path)
    assert s["converged"] and s["robots"] == 2
    assert s["accuracy"]["ate_poses"] < 0.1  # the public implementation's acceptance, against gtsam
    assert {Path(f).name for f in s["files"]} == {"0.g2o", "1.g2o", "merged.g2o", "centralized.g2o"}
    assert "distributed Gauss-Seidel on" in capsys.readouterr().out


def test_slam_run_solves_a_simulated_world_with_one_service_per_robot(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "live"
    argv = ["slam", "run", "--world", "house", "--robots", "3", "--seed", "1", "--out", str(out), "--quiet"]
    assert cli(argv) == 0
    s = summary_of(out)
    assert s["outcome"] == "converged" and s["stages_agree"]
    assert s["check"]["identical"] and s["check"]["messages_live"] == s["check"]["messages_reference"] > 0
    assert [o["state"] for o in s["robot_outcomes"]] == ["done"] * 3
    assert [st[0] for st in s["stages"]] == ["rotation", "pose", "pose"]
    # Against gtsam's Gauss-Newton on the same graph, and against the simulated world.
    assert s["ate_poses_m"] < 0.1
    assert s["ate_vs_truth_m"] < 2 * s["ate_centralized_vs_truth_m"] + 0.05
    # Bytes per link per iteration: the model counts 8 B per float, 9 a key in the rotation
    # stage and 6 in a pose stage; the wire adds the report, the keys and protobuf's framing.
    for link in s["links"]:
        per_key = 9 if link["stage"] == "rotation" else 6
        assert link["floats"] == link["iterations"] * per_key * link["keys"]
        assert link["model_bytes_per_iteration"] == 8 * per_key * link["keys"]
        overhead = link["bytes_per_iteration"] - link["model_bytes_per_iteration"]
        assert 8 * link["keys"] < overhead < 8 * link["keys"] + 40
    # Every SlamStep between robots is counted; those to a non-neighbour carry only the report.
    assert s["swarm_bytes"]["SlamStep"] >= sum(link["bytes"] for link in s["links"])
    assert s["rejected"] == {}
    for name in ("0.g2o", "1.g2o", "2.g2o", "merged.g2o", "centralized.g2o", "map.png"):
        assert (out / name).is_file(), name
    printed = capsys.readouterr().out
    assert (
        "outcome: converged" in printed
        and "identical" in printed
        and "bytes per link per iteration" in printed
    )


def test_a_place_recognition_run_merges_into_one_map_close_to_the_worlds_truth(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = tmp_path / "places"
    assert (
        cli(
            [
                "run",
                "--dataset",
                "synthetic",
                "--frames",
                "600",
                "--robots",
                "4",
                "--out",
                str(run),
                "--quiet",
            ]
        )
        == 0
    )
    merged = tmp_path / "merge"
    assert cli(["slam", "merge", "--run", str(run), "--out", str(merged), "--quiet"]) == 0
    s = summary_of(merged)
    assert s["robots"] == 4 and s["solver"] == "live slam services" and s["outcome"] == "converged"
    live = s["live"]
    assert live["check"]["identical"] and live["outcome"] == "converged"
    closures = s["closures"]
    assert len(closures) > 0 and s["constraints_kept"] >= 3  # at least a chain linking the 4 robots
    kept = [c for c in closures if c["kept"]]
    assert all(c["status"] == "aligned" for c in kept)
    # PCM and GNC keep mostly constraints within 10 degrees and 0.3 m of the truth, and reject the worst.
    assert s["constraints_kept_right"] >= 0.5 * s["constraints_kept"]
    assert max(c["translation_error_m"] for c in kept) < max(
        c["translation_error_m"] for c in closures if c["status"] == "aligned"
    )
    # The merged map against the world: the distributed estimate is gtsam's, within centimetres,
    # and every robot is placed in the world within a metre.
    assert abs(s["ate_distributed_m"] - s["ate_centralized_m"]) < 0.05
    assert all(v < 1.0 for v in s["ate_per_robot_m"].values())
    assert s["object_points"] > 1000 and s["object_points_rms_m"] < 1.0
    for robot in range(4):
        assert (merged / "graph" / f"{robot}.g2o").is_file()
    assert "merged map of 4 robots" in capsys.readouterr().out
