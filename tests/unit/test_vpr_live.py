"""The live full-image method's pure parts: the swarm's routing table, the report's scoring
of answers and loop closures, the run's settings and the command line's refusals."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from swarmrec.cli import main as cli_main
from swarmrec.core.types import Trajectory
from swarmrec.errors import ConfigError
from swarmrec.experiments.places import PixelSettings, PlacesSettings
from swarmrec.experiments.vpr import DvprSettings, VprRunSettings
from swarmrec.experiments.vpr.report import GroundTruth, ground_truth, live_answers, operating_point
from swarmrec.models import DESCRIPTOR_CENTRES, shipped_model
from swarmrec.services.settings import VprSettings
from swarmrec.vpr.clusters import Assignment
from swarmrec.vpr.errors import StateFileError
from swarmrec.vpr.table import swarm_table
from swarmrec.wire import messages as pb

# --- the routing table ------------------------------------------------------------------


def test_the_swarm_table_is_the_shipped_centres_and_the_seeded_assignment_with_their_digest() -> None:
    table = swarm_table(10, 1, 3)
    with np.load(shipped_model(DESCRIPTOR_CENTRES)) as data:
        k10 = np.asarray(data["k10"], "<f4")
    np.testing.assert_array_equal(table.router.centres, k10)
    assert table.digest == hashlib.sha256(np.ascontiguousarray(k10).tobytes()).hexdigest()
    assert table.assignment.seed == 3 and sorted(table.assignment.owners) == list(range(10))
    assert swarm_table(10, 1, 3).assignment == table.assignment  # every member builds the same


def test_a_table_file_replaces_the_seeded_one_and_must_be_for_the_swarms_robots(tmp_path: Path) -> None:
    owners = (1, 1, 0, 2, 0, 1, 2, 2, 0, 1)
    Assignment(owners, 3, version=4).save(tmp_path / "t.json")
    table = swarm_table(3, 99, 0, assignment=tmp_path / "t.json")  # clusters_per_robot is the file's
    assert table.assignment.owners == owners and table.assignment.version == 4
    assert table.router.centres.shape == (10, 128)
    with pytest.raises(StateFileError, match="a table for 3 robots, the swarm has 4"):
        swarm_table(4, 1, 0, assignment=tmp_path / "t.json")


def test_centres_without_the_swarms_k_are_refused_with_the_command_that_makes_them() -> None:
    with pytest.raises(
        StateFileError, match=r"no centres for k=12 .*swarmrec vpr centres --ks 12 --out FILE"
    ):
        swarm_table(4, 3, 0)


# --- scoring the answers ------------------------------------------------------------------


def test_live_answers_number_frames_globally_and_leave_unanswered_ones_empty() -> None:
    blocks = [range(0, 3), range(3, 6)]
    found = pb.PlaceMatch(found=True, distance=0.25, robot_id=0, frame_index=2)
    reports = {
        (1, 0): pb.PlaceReport(robot_id=1, frame_index=0, owner_robot_id=0, answered=True, match=found),
        (0, 1): pb.PlaceReport(robot_id=0, frame_index=1, owner_robot_id=1, answered=True),
        (1, 2): pb.PlaceReport(robot_id=1, frame_index=2, owner_robot_id=1, answered=False),
    }
    a = live_answers(reports, blocks)
    assert a.owners.tolist() == [-1, 1, -1, 0, -1, 1]
    assert a.matches.tolist() == [-1, -1, -1, 2, -1, -1]
    assert a.distances[3] == 0.25 and np.isinf(a.distances[[0, 1, 2, 4, 5]]).all()


def _truth() -> GroundTruth:
    """Four frames of robots 0, 0, 1, 1, arriving in the order 0, 2, 1, 3 (lock-step); frames 0
    and 3 show the same place, and so do 1 and 2."""
    same = np.zeros((4, 4), bool)
    for i, j in ((0, 3), (1, 2)):
        same[i, j] = same[j, i] = True
    robots = np.array([0, 0, 1, 1])
    order = np.array([0, 2, 1, 3])
    arrival = np.empty(4, np.int64)
    arrival[order] = np.arange(4)
    eligible = (arrival[None, :] < arrival[:, None]) & (robots[None, :] != robots[:, None])
    return GroundTruth(same, robots, order, eligible)


def test_the_operating_point_counts_cross_robot_closures_against_the_same_place_truth() -> None:
    truth = _truth()
    # Query 3 could match 0 (same place, on robot 0, arrived first); query 1 could match 2. Frames 0
    # and 2 had nothing before them on another robot, so two queries had a match to find.
    op = operating_point([(3, 0), (1, 3), (2, 0), (1, 0)], truth)
    assert op.queries_with_a_match == 2
    assert (op.loop_closures, op.cross_robot, op.true_cross_robot, op.own_robot) == (4, 3, 1, 1)
    assert op.precision == pytest.approx(1 / 3)
    assert op.recall == pytest.approx(1 / 2)  # query 3 found its place; query 1 did not
    none = operating_point([], truth)
    assert (none.precision, none.recall) == (0.0, 0.0)


def test_ground_truth_takes_the_pose_nearest_in_time_and_cuts_robots_in_blocks() -> None:
    # Cameras along x, 0.3 m apart, all looking along z (identity rotation): frames i and j show
    # the same place when at most 0.5 m apart, so only neighbours do.
    n = 6
    traj = Trajectory(
        timestamps=np.arange(n, dtype=float),
        positions=np.c_[0.3 * np.arange(n), np.zeros(n), np.zeros(n)],
        quaternions=np.tile([0.0, 0.0, 0.0, 1.0], (n, 1)),
    )
    truth = ground_truth(traj, np.arange(n) + 0.01, [range(0, 3), range(3, 6)])
    assert truth.robots.tolist() == [0, 0, 0, 1, 1, 1]
    assert truth.order.tolist() == [0, 3, 1, 4, 2, 5]
    assert truth.same[2, 3] and truth.same[0, 1] and not truth.same[0, 2] and not truth.same[1, 1]
    # Frame 3 (robot 1, step 0) arrived right after frame 0 only.
    assert np.flatnonzero(truth.eligible[3]).tolist() == [0]


# --- settings and the command line -----------------------------------------------------------


def test_the_full_image_method_needs_images_and_says_how_to_give_them(tmp_path: Path) -> None:
    needs = r"--method dvpr describes camera images.*--from-pixels.*--rgbd DIR"
    with pytest.raises(ConfigError, match=needs):
        VprRunSettings(run=PlacesSettings(out=tmp_path))
    ok = VprRunSettings(run=PlacesSettings(out=tmp_path, robots=2, pixels=PixelSettings(from_pixels=True)))
    assert ok.method == "dvpr"
    with pytest.raises(ConfigError, match="--robots 2 or more"):
        VprRunSettings(run=PlacesSettings(out=tmp_path, robots=1, pixels=PixelSettings(from_pixels=True)))


def test_the_methods_settings_are_checked_as_the_services_check_them() -> None:
    with pytest.raises(ConfigError, match="vpr_wire_code must be int8 or float32, got 'pq8'"):
        DvprSettings(wire_code="pq8")
    with pytest.raises(ConfigError, match="vpr_clusters_per_robot must be >= 1"):
        DvprSettings(clusters_per_robot=0)
    part = DvprSettings(clusters_per_robot=4).component(Path("c.npz"))
    assert (part.place_method, part.vpr_centres, part.vpr_clusters_per_robot) == ("dvpr", "c.npz", 4)
    with pytest.raises(ConfigError, match="place_method must be constellations or dvpr"):
        VprSettings(place_method="both")  # type: ignore[arg-type]


def test_swarmrec_run_method_dvpr_without_pixels_stops_before_anything_starts(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code = cli_main(["run", "--method", "dvpr", "--robots", "2", "--out", str(tmp_path / "x"), "--quiet"])
    assert code == 2
    assert "describes camera images" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_swarmrec_vpr_lists_evaluate_and_centres(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        cli_main(["vpr", "--help"])
    assert e.value.code == 0
    text = capsys.readouterr().out
    assert "evaluate" in text and "centres" in text
    with pytest.raises(SystemExit):
        cli_main(["vpr", "centres"])  # --out is required
    assert "--out" in capsys.readouterr().err


def test_the_assignment_table_json_the_owners_serve_reads_back() -> None:
    table = swarm_table(10, 1, 0).assignment
    assert Assignment.from_json(json.loads(json.dumps(table.to_json()))) == table


@pytest.mark.slow
def test_swarmrec_vpr_centres_and_evaluate_write_what_their_main_writes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    centres = tmp_path / "c.npz"
    assert (
        cli_main(["vpr", "centres", "--ks", "3,5", "--worlds", "1", "--stride", "16", "--out", str(centres)])
        == 0
    )
    with np.load(centres) as data:
        assert data["k3"].shape == (3, 128) and data["k5"].shape == (5, 128)
        assert json.loads(str(data["meta"]))["worlds"] == [14_000]
    assert "2 sets of centres (k = 3, 5)" in capsys.readouterr().out
    out = tmp_path / "eval"
    argv = [
        "vpr",
        "evaluate",
        "--robots",
        "2,4",
        "--fig7-robots",
        "4",
        "--clusters-per-robot",
        "1,2",
        "--runs",
        "1",
        "--deployment-frames",
        "300",
        "--other-worlds",
        "1",
        "--out",
        str(out),
    ]
    assert cli_main(argv) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert [row["n_robots"] for row in summary["fig6"]] == [2, 4]
    assert [row["clusters_per_robot"] for row in summary["fig7"]] == [1, 2]
    assert (out / "fig6.png").stat().st_size > 0 and (out / "runs.json").is_file()
    printed = capsys.readouterr().out.splitlines()
    fig7 = printed.index("Fig. 7: 4 robots, c clusters per robot")
    assert [line.split()[0] for line in printed[fig7 + 2 : fig7 + 4]] == ["1", "2"]
