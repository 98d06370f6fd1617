"""The TUM RGB-D sequence reader on tiny sequences written here: association as TUM's
associate.py does it, ground-truth lookup, and bad files giving typed errors or counted skips."""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import pytest

from swarmrec.datasets.tum_rgbd import RgbdImageError, associate, load_rgbd, read_file_list, read_tum_rgbd
from swarmrec.errors import ConfigError, DatasetError, MalformedLineError

H, W = 6, 8


def _write_sequence(
    root: Path,
    rgb: Sequence[float],
    depth: Sequence[float],
    groundtruth: Sequence[Sequence[float]] | None = None,
) -> Path:
    """A sequence with one tiny PNG per stamp: RGB pixel (B, G, R) = (k, 2k, 3k), depth = 1000 + k."""
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    lines = ["# color images", "# timestamp filename"]
    for k, t in enumerate(rgb):
        image = np.zeros((H, W, 3), np.uint8)
        image[:] = (k, 2 * k, 3 * k)
        cv2.imwrite(str(root / "rgb" / f"{t:.6f}.png"), image)
        lines.append(f"{t:.6f} rgb/{t:.6f}.png")
    (root / "rgb.txt").write_text("\n".join(lines) + "\n")
    lines = ["# depth maps"]
    for k, t in enumerate(depth):
        cv2.imwrite(str(root / "depth" / f"{t:.6f}.png"), np.full((H, W), 1000 + k, np.uint16))
        lines.append(f"{t:.6f} depth/{t:.6f}.png")
    (root / "depth.txt").write_text("\n".join(lines) + "\n")
    if groundtruth is not None:
        rows = ["# timestamp tx ty tz qx qy qz qw"] + [
            " ".join(f"{v:.6f}" for v in row) for row in groundtruth
        ]
        (root / "groundtruth.txt").write_text("\n".join(rows) + "\n")
    return root


def _reference_associate(first: list[float], second: list[float], max_dt: float) -> list[tuple[int, int]]:
    """TUM associate.py's algorithm, written out literally on (stamp, index) pairs."""
    candidates = sorted(
        (abs(a - b), i, j)
        for (i, a), (j, b) in itertools.product(enumerate(first), enumerate(second))
        if abs(a - b) < max_dt
    )
    free_a, free_b = set(range(len(first))), set(range(len(second)))
    pairs = []
    for _, i, j in candidates:
        if i in free_a and j in free_b:
            free_a.remove(i)
            free_b.remove(j)
            pairs.append((i, j))
    return sorted(pairs)


def test_frames_pair_rgb_with_the_depth_image_closest_in_time(tmp_path: Path) -> None:
    # 1.066 has its nearest depth image 0.034 s away, beyond 0.02 s: no frame, counted.
    seq = read_tum_rgbd(_write_sequence(tmp_path, [1.0, 1.033, 1.066], [1.005, 1.030, 1.1]))
    assert [f.index for f in seq] == [0, 1]
    assert [f.timestamp for f in seq] == [1.0, 1.033]
    assert [f.rgb_path.name for f in seq] == ["1.000000.png", "1.033000.png"]
    assert [f.depth_path.name for f in seq] == ["1.005000.png", "1.030000.png"]
    assert seq.skipped == {"rgb_without_depth": 1, "depth_without_rgb": 1}
    assert not seq.has_groundtruth and all(f.pose is None for f in seq)


def test_association_is_one_to_one_by_smallest_difference() -> None:
    # Both RGB stamps are within 0.02 s of the one depth stamp; the closer (1.010) takes it.
    assert associate([1.000, 1.010], [1.008]).tolist() == [[1, 0]]


def test_association_ties_go_to_the_earlier_stamp() -> None:
    assert associate([1.0, 1.5], [1.25], max_dt=0.3).tolist() == [[0, 0]]


def test_association_tolerance_is_strict() -> None:
    assert associate([1.0], [1.25], max_dt=0.25).tolist() == []
    assert associate([1.0], [1.25], max_dt=0.2500001).tolist() == [[0, 0]]


def test_association_matches_tum_associate_py_on_random_stamps() -> None:
    rng = np.random.default_rng(3)
    first = np.sort(rng.uniform(0, 5, 300)).tolist()
    second = np.sort(rng.uniform(0, 5, 280)).tolist()
    expected = _reference_associate(first, second, 0.02)
    assert len(expected) > 50
    assert [tuple(p) for p in associate(first, second, 0.02).tolist()] == expected


def test_association_of_nothing_is_nothing() -> None:
    assert associate([], [1.0]).shape == (0, 2)


def test_association_needs_a_positive_tolerance() -> None:
    with pytest.raises(ConfigError, match="max_dt"):
        associate([1.0], [1.0], max_dt=0.0)


def test_frames_get_the_nearest_ground_truth_pose_within_the_tolerance(tmp_path: Path) -> None:
    s = math.sqrt(0.5)  # 90 degrees about z: qz = qw = sin 45 = cos 45
    groundtruth = [
        [0.99, 1.0, 2.0, 3.0, 0.0, 0.0, s, s],
        [1.015, 9.0, 9.0, 9.0, 0.0, 0.0, 0.0, 1.0],
        [2.00, 4.0, 5.0, 6.0, 0.0, 0.0, 0.0, 1.0],
    ]
    # Frame 1.0: poses 0.01 and 0.015 away -> the first. Frame 1.5: nearest 0.485 away -> None.
    seq = read_tum_rgbd(_write_sequence(tmp_path, [1.0, 1.5], [1.0, 1.5], groundtruth))
    assert seq.has_groundtruth
    first, second = seq.frames
    assert first.pose is not None
    expected = [[0.0, -1.0, 0.0, 1.0], [1.0, 0.0, 0.0, 2.0], [0.0, 0.0, 1.0, 3.0], [0.0, 0.0, 0.0, 1.0]]
    np.testing.assert_allclose(first.pose, expected, atol=1e-6)
    assert second.pose is None


def test_pose_tolerance_is_configurable(tmp_path: Path) -> None:
    groundtruth = [[1.1, 1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0]]
    root = _write_sequence(tmp_path, [1.0], [1.0], groundtruth)
    assert read_tum_rgbd(root).frames[0].pose is None
    pose = read_tum_rgbd(root, pose_max_dt=0.2).frames[0].pose
    assert pose is not None and pose[:3, 3].tolist() == [1.0, 2.0, 3.0]


def test_images_are_bgr_uint8_and_raw_uint16_depth(tmp_path: Path) -> None:
    seq = read_tum_rgbd(_write_sequence(tmp_path, [1.0, 2.0], [1.0, 2.0]))
    loaded = list(seq.images())
    assert [frame.index for frame, _, _ in loaded] == [0, 1]
    _, rgb, depth = loaded[1]
    assert rgb.dtype == np.uint8 and rgb.shape == (H, W, 3) and rgb[0, 0].tolist() == [1, 2, 3]
    assert depth.dtype == np.uint16 and depth.shape == (H, W) and (depth == 1001).all()


def test_a_corrupt_image_is_an_error_or_a_counted_skip(tmp_path: Path) -> None:
    seq = read_tum_rgbd(_write_sequence(tmp_path, [1.0, 2.0, 3.0], [1.0, 2.0, 3.0]))
    seq.frames[1].rgb_path.write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    with pytest.raises(DatasetError, match="cannot decode RGB image") as info:
        list(seq.images())
    assert info.value.source == seq.frames[1].rgb_path
    errors: list[DatasetError] = []
    assert [frame.index for frame, _, _ in seq.images(errors)] == [0, 2]
    assert len(errors) == 1 and errors[0].source == seq.frames[1].rgb_path


def test_a_missing_image_is_an_error_naming_it(tmp_path: Path) -> None:
    seq = read_tum_rgbd(_write_sequence(tmp_path, [1.0], [1.0]))
    seq.frames[0].depth_path.unlink()
    with pytest.raises(RgbdImageError, match="depth image is missing") as info:
        list(seq.images())
    assert info.value.problem == "missing"


def test_an_empty_image_file_is_an_error(tmp_path: Path) -> None:
    seq = read_tum_rgbd(_write_sequence(tmp_path, [1.0], [1.0]))
    seq.frames[0].depth_path.write_bytes(b"")
    with pytest.raises(DatasetError, match="cannot decode depth image"):
        list(seq.images())


def test_depth_of_another_size_than_the_rgb_image_is_an_error(tmp_path: Path) -> None:
    seq = read_tum_rgbd(_write_sequence(tmp_path, [1.0], [1.0]))
    cv2.imwrite(str(seq.frames[0].depth_path), np.zeros((H + 1, W), np.uint16))
    with pytest.raises(RgbdImageError, match=r"depth is 8x7 but its RGB image 1\.000000\.png is 8x6") as info:
        load_rgbd(seq.frames[0].rgb_path, seq.frames[0].depth_path)
    assert info.value.problem == "size_mismatch"


def test_an_8_bit_depth_image_is_an_error(tmp_path: Path) -> None:
    seq = read_tum_rgbd(_write_sequence(tmp_path, [1.0], [1.0]))
    cv2.imwrite(str(seq.frames[0].depth_path), np.zeros((H, W), np.uint8))
    with pytest.raises(RgbdImageError, match="16-bit single-channel") as info:
        list(seq.images())
    assert info.value.problem == "corrupt"


def test_file_lists_skip_comments_and_blank_lines(tmp_path: Path) -> None:
    path = tmp_path / "rgb.txt"
    path.write_text("# header\n\n1.5 rgb/a.png\n2.5,rgb/b.png\n")
    stamps, names = read_file_list(path)
    assert stamps.tolist() == [1.5, 2.5] and names == ["rgb/a.png", "rgb/b.png"]


@pytest.mark.parametrize(
    ("text", "line", "reason"),
    [
        ("# c\n1.0 a.png extra\n", 2, "expected 'timestamp filename'"),
        ("1.0\n", 1, "expected 'timestamp filename'"),
        ("1.0 a.png\nabc b.png\n", 2, "not a number"),
        ("nan a.png\n", 1, "non-finite"),
        ("2.0 a.png\n1.0 b.png\n", 2, "timestamps must increase"),
    ],
)
def test_bad_file_list_lines_name_the_line(tmp_path: Path, text: str, line: int, reason: str) -> None:
    path = tmp_path / "depth.txt"
    path.write_text(text)
    with pytest.raises(MalformedLineError, match=reason) as info:
        read_file_list(path)
    assert info.value.line == line


def test_a_sequence_without_rgb_txt_is_an_error(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match=r"rgb\.txt: cannot read file list"):
        read_tum_rgbd(tmp_path)


def test_a_bad_groundtruth_file_is_an_error(tmp_path: Path) -> None:
    root = _write_sequence(tmp_path, [1.0], [1.0])
    (root / "groundtruth.txt").write_text("1.0 0 0 0\n")
    with pytest.raises(MalformedLineError, match="8 columns"):
        read_tum_rgbd(root)


def test_pose_tolerance_must_be_positive(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="pose_max_dt"):
        read_tum_rgbd(_write_sequence(tmp_path, [1.0], [1.0]), pose_max_dt=-1.0)
