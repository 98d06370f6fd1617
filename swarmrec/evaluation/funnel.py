"""Why a frame was never a candidate of a query: the shards' answers recomputed offline.

A live query report lists only the frames some shard returned; a frame no shard
returned stopped at the funnel's first stage (``BELOW_SHARD_CUT``), and the
shards do not keep their scores. From a run's data they can be computed again:
:func:`shard_cuts` builds each label range's index (:class:`~swarmrec.core.index.RangeIndex`,
the shards' own code) from the frames stored before the query and asks it what
the shard asked, so the pair's partial score and the shard's cut (its
``n_ret``-th best score) are the live ones, bit for bit, in a lock-step run
(where step ``t`` of every robot ran before step ``t + 1``). In a paced run
which frames a shard held when the query came is not recorded: the pair's own
partial scores are still exact, the cut is unknown.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from swarmrec.core.index import IndexCandidate, RangeIndex
from swarmrec.core.placement import groups_from_bounds

__all__ = ["ShardCut", "shard_cuts"]

Counts = npt.NDArray[np.int64]


@dataclass(frozen=True)
class ShardCut:
    """One label group asked by a query, and where one stored frame stood in the answer
    of the shard that answered for it (every replica of a group answers alike)."""

    #: The label group and its range [lo, hi).
    group: int
    lo: int
    hi: int
    #: The frame (robot, robot-local index) this is about.
    robot: int
    frame: int
    #: The frame's partial score on this range (0: no common label here).
    score: float
    #: The shard's answer, best first (None: not known, a paced run).
    returned: tuple[IndexCandidate, ...] | None
    #: The frame's rank among every stored frame's positive score (1: best; None: not
    #: ranked, or not known).
    rank: int | None
    #: n_ret of the run.
    n_ret: int

    @property
    def returned_it(self) -> bool | None:
        """Whether the shard returned the frame (None: not known)."""
        if self.returned is None:
            return None
        return any(c.robot == self.robot and c.frame == self.frame for c in self.returned)

    @property
    def cut(self) -> float | None:
        """The lowest score the shard returned when it returned a full n_ret (a frame had
        to beat or tie it); None when it returned fewer (every positive score was
        returned) or the answer is not known."""
        if self.returned is None or len(self.returned) < self.n_ret:
            return None
        return self.returned[-1].score


def shard_cuts(
    descriptors: Counts,
    blocks: list[range],
    bounds: npt.ArrayLike,
    stored: npt.NDArray[np.bool_],
    n_ret: int,
    query: tuple[int, int],
    frame: tuple[int, int],
    *,
    lockstep: bool,
) -> list[ShardCut]:
    """Each shard ``query`` asked where ``frame`` shares a label with it.

    ``descriptors``: the (N, n_labels) label histograms of the dataset in global
    order (robot r's frame f is ``blocks[r][f]``); ``stored``: which frames the
    shards stored (those that queried: at least the preset's min_objects objects);
    ``query`` and ``frame``: (robot, robot-local frame index).
    """
    edges = np.asarray(bounds, np.int64)
    n_robots = len(blocks)
    q = descriptors[blocks[query[0]][query[1]]]
    x = descriptors[blocks[frame[0]][frame[1]]]
    step = query[1]
    out = []
    returned: tuple[IndexCandidate, ...] | None
    # Group k is the k-th non-empty range, as the live index numbers them.
    for k, (lo, hi) in enumerate(groups_from_bounds(edges.tolist())):
        if not q[lo:hi].any() or not np.minimum(q[lo:hi], x[lo:hi]).any():
            continue  # not asked, or the frame has no label of this range in common
        if lockstep:
            index = RangeIndex(lo, hi, n_robots)
            for r, block in enumerate(blocks):
                for f in range(min(step, len(block))):
                    g = block[f]
                    if stored[g] and descriptors[g, lo:hi].any():
                        index.add(r, f, descriptors[g, lo:hi])
            ranked = index.candidates(q[lo:hi], max(index.size, 1), before=step)
            returned = tuple(index.candidates(q[lo:hi], n_ret, before=step))
            place = [i for i, c in enumerate(ranked) if (c.robot, c.frame) == frame]
            rank = place[0] + 1 if place else None
            score = ranked[place[0]].score if place else _alone(lo, hi, n_robots, frame, x, q)
        else:
            returned, rank = None, None
            score = _alone(lo, hi, n_robots, frame, x, q)
        out.append(ShardCut(k, lo, hi, frame[0], frame[1], score, returned, rank, n_ret))
    return out


def _alone(lo: int, hi: int, n_robots: int, frame: tuple[int, int], x: Counts, q: Counts) -> float:
    """The frame's partial score against the query, computed as a shard holding only it would."""
    index = RangeIndex(lo, hi, n_robots)
    index.add(frame[0], frame[1], x[lo:hi])
    found = index.candidates(q[lo:hi], 1)
    return found[0].score if found else 0.0
