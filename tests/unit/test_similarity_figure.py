"""The similarity figure shows every score of a big sparse matrix, and the robots' blocks."""

from __future__ import annotations

from pathlib import Path

import matplotlib.image as mpimg
import numpy as np

from swarmrec.evaluation.plots import block_max, plot_closures_map, plot_similarity


def test_block_maxima_keep_a_single_score_of_a_big_matrix() -> None:
    scores = np.zeros((2500, 2500))
    scores[1234, 77] = 0.3

    shown, block = block_max(scores, bins=500)

    assert block == 5 and shown.shape == (500, 500)
    assert shown[1234 // 5, 77 // 5] == 0.3
    assert np.count_nonzero(shown) == 1


def test_a_matrix_that_is_not_a_multiple_of_the_block_is_padded_not_cut() -> None:
    scores = np.zeros((1001, 1001))
    scores[1000, 1000] = 0.7

    shown, block = block_max(scores, bins=500)

    assert block == 3 and shown.shape == (334, 334) and shown[333, 333] == 0.7


def test_small_matrices_are_shown_as_they_are() -> None:
    scores = np.arange(16.0).reshape(4, 4)

    shown, block = block_max(scores, bins=500)

    assert block == 1 and shown is scores


def test_the_figure_is_drawn_with_robot_blocks_and_an_empty_matrix_too(tmp_path: Path) -> None:
    scores = np.zeros((2000, 2000))
    scores[[100, 900, 1700], [1500, 300, 1100]] = [0.2, 0.3, 0.4]

    plot_similarity(scores, "sparse", tmp_path / "a.png", best_threshold=0.25, robot_starts=[0, 1000])
    plot_similarity(np.zeros((10, 10)), "empty", tmp_path / "b.png")

    for name in ("a.png", "b.png"):
        assert mpimg.imread(tmp_path / name).shape[2] in (3, 4)


def test_closures_on_the_trajectory_are_counted_true_and_false(tmp_path: Path) -> None:
    # Two robots of two frames each, seen from above; one true and one false closure.
    positions = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 0.1, 1.0], [5.0, 5.0, 1.0]])
    truth = np.zeros((4, 4), dtype=bool)
    truth[0, 2] = truth[2, 0] = True
    path = tmp_path / "map.png"

    drawn = plot_closures_map(positions, [0, 2], [(0, 2), (1, 3)], truth, "two robots", path)

    assert drawn == (1, 1)
    pixels = mpimg.imread(path)
    # The true closure in green and the false one in red are both on the figure.
    rgb = pixels[..., :3]
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    green = (g > 0.45) & (r < 0.45) & (b < 0.45) & (g - r > 0.2)
    red = (r > 0.7) & (g < 0.45) & (b < 0.45) & (r - g > 0.35)  # orange (a robot's) has g 0.5
    assert green.any() and red.any()
    # Without a truth nothing is called true or false.
    assert plot_closures_map(positions, [0, 2], [(0, 2)], None, "no truth", tmp_path / "grey.png") == (0, 0)
