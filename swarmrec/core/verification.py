"""Geometric verification of a query frame against a robot's own frames
(paper Sec. III-D, Eq. 2-7), as the verifier service runs it.

Frames are named swarm-wide by ``(robot, frame)``. The association breaks
ties by argument order, so each pair is scored with the frame that comes
first in ``(robot, frame)`` order as the first argument: that is the order
the offline evaluation uses (its global frame index is robot-major), so a
lock-step swarm's scores equal the offline ones bit for bit.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from swarmrec.core.association import FrameTable, build_table, score_tables
from swarmrec.core.presets import Preset
from swarmrec.core.types import Constellation

__all__ = ["FrameMatch", "verify", "verify_tables"]

IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True)
class FrameMatch:
    """A stored frame compared with the query."""

    frame: int
    score: float
    semantic: float
    #: (m, 2): object index in the query, object index in the stored frame.
    pairs: IntArray
    #: Objects in common (sum of per-label minima) and in either frame: the
    #: integers the scores are ratios of, which is what travels on the wire.
    n_common: int
    n_union: int


def verify(
    query: Constellation,
    query_key: tuple[int, int],
    own_robot: int,
    frames: Iterable[tuple[int, Constellation]],
    n_labels: int,
    preset: Preset,
) -> list[FrameMatch]:
    """Score ``query`` against each ``(frame index, constellation)`` of ``own_robot``;
    every result, best first (ties by frame index)."""
    return verify_tables(
        build_table([query], n_labels),
        query_key,
        own_robot,
        ((f, build_table([c], n_labels)) for f, c in frames),
        preset,
    )


def verify_tables(
    query: FrameTable,
    query_key: tuple[int, int],
    own_robot: int,
    frames: Iterable[tuple[int, FrameTable]],
    preset: Preset,
) -> list[FrameMatch]:
    """:func:`verify` with the query and each stored frame already packed as a one-frame
    :class:`~swarmrec.core.association.FrameTable` (the verifier packs a frame once,
    when it stores it, not once per query it is compared with)."""
    out = []
    q_counts = query.desc[0]
    n_query = query.n_objects(0)
    for frame, stored in frames:
        first_is_query = query_key < (own_robot, frame)
        a, b = (query, stored) if first_is_query else (stored, query)
        s = score_tables(
            a, b, d=preset.d, min_common=preset.min_common, same_label_only=preset.same_label_only
        )
        pairs = s.matches if first_is_query else s.matches[:, ::-1]
        common = int(np.minimum(q_counts, stored.desc[0]).sum())
        union = n_query + stored.n_objects(0) - common
        out.append(FrameMatch(frame, s.score, s.semantic, np.ascontiguousarray(pairs), common, union))
    out.sort(key=lambda m: (-m.score, m.frame))
    return out
