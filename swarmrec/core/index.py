"""The index of one label range: partial descriptors from every robot, and
the n_ret best candidates for a query (paper Sec. III-C).

A holder scores the query's slice against every stored slice with the
partial Jaccard index and keeps the ``n_ret`` best scores > 0. In lock-step
(``before=t``) candidates are picked as the published evaluation picks them,
robot-major over ``n_robots x t`` slots (unstored slots score 0), so that
ties are broken by the same sort on the same array and a swarm replaying in
lock-step returns exactly the offline evaluation's candidates. Without a
step (a free-running swarm, a read-only lookup) there is no evaluation to
equal, and equal scores at the cut are kept in (robot, frame) order.
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
    """Partial descriptors of labels ``[lo, hi)`` from robots ``0 .. n_robots - 1``.

    Stored compactly, one row per stored (robot, frame) with the robot and the
    frame as columns, so memory and the work of a query grow with what is
    stored, never with the frame indices a request claims. In lock-step the
    candidates are still those of the published layout (robot-major
    ``n_robots x t`` slots, unstored slots scoring 0): the kept set and its
    order depend on the slots only through their (robot, frame) order, except
    when a tie straddles the ``n_ret`` cut, where the published unstable
    argsort decides; only then is the dense ``n_robots x t`` score vector
    built, for that one call, as the offline evaluation builds it. Without a
    step the tie is cut in (robot, frame) order, so that no claimed frame
    index, however high, makes a query cost more than the rows stored.
    """

    def __init__(self, lo: int, hi: int, n_robots: int) -> None:
        if not 0 <= lo < hi:
            raise ValueError(f"empty label range [{lo}, {hi})")
        if n_robots < 1:
            raise ValueError(f"need at least one robot, got {n_robots}")
        self.lo, self.hi, self.n_robots = lo, hi, n_robots
        # Rows [0, size) are stored, in arrival order; the arrays grow by doubling so a
        # query reads slices of them instead of assembling rows every time, and row sums
        # are kept beside them for the same reason.
        self._counts = np.zeros((0, hi - lo))
        self._sums = np.zeros(0)
        self._robot = np.zeros(0, np.int64)
        self._frame = np.zeros(0, np.int64)
        self._row: dict[int, int] = {}  # robot << 32 | frame -> row
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

    @property
    def nbytes(self) -> int:
        """Bytes the stored rows take (arrays allocated, the row map estimated)."""
        arrays = self._counts.nbytes + self._sums.nbytes + self._robot.nbytes + self._frame.nbytes
        return arrays + self._frames.nbytes + 100 * len(self._row)  # ~100 B a dict entry and its ints

    def get(self, robot: int, frame: int) -> FloatArray | None:
        """The stored slice of ``robot``'s frame ``frame`` (a copy), or None."""
        row = self._row.get(_key(robot, frame))
        return None if row is None else self._counts[row].copy()

    def rows(self, start: int, stop: int) -> list[tuple[int, int, FloatArray]]:
        """Stored rows ``[start, stop)`` in arrival order, as (robot, frame, slice copy): what a
        new replica copies, page by page (rows only ever get appended, so a copy that pages
        to :attr:`size` has everything stored before it asked)."""
        stop = min(stop, self.size)
        return [
            (int(self._robot[r]), int(self._frame[r]), self._counts[r].copy())
            for r in range(max(start, 0), stop)
        ]

    def _grow(self, rows: int) -> None:
        cap = self._counts.shape[0]
        if rows <= cap:
            return
        new_cap = max(rows, 2 * cap, 64)
        counts = np.zeros((new_cap, self.width))
        counts[:cap] = self._counts
        sums, robot, frame = np.zeros(new_cap), np.zeros(new_cap, np.int64), np.zeros(new_cap, np.int64)
        sums[:cap], robot[:cap], frame[:cap] = self._sums, self._robot, self._frame
        self._counts, self._sums, self._robot, self._frame = counts, sums, robot, frame

    def add(self, robot: int, frame: int, counts: npt.ArrayLike) -> bool:
        """Store (or replace) a frame's slice; True when it was new."""
        row_counts = np.asarray(counts, dtype=np.float64).reshape(-1)
        if row_counts.shape[0] != self.width:
            raise ValueError(f"slice of {row_counts.shape[0]} bins for a range of {self.width}")
        if not (0 <= robot < self.n_robots and 0 <= frame < 2**32):
            raise ValueError(f"(robot {robot}, frame {frame}) is outside {self.n_robots} robots' frames")
        key = _key(robot, frame)
        row = self._row.get(key)
        new = row is None
        if row is None:
            row = self.size
            self._grow(row + 1)
            self._row[key] = row
            self._robot[row], self._frame[row] = robot, frame
            self.size += 1
        self._counts[row] = row_counts
        self._sums[row] = row_counts.sum()
        self._frames[robot] = max(self._frames[robot], frame + 1)
        return new

    def candidates(
        self,
        counts: npt.ArrayLike,
        n_ret: int,
        *,
        before: int | None = None,
        exclude: tuple[int, int] | None = None,
    ) -> list[IndexCandidate]:
        """The ``n_ret`` best stored frames for the query slice ``counts``, best first.

        ``before`` limits the search to frames with a smaller index on every
        robot (lock-step replay at step ``before``, ties as the published
        evaluation breaks them); None searches everything (equal scores at the
        ``n_ret`` cut kept in (robot, frame) order). ``exclude`` (robot, frame)
        is never named: a frame is not its own candidate, even where its slice
        is stored before its query comes (a replica's store can be).
        """
        query = np.asarray(counts, dtype=np.float64).reshape(-1)
        t = before if before is not None else self.frames
        if t <= 0:
            return []
        n = self.size
        keep = self._frame[:n] < t if before is not None else np.ones(n, dtype=bool)
        if exclude is not None:
            keep &= (self._robot[:n] != exclude[0]) | (self._frame[:n] != exclude[1])
        rows = np.flatnonzero(keep)
        # Only the query's non-zero bins can have a non-zero minimum; the sums are
        # of small integers, exact in float64 in any order, so skipping the zero
        # bins changes no bit of the result (and saves most of the work).
        bins = np.flatnonzero(query)
        common = np.minimum(self._counts[np.ix_(rows, bins)], query[bins]).sum(axis=1)
        # Then the offline evaluation's operations in its order, and one division
        # with the published epsilon.
        total = self._sums[rows] + query.sum() - common
        values = common / (total + PARTIAL_EPSILON)
        # Each row's slot in the published robot-major n_robots x t layout.
        slots = self._robot[rows] * t + self._frame[rows]
        positive = np.flatnonzero(values > 0.0)
        kept = self._select(values[positive], slots[positive], n_ret, t if before is not None else None)
        chosen_slots, chosen_values = slots[positive][kept], values[positive][kept]
        # Best first, equal scores in slot order (a stable sort of the slot-sorted set).
        by_slot = np.argsort(chosen_slots, kind="stable")
        chosen_slots, chosen_values = chosen_slots[by_slot], chosen_values[by_slot]
        order = np.argsort(-chosen_values, kind="stable")
        return [
            IndexCandidate(int(s // t), int(s % t), float(v))
            for s, v in zip(chosen_slots[order].tolist(), chosen_values[order].tolist(), strict=True)
        ]

    def _select(self, values: FloatArray, slots: IntArray, n_ret: int, t: int | None) -> IntArray:
        """Which of the positive ``values`` (at ``slots``) are kept: with a step ``t``,
        :func:`~swarmrec.core.selection.select_candidates` on the dense slot vector;
        without, equal scores at the cut in slot order."""
        m = values.shape[0]
        if m <= n_ret:
            return np.arange(m)
        kth = np.partition(values, m - n_ret)[m - n_ret]
        keep = np.flatnonzero(values >= kth)
        if keep.shape[0] == n_ret:
            return keep
        if t is None:
            above = np.flatnonzero(values > kth)
            tied = np.flatnonzero(values == kth)
            tied = tied[np.argsort(slots[tied], kind="stable")][: n_ret - above.shape[0]]
            return np.concatenate([above, tied])
        # A tie straddles the cut: which of the equal scores are kept is decided by the
        # published unstable argsort on the dense vector, zeros included, so it is built.
        dense = np.zeros(self.n_robots * t)
        dense[slots] = values
        picked = select_candidates(dense, n_ret)
        return np.flatnonzero(np.isin(slots, picked))


def _key(robot: int, frame: int) -> int:
    return (int(robot) << 32) | int(frame)
