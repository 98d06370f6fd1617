"""The index of one label range: partial descriptors from every robot, and
the n_ret best candidates for a query (paper Sec. III-C).

A holder scores the query's slice against every stored slice with the
partial Jaccard index and keeps the ``n_ret`` best scores > 0. Candidates
are laid out as the published evaluation lays them out, robot-major over
``n_robots x n_frames`` slots (unstored slots score 0), so that ties are
broken by the same sort on the same array and a swarm replaying in lock-step
returns exactly the offline evaluation's candidates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from swarmrec.core.selection import select_candidates

__all__ = ["IndexCandidate", "RangeIndex"]

IntArray = npt.NDArray[np.int64]
FloatArray = npt.NDArray[np.float64]

# The published scripts add this to every partial-score denominator; it
# changes the order of equal fractions (2/4 ranks above 1/2), so it is kept.
PARTIAL_EPSILON = 1e-12


@dataclass(frozen=True)
class IndexCandidate:
    robot: int
    frame: int
    score: float


class RangeIndex:
    """Partial descriptors of labels ``[lo, hi)`` from robots ``0 .. n_robots - 1``."""

    def __init__(self, lo: int, hi: int, n_robots: int) -> None:
        if not 0 <= lo < hi:
            raise ValueError(f"empty label range [{lo}, {hi})")
        self.lo, self.hi, self.n_robots = lo, hi, n_robots
        # One (robot, frame, bin) array, grown by doubling along frames, so a query
        # reads a view of it instead of assembling the robots' rows every time;
        # row sums are kept beside it for the same reason.
        self._counts = np.zeros((n_robots, 0, hi - lo))
        self._sums = np.zeros((n_robots, 0))
        self._stored = np.zeros((n_robots, 0), np.bool_)
        self._frames = np.zeros(n_robots, np.int64)  # one past each robot's highest stored frame
        self.size = 0

    @property
    def width(self) -> int:
        return self.hi - self.lo

    def frames_of(self, robot: int) -> int:
        """One past the highest frame index stored for ``robot``."""
        return int(self._frames[robot])

    @property
    def frames(self) -> int:
        """One past the highest frame index stored for any robot."""
        return int(self._frames.max(initial=0))

    def _grow(self, frames: int) -> None:
        cap = self._counts.shape[1]
        if frames <= cap:
            return
        new_cap = max(frames, 2 * cap, 64)
        counts = np.zeros((self.n_robots, new_cap, self.width))
        counts[:, :cap] = self._counts
        sums = np.zeros((self.n_robots, new_cap))
        sums[:, :cap] = self._sums
        stored = np.zeros((self.n_robots, new_cap), np.bool_)
        stored[:, :cap] = self._stored
        self._counts, self._sums, self._stored = counts, sums, stored

    def add(self, robot: int, frame: int, counts: npt.ArrayLike) -> bool:
        """Store (or replace) a frame's slice; True when it was new."""
        row = np.asarray(counts, dtype=np.float64).reshape(-1)
        if row.shape[0] != self.width:
            raise ValueError(f"slice of {row.shape[0]} bins for a range of {self.width}")
        self._grow(frame + 1)
        new = not self._stored[robot, frame]
        self._counts[robot, frame] = row
        self._sums[robot, frame] = row.sum()
        self._stored[robot, frame] = True
        self._frames[robot] = max(self._frames[robot], frame + 1)
        self.size += int(new)
        return new

    def candidates(
        self, counts: npt.ArrayLike, n_ret: int, *, before: int | None = None
    ) -> list[IndexCandidate]:
        """The ``n_ret`` best stored frames for the query slice ``counts``, best first.

        ``before`` limits the search to frames with a smaller index on every
        robot (lock-step replay at step ``before``); None searches everything.
        """
        query = np.asarray(counts, dtype=np.float64).reshape(-1)
        t = before if before is not None else self.frames
        if t <= 0:
            return []
        self._grow(t)  # a lock-step query may look past the frames stored so far (zeros)
        # Only the query's non-zero bins can have a non-zero minimum; the sums are
        # of small integers, exact in float64 in any order, so skipping the zero
        # bins changes no bit of the result (and saves most of the work).
        bins = np.flatnonzero(query)
        common = np.minimum(self._counts[:, :t, bins], query[bins]).sum(axis=2)
        # Then the offline evaluation's operations in its order, and one division
        # with the published epsilon.
        total = self._sums[:, :t] + query.sum() - common
        values = (common / (total + PARTIAL_EPSILON)).reshape(-1)
        cols = select_candidates(values, n_ret)
        order = cols[np.argsort(-values[cols], kind="stable")]
        return [IndexCandidate(int(c // t), int(c % t), float(values[c])) for c in order.tolist()]
