"""The RGB-D renderer of the synthetic office: images, determinism, boxes and depth against the
world's geometry (computed here from the poses and intrinsics, not from the renderer), occlusion,
and the TUM RGB-D folder it writes read back by the project's own readers."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from swarmrec.datasets.constellations import read_constellations
from swarmrec.datasets.tum_rgbd import read_tum_rgbd
from swarmrec.detection.points import CameraIntrinsics, object_points, transform_points
from swarmrec.errors import ConfigError
from swarmrec.synthetic import (
    OfficeConfig,
    OfficeWorld,
    SyntheticDataset,
    coco_names,
    generate_office,
    label_index,
    quaternions_to_matrices,
)
from swarmrec.synthetic.render import (
    RenderCommand,
    RenderSettings,
    SceneRenderer,
    SequenceRenderer,
    _parse_args,
    main,
    write_rgbd_sequence,
)
from swarmrec.synthetic.render_mesh import SceneBuilder
from swarmrec.synthetic.render_shapes import CLASS_SHAPES

pytestmark = pytest.mark.unit

SMALL = RenderSettings(width=160, height=120)
# Frames of the easy sequence that look at the desks from different sides.
FRAMES = (0, 13, 27, 41, 55)
# Compact classes: the surface a pixel shows is within a few centimetres of the object's point
# from any side (a flat book or keyboard seen at a grazing angle shows its near half).
COMPACT = {"cup", "bottle", "mouse"}


@pytest.fixture(scope="module")
def ds() -> SyntheticDataset:
    return generate_office(OfficeConfig.preset("easy", n_frames=60, seed=2))


@pytest.fixture(scope="module")
def renderer(ds: SyntheticDataset) -> SequenceRenderer:
    return SequenceRenderer(ds)


def _camera_points(ds: SyntheticDataset, i: int) -> np.ndarray:
    """Every world object in the camera frame of frame ``i``: ``R^T (p - t)`` from the stored pose."""
    rotation = quaternions_to_matrices(ds.trajectory.quaternions[i])[0]
    result: np.ndarray = (ds.world.positions - ds.trajectory.positions[i]) @ rotation
    return result


def test_frame_has_tum_image_types_and_boxes_inside_the_image(ds: SyntheticDataset) -> None:
    frame = SequenceRenderer(ds, SMALL).render(0)
    assert frame.rgb.shape == (120, 160, 3) and frame.rgb.dtype == np.uint8
    assert frame.depth.shape == (120, 160) and frame.depth.dtype == np.uint16
    assert frame.instances.shape == (120, 160)
    n = len(frame.objects)
    assert n > 5
    assert frame.boxes.shape == (n, 4) and frame.points.shape == (n, 3)
    assert (
        np.all(frame.boxes[:, :2] >= 0)
        and np.all(frame.boxes[:, 2] <= 160)
        and np.all(frame.boxes[:, 3] <= 120)
    )
    assert np.all(frame.boxes[:, 2] > frame.boxes[:, 0]) and np.all(frame.boxes[:, 3] > frame.boxes[:, 1])
    np.testing.assert_array_equal(frame.labels, ds.world.labels[frame.objects])
    assert np.all(frame.pixels > 0)
    assert np.all((frame.visible_fraction > 0) & (frame.visible_fraction <= 1))
    # Depth readings in metres are plausible for a room a few metres across.
    metres = frame.depth[frame.depth > 0] / 5000.0
    assert metres.size > 0.5 * frame.depth.size and metres.min() >= 0.4 and metres.max() <= 5.0


def test_same_seed_renders_the_same_frames_in_any_order_and_another_seed_does_not(
    ds: SyntheticDataset,
) -> None:
    first = SequenceRenderer(ds, SMALL)
    a = first.render(7)
    first.render(3)
    b = SequenceRenderer(generate_office(ds.config), SMALL).render(7)
    again = first.render(7)
    for other in (b, again):
        np.testing.assert_array_equal(a.rgb, other.rgb)
        np.testing.assert_array_equal(a.depth, other.depth)
        np.testing.assert_array_equal(a.boxes, other.boxes)
    c = SequenceRenderer(generate_office(OfficeConfig.preset("easy", n_frames=60, seed=3)), SMALL).render(7)
    assert not np.array_equal(a.rgb, c.rgb)


def test_boxes_contain_the_projected_point_of_every_fully_visible_object(
    ds: SyntheticDataset, renderer: SequenceRenderer
) -> None:
    cam = ds.camera
    checked = 0
    for i in FRAMES:
        frame = renderer.render(i)
        p = _camera_points(ds, i)[frame.objects]
        u = cam.fx * p[:, 0] / p[:, 2] + cam.cx
        v = cam.fy * p[:, 1] / p[:, 2] + cam.cy
        full = (frame.visible_fraction == 1.0) & (p[:, 2] > 0.1)
        full &= (u >= 0) & (u <= cam.width - 1) & (v >= 0) & (v <= cam.height - 1)
        x1, y1, x2, y2 = frame.boxes[full].T
        # Pixel u samples the ray through u and covers [u, u + 1): allow the one-pixel rounding.
        assert np.all((u[full] >= x1 - 1) & (u[full] <= x2) & (v[full] >= y1 - 1) & (v[full] <= y2))
        checked += int(full.sum())
    assert checked >= 20


def test_depth_of_an_unoccluded_compact_object_recovers_its_point(
    ds: SyntheticDataset, renderer: SequenceRenderer
) -> None:
    cam = ds.camera
    intrinsics = CameraIntrinsics(cam.fx, cam.fy, cam.cx, cam.cy, 5000.0)
    checked = 0
    for i in FRAMES:
        frame = renderer.render(i)
        expected = _camera_points(ds, i)
        for k, box, fraction, pixels in zip(
            frame.objects, frame.boxes, frame.visible_fraction, frame.pixels, strict=True
        ):
            if ds.world.label_of(k) not in COMPACT or fraction < 0.99 or pixels < 40:
                continue
            if box[0] == 0 or box[1] == 0 or box[2] == cam.width or box[3] == cam.height:
                continue  # cut by the image border: the box's centre is not the object's
            col, row = (box[0] + box[2] - 1) // 2, (box[1] + box[3] - 1) // 2
            if frame.instances[row, col] != k or frame.depth[row, col] == 0:
                continue  # a non-convex outline (a mug's handle) leaves the centre off the object
            z = frame.depth[row, col] / 5000.0
            seen = cam.unproject(np.float64(col), np.float64(row), np.float64(z))
            # A pixel shows the surface, up to a radius (a mug's handle: 5.6 cm) before the point.
            assert np.linalg.norm(seen - expected[k]) < 0.065, (i, ds.world.label_of(k))
            # The detector's median of the box's depth points lands closer (1-2 cm here).
            median = object_points(frame.depth, box[None, :], intrinsics).points[0]
            assert np.linalg.norm(median - expected[k]) < 0.035, (i, ds.world.label_of(k))
            checked += 1
    assert checked >= 8


def _looking_along_y(z: float) -> tuple[np.ndarray, np.ndarray]:
    """A camera at (0, 0, z) looking along world +y, level: columns right, down, forward."""
    rotation = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    return rotation, np.array([0.0, 0.0, z])


def test_a_nearer_object_hides_a_farther_one_and_cuts_a_second_in_part() -> None:
    labels = np.array([label_index("tvmonitor"), label_index("bottle"), label_index("bottle")])
    positions = np.array([[0.0, 1.2, 1.0], [0.0, 2.5, 1.0], [0.57, 2.5, 1.0]])
    world = OfficeWorld(
        labels=labels,
        positions=positions,
        groups=("screen", "behind", "beside"),
        facing=np.array([[0.0, -1.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]),
        occluder_radius=np.zeros(3),
        label_names=coco_names(),
    )
    rotation, position = _looking_along_y(1.0)
    renderer = SceneRenderer(
        world, settings=RenderSettings(rgb_noise=0.0, depth_noise=0.0), room_points=position[None, :]
    )
    frame = renderer.render(rotation, position)
    assert 0 in frame.objects and 1 not in frame.objects
    # The hidden bottle's centre projects to the principal point: the depth there is the screen's.
    row, col = round(renderer.camera.cy), round(renderer.camera.cx)
    assert frame.instances[row, col] == 0
    assert abs(frame.depth[row, col] / 5000.0 - 1.18) < 0.01
    partial = float(frame.visible_fraction[list(frame.objects).index(2)])
    assert 0.1 < partial < 0.9
    # Seen from the side, nothing is in front of the far bottle any more: all of it shows.
    side = renderer.render(rotation, np.array([1.0, 0.0, 1.0]))
    assert 1 in side.objects and float(side.visible_fraction[list(side.objects).index(1)]) == 1.0


def test_written_folder_reads_back_as_tum_rgbd_with_its_boxes_and_constellations(
    ds: SyntheticDataset, tmp_path: Path
) -> None:
    chosen = [0, 4, 8]
    summary = write_rgbd_sequence(ds, tmp_path, frames=chosen, settings=SMALL)
    assert summary.frames == 3 and summary.boxes > 0
    seq = read_tum_rgbd(tmp_path)
    ids = [ds.sequence.frame_ids[i] for i in chosen]
    assert [f.timestamp for f in seq] == [float(x) for x in ids]
    assert seq.has_groundtruth and seq.skipped == {"rgb_without_depth": 0, "depth_without_rgb": 0}
    renderer = SequenceRenderer(ds, SMALL)
    for (frame, rgb, depth), i in zip(seq.images(), chosen, strict=True):
        expected = renderer.render(i)
        np.testing.assert_array_equal(rgb, expected.rgb)
        np.testing.assert_array_equal(depth, expected.depth)
        assert frame.pose is not None
        rotation = quaternions_to_matrices(ds.trajectory.quaternions[i])[0]
        np.testing.assert_allclose(frame.pose[:3, :3], rotation, atol=1e-6)
        np.testing.assert_allclose(frame.pose[:3, 3], ds.trajectory.positions[i], atol=1e-6)

    boxes = json.loads((tmp_path / "boxes.json").read_text())
    assert (boxes["width"], boxes["height"]) == (160, 120)
    assert boxes["label_names"] == list(coco_names())
    assert [f["id"] for f in boxes["frames"]] == ids
    first = boxes["frames"][0]["objects"]
    expected0 = renderer.render(0)
    assert [o["box"] for o in first] == expected0.boxes.tolist()
    assert [o["class_id"] for o in first] == expected0.labels.tolist()
    assert all(coco_names()[o["class_id"]] == o["label"] for o in first)

    exact = read_constellations(tmp_path)
    world = read_constellations(tmp_path / "world_constellations")
    assert exact.frame_ids == world.frame_ids == tuple(ids)
    for c, w, frame, i in zip(exact.constellations, world.constellations, seq, chosen, strict=True):
        truth = renderer.render(i).constellation()
        np.testing.assert_array_equal(c.labels, truth.labels)
        np.testing.assert_array_equal(c.positions, truth.positions)  # repr floats: exact
        np.testing.assert_array_equal(w.labels, c.labels)
        assert frame.pose is not None
        np.testing.assert_allclose(transform_points(c.positions, frame.pose), w.positions, atol=1e-6)


def test_writer_refuses_a_non_empty_folder_unless_told_to_overwrite_and_bad_frame_lists(
    ds: SyntheticDataset, tmp_path: Path
) -> None:
    write_rgbd_sequence(ds, tmp_path, frames=[0, 1], settings=SMALL)
    with pytest.raises(FileExistsError):
        write_rgbd_sequence(ds, tmp_path, frames=[2], settings=SMALL)
    write_rgbd_sequence(ds, tmp_path, frames=[2], settings=SMALL, overwrite=True)
    assert len(list((tmp_path / "rgb").iterdir())) == 1
    assert len(read_constellations(tmp_path)) == 1
    for frames in ([], [3, 3], [2, 1], [len(ds.trajectory)]):
        with pytest.raises(ConfigError, match="frames"):
            write_rgbd_sequence(ds, tmp_path / "other", frames=frames, settings=SMALL)


def test_command_line_renders_every_kth_frame_at_the_size_asked(tmp_path: Path) -> None:
    command = _parse_args(
        ["--out", str(tmp_path), "--frames", "7", "--seed", "1", "--every", "3", "--size", "80x60"]
    )
    assert command == RenderCommand(out=tmp_path, frames=7, seed=1, every=3, width=80, height=60)
    summary = main(
        RenderCommand(out=tmp_path, frames=7, seed=1, every=3, width=80, height=60, progress=False)
    )
    assert summary.frames == 3
    seq = read_tum_rgbd(tmp_path)
    assert len(seq) == 3
    _, rgb, depth = next(seq.images())
    assert rgb.shape == (60, 80, 3) and depth.shape == (60, 80)
    with pytest.raises(SystemExit):
        _parse_args(["--out", str(tmp_path), "--size", "80by60"])


def test_every_class_of_the_world_has_a_shape_that_holds_its_point() -> None:
    world = generate_office(OfficeConfig(n_frames=2)).world
    assert {world.label_of(k) for k in range(len(world))} <= set(CLASS_SHAPES)
    rng = np.random.default_rng(0)
    for label, shape in CLASS_SHAPES.items():
        builder = SceneBuilder()
        verts = np.concatenate([builder.add_part(p, np.eye(3), np.zeros(3), 0) for p in shape(rng)])
        lo, hi = verts.reshape(-1, 3).min(axis=0), verts.reshape(-1, 3).max(axis=0)
        assert np.all(lo <= 1e-9) and np.all(hi >= -1e-9), label


def test_a_class_without_a_shape_and_bad_settings_are_refused() -> None:
    world = OfficeWorld(
        labels=np.array([label_index("toilet")]),
        positions=np.zeros((1, 3)),
        groups=("bathroom",),
        facing=np.zeros((1, 3)),
        occluder_radius=np.zeros(1),
        label_names=coco_names(),
    )
    with pytest.raises(ConfigError, match="toilet"):
        SceneRenderer(world)
    with pytest.raises(ConfigError, match="width"):
        RenderSettings(width=0)
    with pytest.raises(ConfigError, match="depth_range_m"):
        RenderSettings(depth_range_m=(2.0, 1.0))
