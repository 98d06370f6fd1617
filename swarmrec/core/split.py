"""How a dataset is shared among robots: consecutive sub-trajectories.

Kept apart from the scoring code so that a detector replaying its share
imports no numba.
"""

from __future__ import annotations

import math

__all__ = ["split_frames"]


def split_frames(n_frames: int, n_robots: int) -> list[range]:
    """The frames of each robot: consecutive blocks of ``ceil(N / n)`` frames,
    the last one shorter (possibly empty when n does not divide well)."""
    per = math.ceil(n_frames / n_robots)
    return [range(min(r * per, n_frames), min((r + 1) * per, n_frames)) for r in range(n_robots)]
