"""Readers of constellation files, label lists and TUM trajectories: good
input round-trips, bad input names the file and line."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
import pytest

from swarmrec.core.types import Trajectory
from swarmrec.datasets.constellations import read_constellations, write_constellations
from swarmrec.datasets.labels import COCO_NAMES, read_label_names
from swarmrec.datasets.tum import associate_poses, read_trajectory, write_trajectory
from swarmrec.errors import DatasetError, MalformedLineError, UnknownLabelError
from tests.conftest import label


def _folder(tmp_path: Path, files: dict[str, str]) -> Path:
    for name, text in files.items():
        (tmp_path / name).write_text(text)
    return tmp_path


def test_labels_with_spaces_are_every_token_but_the_last_three(tmp_path: Path) -> None:
    seq = read_constellations(
        _folder(tmp_path, {"1.5.txt": "teddy bear 0.1 0.2 0.3\ncell phone 1 2 3\n"})
    )
    assert seq.constellations[0].labels.tolist() == [label("teddy bear"), label("cell phone")]
    assert seq.constellations[0].positions.tolist() == [[0.1, 0.2, 0.3], [1, 2, 3]]


def test_frames_are_ordered_by_timestamp_not_by_name(tmp_path: Path) -> None:
    seq = read_constellations(
        _folder(tmp_path, {"10.0.txt": "cup 0 0 1\n", "9.5.txt": "book 0 0 1\n"})
    )
    assert seq.frame_ids == ("9.5", "10.0")
    assert seq.timestamps.tolist() == [9.5, 10.0]


def test_empty_frames_are_legal_and_counted(tmp_path: Path) -> None:
    seq = read_constellations(
        _folder(tmp_path, {"1.0.txt": "", "2.0.txt": "cup 0 0 1\n", "3.0.txt": "\n"})
    )
    assert [len(c) for c in seq.constellations] == [0, 1, 0]
    assert seq.skipped == {"empty_frames": 2}


@pytest.mark.parametrize(
    ("line", "error", "message"),
    [
        ("cup 0 0", MalformedLineError, "got 3 column"),
        ("cup 0 zero 1", MalformedLineError, "not numbers"),
        ("cup 0 nan 1", MalformedLineError, "non-finite"),
        ("cup 0 inf 1", MalformedLineError, "non-finite"),
        ("unicorn 0 0 1", UnknownLabelError, "'unicorn' is not in the label list"),
    ],
)
def test_bad_lines_name_the_file_and_line(
    tmp_path: Path, line: str, error: type[DatasetError], message: str
) -> None:
    folder = _folder(tmp_path, {"1.0.txt": "cup 0 0 1\n" + line + "\n"})
    with pytest.raises(error, match=message) as info:
        read_constellations(folder)
    assert str(info.value).startswith(f"{folder / '1.0.txt'}:2: ")


def test_a_file_name_that_is_not_a_timestamp_is_an_error(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="not a timestamp"):
        read_constellations(_folder(tmp_path, {"frame.txt": "cup 0 0 1\n"}))


def test_missing_and_empty_inputs_are_clear_errors(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="no such file"):
        read_constellations(tmp_path / "nope")
    with pytest.raises(DatasetError, match=r"no <timestamp>\.txt"):
        read_constellations(tmp_path)


def test_zip_archives_read_like_folders_and_name_the_member(tmp_path: Path) -> None:
    archive = tmp_path / "c.zip"
    with zipfile.ZipFile(archive, "w") as z:
        z.writestr("constellations/", "")
        z.writestr("constellations/2.0.txt", "book 1 2 3\n")
        z.writestr("constellations/1.0.txt", "cup 0 0 1\nchair 0 x 1\n")
    with pytest.raises(MalformedLineError) as info:
        read_constellations(archive)
    assert str(info.value).startswith(f"{archive}:constellations/1.0.txt:2:")


def test_written_constellations_read_back_exactly(tmp_path: Path) -> None:
    src = read_constellations(
        _folder(tmp_path, {"1.0.txt": "teddy bear 0.1 -0.2 1.3\nbottle 1e-3 2 3\n"})
    )
    out = write_constellations(src, tmp_path / "out")
    back = read_constellations(out)
    assert back.frame_ids == src.frame_ids
    assert np.array_equal(back.constellations[0].positions, src.constellations[0].positions)
    assert np.array_equal(back.constellations[0].labels, src.constellations[0].labels)


def test_the_published_tum_constellations_read_whole(tum_zip: Path) -> None:
    seq = read_constellations(tum_zip)
    assert len(seq) == 2585
    # Non-blank lines of all 2585 files, counted with `awk "NF>0" *.txt | wc -l`.
    assert sum(len(c) for c in seq.constellations) == 20606
    assert seq.label_names[label("bottle")] == "bottle"


def test_label_list_rejects_blank_lines_inside_and_duplicates(tmp_path: Path) -> None:
    (tmp_path / "a.names").write_text("cup\n\nbook\n")
    with pytest.raises(DatasetError, match="blank line"):
        read_label_names(tmp_path / "a.names")
    (tmp_path / "b.names").write_text("cup\nbook\ncup\n")
    with pytest.raises(DatasetError, match="repeats the one on line 1"):
        read_label_names(tmp_path / "b.names")
    (tmp_path / "c.names").write_text("cup\nbook\n\n")
    assert read_label_names(tmp_path / "c.names") == ("cup", "book")


def test_builtin_labels_are_the_80_coco_classes() -> None:
    assert len(COCO_NAMES) == 80 and COCO_NAMES[0] == "person" and COCO_NAMES[79] == "toothbrush"


def test_trajectory_round_trips_and_skips_comments(tmp_path: Path) -> None:
    path = tmp_path / "groundtruth.txt"
    path.write_text("# header\n1.0 0 0 0 0 0 0 1\n2.0 1 2 3 0 0 0.7071068 0.7071068\n")
    traj = read_trajectory(path)
    assert traj.timestamps.tolist() == [1.0, 2.0]
    write_trajectory(traj, tmp_path / "copy.txt")
    again = read_trajectory(tmp_path / "copy.txt")
    assert np.allclose(again.positions, traj.positions) and np.allclose(
        again.quaternions, traj.quaternions
    )


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("1.0 0 0 0 0 0 1\n", "expected 8 columns"),
        ("1.0 0 0 0 0 0 0 2\n", "quaternion norm"),
        ("1.0 0 0 nan 0 0 0 1\n", "non-finite"),
        ("2.0 0 0 0 0 0 0 1\n1.0 0 0 0 0 0 0 1\n", "timestamps must increase"),
    ],
)
def test_bad_trajectory_lines_name_the_line(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "gt.txt"
    path.write_text(text)
    with pytest.raises(MalformedLineError, match=message):
        read_trajectory(path)


def test_poses_are_associated_by_nearest_time_later_on_ties() -> None:
    traj = Trajectory(np.array([0.0, 1.0, 2.0]), np.zeros((3, 3)), np.tile([0, 0, 0, 1.0], (3, 1)))
    assert associate_poses(traj, [0.1, 0.5, 1.6, 2.0], max_dt=0.5).tolist() == [0, 1, 2, 2]


def test_a_frame_far_from_every_pose_is_an_error() -> None:
    traj = Trajectory(np.array([0.0, 1.0]), np.zeros((2, 3)), np.tile([0, 0, 0, 1.0], (2, 1)))
    with pytest.raises(DatasetError, match="no pose within"):
        associate_poses(traj, [5.0], max_dt=0.05)


def test_a_dataset_folder_is_read_from_its_constellations_subfolder(tmp_path: Path) -> None:
    # The layout `swarmrec synth` writes: frames in constellations/, other .txt beside it.
    _folder(tmp_path, {"groundtruth.txt": "# timestamp tx ty tz qx qy qz qw\n", "world.txt": "cup 0 0 0\n"})
    (tmp_path / "constellations").mkdir()
    _folder(tmp_path / "constellations", {"1.0.txt": "cup 0 0 1\n", "2.0.txt": "book 0 0 1\n"})
    assert read_constellations(tmp_path).frame_ids == ("1.0", "2.0")
