"""The band of an N x N frame matrix within the exclusion window: the pairs the
evaluation never counts (a frame and its own recent frames)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = ["fill_band"]


def fill_band(m: npt.NDArray[np.float64], width: int, value: float) -> None:
    """Set every ``m[i, j]`` with ``|i - j| <= width`` to ``value``, in place.

    One diagonal at a time: O(N * width), where a mask of every (i, j) took 0.8 s and
    0.4 GB at 5,000 frames."""
    n = m.shape[0]
    if m.shape != (n, n):
        raise ValueError(f"fill_band: a square matrix, not {m.shape}")
    w = min(width, n - 1)
    for k in range(-w, w + 1):
        rows = np.arange(max(0, -k), min(n, n - k))
        m[rows, rows + k] = value
