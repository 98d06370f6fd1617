"""Errors of the SLAM back end (drawn in :mod:`swarmrec.errors`'s tree).

Two families: :class:`G2oError` is bad *input* (a g2o file or folder that
cannot be used, always naming the file and, when it is one line's fault, the
line), so it derives from :class:`~swarmrec.errors.DatasetError`;
:class:`SlamError` is a problem the solver finds in a well-formed graph or in
what a caller hands it (a disconnected team, a message that does not fit the
receiving agent, too few points to align).
"""

from __future__ import annotations

from dataclasses import dataclass

from swarmrec.errors import DatasetError, SwarmrecError

__all__ = [
    "AlignmentError",
    "G2oError",
    "G2oInformationError",
    "G2oKeyError",
    "G2oQuaternionError",
    "GraphError",
    "MessageError",
    "SlamError",
    "TurnRejected",
]


@dataclass
class G2oError(DatasetError):
    """A g2o file (or a folder of them) cannot be used: malformed line, unsupported tag, bad values."""


@dataclass
class G2oQuaternionError(G2oError):
    """A quaternion too far from unit norm to be a rounding artefact (``norm`` is what was read)."""

    norm: float = float("nan")


@dataclass
class G2oInformationError(G2oError):
    """An information matrix that is not finite, symmetric and positive definite."""


@dataclass
class G2oKeyError(G2oError):
    """A vertex key declared twice, or an edge to a vertex no file declares (``key`` is the culprit)."""

    key: int = -1


class SlamError(SwarmrecError):
    """A well-formed input the SLAM back end cannot solve or accept."""


class GraphError(SlamError, ValueError):
    """A pose graph that cannot be solved as given (disconnected team, no anchor, bad partition)."""


class MessageError(SlamError, ValueError):
    """A distributed Gauss-Seidel message that does not fit the agent receiving it."""


class TurnRejected(MessageError):
    """A live team member's message refused by :class:`~swarmrec.slam.live.TeamRobot`; nothing changed.

    ``reason`` is one of :data:`~swarmrec.slam.live.REJECT_REASONS` (a metric label).
    """

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


class AlignmentError(SlamError, ValueError):
    """Points that cannot be rigidly aligned (too few, degenerate, or no consensus)."""
