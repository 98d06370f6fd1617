"""The procedural facade renderer: classes, determinism, shapes and the preview grid."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from swarmrec.errors import ConfigError
from swarmrec.fusion.facades import (
    FACADE_DESIGNS,
    IMAGE_SIZE,
    RenderSettings,
    View,
    render_dataset,
    render_view,
    write_preview,
)

HEAD_ON = View(8.0, 0.0)


def test_there_are_19_designs_each_two_differing_in_at_least_three_attributes() -> None:
    assert len(FACADE_DESIGNS) == 19
    for a, b in itertools.combinations(FACADE_DESIGNS, 2):
        assert sum(x != y for x, y in zip(a.attributes(), b.attributes(), strict=True)) >= 3


def test_no_single_attribute_separates_all_classes() -> None:
    for values in zip(*(d.attributes() for d in FACADE_DESIGNS), strict=True):
        assert len(set(values)) < 19


def test_a_render_is_a_small_rgb_uint8_image() -> None:
    for landmark in range(19):
        image = render_view(landmark, HEAD_ON, seed=landmark)
        assert image.shape == (IMAGE_SIZE, IMAGE_SIZE, 3) and image.dtype == np.uint8
    assert render_view(0, HEAD_ON, 0, RenderSettings(size=32)).shape == (32, 32, 3)


def test_the_same_seed_gives_the_same_image_and_another_seed_another() -> None:
    view = View(6.0, 0.4, -0.2)
    assert np.array_equal(render_view(3, view, 11), render_view(3, view, 11))
    assert np.array_equal(render_view(3, view, (4, 2)), render_view(3, view, np.random.default_rng((4, 2))))
    assert not np.array_equal(render_view(3, view, 11), render_view(3, view, 12))


def test_classes_look_different_under_the_same_seed_and_view() -> None:
    images = [render_view(k, HEAD_ON, 0).astype(np.int64) for k in range(19)]
    for a, b in itertools.combinations(images, 2):
        assert np.abs(a - b).mean() > 3.0


@pytest.mark.parametrize(
    "view",
    [
        View(0.8, 0.0),
        View(40.0, 0.0),
        View(2.0, math.radians(85)),
        View(2.0, math.radians(-85)),
        View(5.0, 0.5, 0.5),
    ],
)
def test_extreme_views_render(view: View) -> None:
    image = render_view(7, view, 0)
    assert image.shape == (IMAGE_SIZE, IMAGE_SIZE, 3)
    assert image.std() > 1.0  # not a blank frame


def test_views_are_validated() -> None:
    with pytest.raises(ConfigError):
        View(0.0, 0.0)
    with pytest.raises(ConfigError):
        View(5.0, math.radians(90))
    with pytest.raises(ConfigError):
        render_view(19, HEAD_ON, 0)
    with pytest.raises(ConfigError):
        RenderSettings(occlusion=1.5)


def test_render_dataset_is_class_balanced_and_seeded() -> None:
    images, labels, views = render_dataset(2, seed=1)
    assert images.shape == (38, IMAGE_SIZE, IMAGE_SIZE, 3) and images.dtype == np.uint8
    assert np.bincount(labels).tolist() == [2] * 19 and len(views) == 38
    again, _, _ = render_dataset(2, seed=1)
    other, _, _ = render_dataset(2, seed=2)
    assert np.array_equal(images, again) and not np.array_equal(images, other)


def test_preview_is_a_png_with_a_row_per_landmark(tmp_path: Path) -> None:
    path = write_preview(tmp_path / "sub" / "preview.png", seed=0, views_per_class=2)
    grid = cv2.imread(str(path))
    assert grid is not None
    assert grid.shape == (19 * (IMAGE_SIZE + 2), 3 * (IMAGE_SIZE + 2), 3)
