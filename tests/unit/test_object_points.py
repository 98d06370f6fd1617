"""Object to point on synthetic depth images whose geometry is known, so every expected
point comes from the pinhole formula X = (u - cx) Z / fx worked by hand, not from the code."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import pytest

from swarmrec.detection import (
    CameraIntrinsics,
    DetectionError,
    object_points,
    transform_points,
)
from swarmrec.errors import ConfigError

FX, FY, CX, CY, SCALE = 535.4, 539.2, 320.1, 247.6, 5000.0
H, W = 480, 640


def _plane(metres: float) -> npt.NDArray[np.uint16]:
    return np.full((H, W), round(metres * SCALE), dtype=np.uint16)


def test_tum_fr3_intrinsics_are_the_defaults() -> None:
    cam = CameraIntrinsics()
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.depth_scale) == (FX, FY, CX, CY, SCALE)


def test_box_on_a_fronto_parallel_plane_gives_its_centre_pixel_at_the_plane_depth() -> None:
    # Pixel centres inside [300, 341) x [200, 251): columns 300..340 and rows 200..250, so the
    # median pixel is (320, 225); on a plane every axis is monotonic in the pixel, so it is the median.
    result = object_points(_plane(2.0), [[300.0, 200.0, 341.0, 251.0]])
    assert result.kept.tolist() == [0] and result.n_dropped == 0
    assert result.points[0] == pytest.approx([(320 - CX) * 2.0 / FX, (225 - CY) * 2.0 / FY, 2.0], abs=1e-12)


def test_an_object_at_a_known_point_is_recovered_exactly() -> None:
    # A 5 x 5 patch at 2.5 m centred on pixel (420, 200) in front of a wall at 4 m.
    depth = _plane(4.0)
    depth[198:203, 418:423] = round(2.5 * SCALE)
    result = object_points(depth, [[418.0, 198.0, 423.0, 203.0]])
    assert result.points[0] == pytest.approx([(420 - CX) * 2.5 / FX, (200 - CY) * 2.5 / FY, 2.5], abs=1e-12)


def test_the_median_ignores_a_minority_of_background_pixels() -> None:
    # A 10 x 10 box with 60 pixels on the object at 1.5 m and 40 on the wall at 6 m.
    depth = _plane(6.0)
    depth[100:106, 100:110] = round(1.5 * SCALE)
    result = object_points(depth, [[100.0, 100.0, 110.0, 110.0]])
    assert result.points[0][2] == 1.5


def test_an_even_number_of_pixels_takes_the_mean_of_the_two_middle_ones() -> None:
    depth = np.zeros((H, W), np.uint16)
    depth[10, 10], depth[10, 11] = 5000, 15000  # 1 m and 3 m
    result = object_points(depth, [[10.0, 10.0, 12.0, 11.0]])
    assert result.points[0][2] == 2.0
    # X of the two pixels: (10 - cx) 1 / fx and (11 - cx) 3 / fx; the median is their mean.
    assert result.points[0][0] == pytest.approx(((10 - CX) / FX + (11 - CX) * 3 / FX) / 2, abs=1e-12)


def test_holes_in_the_depth_are_skipped() -> None:
    depth = _plane(3.0)
    depth[200:251, 300:320] = 0  # the left 20 of 41 columns have no reading
    result = object_points(depth, [[300.0, 200.0, 341.0, 251.0]])
    # Columns 320..340 remain: median column 330, median row 225.
    assert result.points[0] == pytest.approx([(330 - CX) * 3.0 / FX, (225 - CY) * 3.0 / FY, 3.0], abs=1e-12)


def test_non_finite_depth_in_a_float_image_is_skipped() -> None:
    depth = np.full((H, W), 2.0)
    depth[50, 50:53] = [np.nan, np.inf, -1.0]
    result = object_points(depth, [[50.0, 50.0, 54.0, 51.0]], CameraIntrinsics(depth_scale=1.0))
    # Only pixel (53, 50) is valid.
    assert result.points[0] == pytest.approx([(53 - CX) * 2.0 / FX, (50 - CY) * 2.0 / FY, 2.0], abs=1e-12)


def test_zero_depth_everywhere_drops_and_counts_every_box() -> None:
    result = object_points(np.zeros((H, W), np.uint16), [[0, 0, 10, 10], [100, 100, 200, 200], [5, 5, 6, 6]])
    assert result.points.shape == (0, 3)
    assert result.kept.tolist() == [] and result.dropped.tolist() == [0, 1, 2] and result.n_dropped == 3


def test_kept_and_dropped_keep_the_box_order() -> None:
    depth = _plane(1.0)
    depth[:, 200:400] = 0
    result = object_points(depth, [[10, 10, 20, 20], [250, 10, 350, 20], [500, 10, 510, 20]])
    assert result.kept.tolist() == [0, 2] and result.dropped.tolist() == [1]
    assert result.points.shape == (2, 3)


def test_max_depth_leaves_out_far_pixels() -> None:
    depth = _plane(5.0)
    depth[0:10, 0:3] = round(1.0 * SCALE)  # 30 near pixels in a 10 x 10 box of far ones
    boxes = [[0.0, 0.0, 10.0, 10.0], [100.0, 100.0, 110.0, 110.0]]
    assert object_points(depth, boxes).points[0][2] == 5.0
    near = object_points(depth, boxes, max_depth=4.0)
    assert near.kept.tolist() == [0] and near.dropped.tolist() == [1]
    assert near.points[0] == pytest.approx([(1 - CX) * 1.0 / FX, (4.5 - CY) * 1.0 / FY, 1.0], abs=1e-12)


def test_boxes_partly_outside_the_image_are_clipped_to_it() -> None:
    # [-10, -10, 5, 5) holds columns and rows 0..4 of the image: median pixel (2, 2).
    # [630, 470, 700, 900) holds columns 630..639 and rows 470..479: medians 634.5 and 474.5.
    result = object_points(_plane(2.0), [[-10.0, -10.0, 5.0, 5.0], [630.0, 470.0, 700.0, 900.0]])
    assert result.points[0] == pytest.approx([(2 - CX) * 2.0 / FX, (2 - CY) * 2.0 / FY, 2.0], abs=1e-12)
    assert result.points[1] == pytest.approx(
        [(634.5 - CX) * 2.0 / FX, (474.5 - CY) * 2.0 / FY, 2.0], abs=1e-12
    )


def test_boxes_outside_the_image_or_not_finite_are_dropped() -> None:
    boxes = [
        [700, 10, 800, 20],
        [10, -50, 20, -1],
        [np.nan, 0, 10, 10],
        [0, 0, np.inf, 10],
        [3.2, 3.2, 3.4, 3.4],
    ]
    result = object_points(_plane(1.0), boxes)
    assert result.dropped.tolist() == [0, 1, 2, 3, 4]


def test_no_boxes_gives_no_points() -> None:
    result = object_points(_plane(1.0), np.zeros((0, 4)))
    assert result.points.shape == (0, 3) and result.n_dropped == 0
    assert object_points(_plane(1.0), []).points.shape == (0, 3)


def test_other_intrinsics_are_used() -> None:
    cam = CameraIntrinsics(fx=100.0, fy=200.0, cx=10.0, cy=20.0, depth_scale=1000.0)
    depth = np.full((40, 40), 3000, np.uint16)  # 3 m at 1000 units per metre
    result = object_points(depth, [[30.0, 0.0, 31.0, 1.0]], cam)
    assert result.points[0] == pytest.approx([(30 - 10) * 3.0 / 100, (0 - 20) * 3.0 / 200, 3.0], abs=1e-12)


def test_transform_points_applies_rotation_then_translation() -> None:
    # 90 degrees about z: x -> y, y -> -x; then translate by (1, 2, 3).
    pose = np.array([[0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]], float)
    moved = transform_points([[1.0, 0.0, 0.0], [0.0, 2.0, 5.0]], pose)
    assert moved.tolist() == [[1.0, 3.0, 3.0], [-1.0, 2.0, 8.0]]


@pytest.mark.parametrize(
    ("depth", "boxes"),
    [
        (np.zeros((4, 4, 1)), [[0, 0, 1, 1]]),
        (np.zeros((4, 4)), [[0, 0, 1]]),
        (np.zeros((4, 4)), [0, 0, 1, 1]),
    ],
)
def test_bad_shapes_are_detection_errors(depth: npt.NDArray[np.float64], boxes: list[object]) -> None:
    with pytest.raises(DetectionError, match="expected"):
        object_points(depth, boxes)


def test_transform_points_rejects_bad_shapes() -> None:
    with pytest.raises(DetectionError, match="4 x 4"):
        transform_points([[0.0, 0.0, 0.0]], np.eye(3))
    with pytest.raises(DetectionError, match=r"\(n, 3\)"):
        transform_points([0.0, 0.0, 0.0], np.eye(4))


@pytest.mark.parametrize(
    "changes", [{"fx": 0.0}, {"fy": -1.0}, {"depth_scale": float("nan")}, {"cx": float("inf")}]
)
def test_bad_intrinsics_are_config_errors(changes: dict[str, float]) -> None:
    with pytest.raises(ConfigError):
        CameraIntrinsics(**changes)


def test_max_depth_must_be_positive() -> None:
    with pytest.raises(ConfigError, match="max_depth"):
        object_points(_plane(1.0), [[0, 0, 1, 1]], max_depth=0.0)
