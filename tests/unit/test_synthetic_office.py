"""The built-in synthetic office: determinism, TUM-like statistics, geometry, files."""

from __future__ import annotations

import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

import swarmrec.synthetic as synthetic
from swarmrec.core.types import Constellation, ConstellationSequence
from swarmrec.datasets.constellations import read_constellations
from swarmrec.errors import ConfigError, UnknownLabelError
from swarmrec.synthetic import (
    OfficeConfig,
    SyntheticDataset,
    coco_names,
    covisibility,
    generate_office,
    matrices_to_quaternions,
    quaternions_to_matrices,
    write_dataset,
)
from swarmrec.synthetic.stats import (
    StatsSettings,
    compare_markdown,
    main,
    sequence_stats,
)

pytestmark = pytest.mark.unit

TUM_ZIP = (
    Path(__file__).resolve().parents[2].parent
    / "shared"
    / "data"
    / "tum_fr3_long_office_household_constellations.zip"
)
OFFICE_LABELS = {"bottle", "book", "chair", "tvmonitor", "mouse", "keyboard", "cup"}


@pytest.fixture(scope="module")
def default_ds() -> SyntheticDataset:
    return generate_office(OfficeConfig())


def _label_counts(seq: ConstellationSequence) -> Counter[str]:
    return Counter(seq.label_names[int(k)] for c in seq.constellations for k in c.labels)


def _same(a: SyntheticDataset, b: SyntheticDataset) -> bool:
    if a.sequence.frame_ids != b.sequence.frame_ids:
        return False
    if not np.array_equal(a.trajectory.quaternions, b.trajectory.quaternions):
        return False
    return all(
        np.array_equal(x.labels, y.labels) and np.array_equal(x.positions, y.positions)
        for x, y in zip(a.sequence.constellations, b.sequence.constellations, strict=True)
    )


def _parse_constellation(text: str) -> tuple[list[str], np.ndarray]:
    labels, points = [], []
    for line in text.splitlines():
        tokens = line.split()
        labels.append(" ".join(tokens[:-3]))
        points.append([float(v) for v in tokens[-3:]])
    return labels, np.array(points, dtype=np.float64).reshape(-1, 3)


# --- public surface --------------------------------------------------------


def test_public_all_names_exist_in_the_package() -> None:
    for name in synthetic.__all__:
        assert hasattr(synthetic, name), name


def test_bundled_label_list_is_the_80_coco_names_in_yolo_spelling() -> None:
    names = coco_names()
    assert len(names) == 80
    assert names[0] == "person" and names[79] == "toothbrush"
    assert {"tvmonitor", "diningtable", "pottedplant", "sofa", "teddy bear"} <= set(names)


# --- determinism -----------------------------------------------------------


def test_same_seed_gives_an_identical_dataset(default_ds: SyntheticDataset) -> None:
    assert _same(default_ds, generate_office(OfficeConfig(seed=0)))


def test_different_seeds_give_different_datasets() -> None:
    a = generate_office(OfficeConfig.preset("easy", seed=1))
    b = generate_office(OfficeConfig.preset("easy", seed=2))
    assert not _same(a, b)


def test_default_dataset_is_generated_in_well_under_five_seconds() -> None:
    start = time.perf_counter()
    generate_office(OfficeConfig(seed=5))
    assert time.perf_counter() - start < 5.0


# --- shape of the dataset ----------------------------------------------------


def test_dataset_has_one_frame_pose_and_noise_free_frame_per_timestamp(
    default_ds: SyntheticDataset,
) -> None:
    seq = default_ds.sequence
    assert seq.name == "synthetic-office"
    assert len(seq) == len(default_ds.noise_free) == len(default_ds.trajectory) == 2500
    assert seq.label_names == coco_names()
    assert seq.frame_ids[0] == "1000000000.000000"
    assert seq.frame_ids[1] == "1000000000.033333"
    assert len(set(seq.frame_ids)) == len(seq)
    assert np.all(np.diff(seq.timestamps) > 0)
    np.testing.assert_array_equal(seq.timestamps, default_ds.trajectory.timestamps)
    for c, src in zip(seq.constellations, default_ds.sources, strict=True):
        assert len(c) == len(src)


def test_frame_count_and_rate_are_settings() -> None:
    ds = generate_office(OfficeConfig.preset("easy", n_frames=50, rate_hz=10.0))
    assert len(ds.sequence) == 50
    assert ds.sequence.frame_ids[1] == "1000000000.100000"


def test_no_frame_is_empty_because_a_zero_threshold_detector_always_reports_something(
    default_ds: SyntheticDataset,
) -> None:
    assert min(len(c) for c in default_ds.sequence.constellations) >= 1


def test_dataset_contains_misses_false_positives_and_confusions(
    default_ds: SyntheticDataset,
) -> None:
    n_noisy = sum(len(c) for c in default_ds.sequence.constellations)
    n_visible = sum(len(c) for c in default_ds.noise_free.constellations)
    assert n_noisy < n_visible
    sources = np.concatenate(default_ds.sources)
    assert (sources == -1).any()
    labels = np.concatenate([c.labels for c in default_ds.sequence.constellations])
    real = sources >= 0
    assert (labels[real] != default_ds.world.labels[sources[real]]).any()


def test_easy_preset_detects_almost_everything_visible_without_noise() -> None:
    ds = generate_office(OfficeConfig.preset("easy"))
    n_noisy = sum(len(c) for c in ds.sequence.constellations)
    n_visible = sum(len(c) for c in ds.noise_free.constellations)
    assert n_noisy > 0.9 * n_visible
    assert (np.concatenate(ds.sources) >= 0).all()


# --- statistics like the real TUM sequence --------------------------------------


def test_objects_per_frame_average_is_close_to_tum(default_ds: SyntheticDataset) -> None:
    # TUM has 7.97 objects per frame; 5-11 leaves room for other seeds and
    # for tuning, and still rules out a world that is far denser or sparser.
    stats = sequence_stats(default_ds.sequence)
    assert 5.0 <= stats["objects_per_frame_mean"] <= 11.0
    assert stats["frames_below_3_pct"] < 20.0
    assert stats["objects_per_frame_max"] <= 30


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_bottle_is_the_most_frequent_label_and_the_top_five_are_office_classes(
    seed: int,
) -> None:
    counts = _label_counts(generate_office(OfficeConfig(seed=seed)).sequence)
    top = [label for label, _ in counts.most_common(5)]
    assert top[0] == "bottle"
    assert set(top) <= OFFICE_LABELS


def test_repeated_desk_layouts_hold_the_same_kinds_of_objects(
    default_ds: SyntheticDataset,
) -> None:
    world = default_ds.world
    by_desk: dict[str, Counter[str]] = {}
    for k, group in enumerate(world.groups):
        by_desk.setdefault(group, Counter())[world.label_of(k)] += 1
    twins = [counts for group, counts in by_desk.items() if "(workstation)" in group]
    assert len(twins) >= 2  # the same layout repeats: perceptual aliasing
    assert all(counts == twins[0] for counts in twins)


# --- geometry ----------------------------------------------------------------------


def test_noise_free_detections_transformed_by_the_pose_are_the_world_objects(
    default_ds: SyntheticDataset,
) -> None:
    traj = default_ds.trajectory
    rot = quaternions_to_matrices(traj.quaternions)
    worst = 0.0
    for i, (c, objects) in enumerate(
        zip(default_ds.noise_free.constellations, default_ds.visible, strict=True)
    ):
        world_points = c.positions @ rot[i].T + traj.positions[i]
        expected = default_ds.world.positions[objects]
        np.testing.assert_array_equal(c.labels, default_ds.world.labels[objects])
        if len(c):
            worst = max(worst, float(np.abs(world_points - expected).max()))
    assert worst < 1e-9


def test_visible_objects_are_in_front_of_the_camera_and_inside_the_image(
    default_ds: SyntheticDataset,
) -> None:
    cam = default_ds.camera
    points = np.concatenate([c.positions for c in default_ds.noise_free.constellations])
    near, far = default_ds.config.depth_range_m
    assert (points[:, 2] >= near).all() and (points[:, 2] <= far).all()
    u, v = cam.project(points)
    assert (u >= 0).all() and (u < cam.width).all() and (v >= 0).all() and (v < cam.height).all()


def test_position_noise_grows_with_depth(default_ds: SyntheticDataset) -> None:
    depths, errors = [], []
    for noisy, sources, exact, visible in zip(
        default_ds.sequence.constellations,
        default_ds.sources,
        default_ds.noise_free.constellations,
        default_ds.visible,
        strict=True,
    ):
        where = {int(obj): k for k, obj in enumerate(visible)}
        for k, obj in enumerate(sources):
            if obj >= 0:
                truth = exact.positions[where[int(obj)]]
                depths.append(truth[2])
                errors.append(np.linalg.norm(noisy.positions[k] - truth))
    z, err = np.array(depths), np.array(errors)
    near = np.median(err[(z > 0.8) & (z < 1.5)])
    far = np.median(err[(z > 2.5) & (z < 4.0)])
    assert far > 1.5 * near
    slope = np.polyfit(z**2, err, 1)[0]
    assert slope > 0


def test_trajectory_revisits_places_more_than_100_frames_apart(
    default_ds: SyntheticDataset,
) -> None:
    traj = default_ds.trajectory
    forward = quaternions_to_matrices(traj.quaternions)[:, :, 2]
    dist = np.linalg.norm(traj.positions[:, None, :] - traj.positions[None, :, :], axis=2)
    angle = np.degrees(np.arccos(np.clip(forward @ forward.T, -1.0, 1.0)))
    index = np.arange(len(traj))
    far_in_time = np.abs(index[:, None] - index[None, :]) > 100
    revisits = far_in_time & (dist < 0.5) & (angle < 30.0)
    # Not one lucky pair: a good share of frames has a revisit.
    assert revisits.any(axis=1).mean() > 0.3


def test_trajectory_is_smooth_and_at_handheld_height(default_ds: SyntheticDataset) -> None:
    traj = default_ds.trajectory
    step = np.linalg.norm(np.diff(traj.positions, axis=0), axis=1)
    assert step.max() < 0.05  # under 1.5 m/s at 30 Hz
    lo, hi = default_ds.config.camera_height_m
    assert (traj.positions[:, 2] >= lo - 1e-9).all() and (traj.positions[:, 2] <= hi + 1e-9).all()
    np.testing.assert_allclose(np.linalg.norm(traj.quaternions, axis=1), 1.0, atol=1e-12)


def test_quaternions_and_matrices_convert_both_ways() -> None:
    rng = np.random.default_rng(7)
    q = rng.normal(size=(200, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 3] < 0] *= -1
    r = quaternions_to_matrices(q)
    np.testing.assert_allclose(r @ r.transpose(0, 2, 1), np.broadcast_to(np.eye(3), r.shape), atol=1e-12)
    np.testing.assert_allclose(matrices_to_quaternions(r), q, atol=1e-12)
    # 90 degrees about z maps x to y.
    quarter = quaternions_to_matrices(np.array([0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)]))[0]
    np.testing.assert_allclose(quarter @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)


def test_covisibility_is_symmetric_with_ones_on_the_diagonal() -> None:
    ds = generate_office(OfficeConfig.preset("easy", n_frames=200))
    cov = covisibility(ds)
    np.testing.assert_allclose(cov, cov.T)
    seen = np.array([len(v) > 0 for v in ds.visible])
    np.testing.assert_allclose(np.diag(cov)[seen], 1.0)
    assert ((cov >= 0) & (cov <= 1)).all()


# --- files ---------------------------------------------------------------------------


def test_written_dataset_parses_back_to_the_same_labels_and_positions(tmp_path: Path) -> None:
    ds = generate_office(OfficeConfig(n_frames=300))
    write_dataset(ds, tmp_path / "office")
    root = tmp_path / "office"
    files = sorted((root / "constellations").glob("*.txt"), key=lambda p: float(p.stem))
    assert [p.stem for p in files] == list(ds.sequence.frame_ids)
    names = ds.sequence.label_names
    multi_word = False
    for path, c in zip(files, ds.sequence.constellations, strict=True):
        labels, points = _parse_constellation(path.read_text(encoding="utf-8"))
        assert labels == [names[int(k)] for k in c.labels]
        np.testing.assert_allclose(points, c.positions, atol=1e-6, rtol=0)
        multi_word |= any(" " in label for label in labels)
    assert multi_word, "expected a label with a space (teddy bear...) in 300 frames"

    gt_lines = (root / "groundtruth.txt").read_text(encoding="utf-8").splitlines()
    assert gt_lines[0] == "# timestamp tx ty tz qx qy qz qw"
    rows = [line.split() for line in gt_lines[1:]]
    assert [r[0] for r in rows] == list(ds.sequence.frame_ids)
    values = np.array([[float(v) for v in r[1:]] for r in rows])
    np.testing.assert_allclose(values[:, :3], ds.trajectory.positions, atol=1e-6, rtol=0)
    np.testing.assert_allclose(values[:, 3:], ds.trajectory.quaternions, atol=1e-6, rtol=0)

    written_names = (root / "coco.names").read_text(encoding="utf-8").splitlines()
    assert tuple(written_names) == names
    assert "seed" in (root / "README.md").read_text(encoding="utf-8")
    assert len((root / "world.txt").read_text(encoding="utf-8").splitlines()) == len(ds.world)


def test_write_dataset_refuses_a_non_empty_folder_unless_told_to_overwrite(
    tmp_path: Path,
) -> None:
    small = generate_office(OfficeConfig.preset("easy", n_frames=20))
    write_dataset(small, tmp_path)
    with pytest.raises(FileExistsError):
        write_dataset(small, tmp_path)
    smaller = generate_office(OfficeConfig.preset("easy", n_frames=10))
    write_dataset(smaller, tmp_path, overwrite=True)
    assert len(list((tmp_path / "constellations").glob("*.txt"))) == 10


# --- configuration -------------------------------------------------------------------


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"n_frames": 1}, "n_frames"),
        ({"n_frames": 2.5}, "n_frames must be an integer"),
        ({"seed": -1}, "seed"),
        ({"seed": True}, "seed must be an integer"),
        ({"n_desks": 3}, "even"),
        ({"rate_hz": 0.0}, "rate_hz"),
        ({"detection_prob": 1.5}, "detection_prob"),
        ({"sigma_base_m": float("nan")}, "sigma_base_m"),
        ({"camera_height_m": (1.6, 1.2)}, "camera_height_m"),
        ({"camera_height_m": 1.4}, r"camera_height_m must be a \(low, high\) pair"),
        ({"depth_range_m": (2.0, 2.0)}, "near < far"),
        ({"orbit_radius_m": 1.2}, "too small"),
        ({"false_positives_per_frame": -0.1}, "false_positives_per_frame"),
    ],
)
def test_config_rejects_bad_settings_with_a_clear_message(
    settings: dict[str, object], message: str
) -> None:
    with pytest.raises(ConfigError, match=message):
        OfficeConfig(**settings)  # type: ignore[arg-type]  # wrong types on purpose


def test_presets_are_named_and_reject_unknown_names_and_settings() -> None:
    assert OfficeConfig.preset("default") == OfficeConfig()
    assert OfficeConfig.preset("easy", seed=4).seed == 4
    assert OfficeConfig.preset("hard").false_positives_per_frame > OfficeConfig().false_positives_per_frame
    with pytest.raises(ConfigError, match="unknown preset"):
        OfficeConfig.preset("paper")
    with pytest.raises(ConfigError, match="n_framez"):
        OfficeConfig.preset("easy", n_framez=3)


def test_a_config_error_is_a_value_error() -> None:
    with pytest.raises(ValueError):
        OfficeConfig(n_desks=5)


# --- statistics module -------------------------------------------------------------


def _tiny_sequence() -> ConstellationSequence:
    frames = [
        Constellation(np.array([39, 39, 73]), np.array([[0, 0, 1.0], [0, 0, 2.0], [0, 0, 3.0]])),
        Constellation(np.array([39]), np.array([[0, 0, 1.5]])),
        Constellation.empty(),
    ]
    return ConstellationSequence(
        frame_ids=("1", "2", "3"),
        timestamps=np.array([1.0, 2.0, 3.0]),
        constellations=tuple(frames),
        label_names=coco_names(),
        name="tiny",
    )


def test_sequence_stats_counts_objects_labels_and_depths() -> None:
    stats = sequence_stats(_tiny_sequence())
    assert stats["n_frames"] == 3 and stats["n_objects"] == 4
    assert stats["objects_per_frame_mean"] == pytest.approx(4 / 3)
    assert stats["objects_per_frame_histogram"] == {0: 1, 1: 1, 3: 1}
    assert stats["frames_below_3_pct"] == pytest.approx(200 / 3)
    assert stats["n_distinct_labels"] == 2
    assert stats["label_frequency_pct"] == [("bottle", 75.0), ("book", 25.0)]
    assert stats["depth_median_m"] == pytest.approx(1.75)


def test_compare_markdown_puts_the_two_sequences_side_by_side() -> None:
    stats = sequence_stats(_tiny_sequence())
    table = compare_markdown(stats, stats, ("left", "right"))
    assert "| | left | right |" in table
    assert "| 1 | bottle 75.0 | bottle 75.0 |" in table
    with pytest.raises(ValueError):
        compare_markdown(stats, stats, ("only one",))


def test_stats_script_prints_synthetic_statistics_without_the_tum_data(tmp_path: Path) -> None:
    text = main(StatsSettings(tum_zip=tmp_path / "missing.zip", n_frames=100))
    assert "synthetic (seed 0)" in text and "objects per frame, mean" in text


def test_tum_zip_reading_names_the_file_and_line_of_an_unknown_label(
    tmp_path: Path,
) -> None:
    import zipfile

    path = tmp_path / "bad.zip"
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("constellations/1.000000.txt", "bottle 0 0 1\nunicorn 0 0 2\n")
    with pytest.raises(UnknownLabelError) as info:
        read_constellations(path, coco_names())
    assert info.value.line == 2 and "1.000000.txt" in str(info.value)


@pytest.mark.skipif(not TUM_ZIP.exists(), reason="../shared/data (real TUM constellations) absent")
def test_synthetic_statistics_are_close_to_the_real_tum_sequence(
    default_ds: SyntheticDataset,
) -> None:
    tum = sequence_stats(read_constellations(TUM_ZIP, coco_names()))
    ours = sequence_stats(default_ds.sequence)
    assert tum["n_frames"] == 2585
    assert tum["objects_per_frame_mean"] == pytest.approx(7.97, abs=0.01)
    assert abs(ours["objects_per_frame_mean"] - tum["objects_per_frame_mean"]) < 1.5
    assert abs(ours["depth_median_m"] - tum["depth_median_m"]) < 0.3
    assert ours["label_frequency_pct"][0][0] == tum["label_frequency_pct"][0][0] == "bottle"
    top_tum = {name for name, _ in tum["label_frequency_pct"][:7]}
    top_ours = {name for name, _ in ours["label_frequency_pct"][:7]}
    assert len(top_tum & top_ours) >= 6
