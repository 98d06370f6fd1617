"""Small helpers the services share: label ranges from settings, request checks."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from swarmrec.core.ranges import even_ranges
from swarmrec.errors import ConfigError, WireError
from swarmrec.services.config import ServiceSettings
from swarmrec.services.runner import RequestError
from swarmrec.wire import messages as pb

__all__ = ["MAX_FRAME_GAP", "MAX_FRAME_INDEX", "MAX_N_RET", "invalid", "label_bounds_of", "wire_error"]

IntArray = npt.NDArray[np.int64]

#: The most candidates a shard returns for one query, whatever the request asks.
MAX_N_RET = 256

#: Frame indices (and lock-step steps) at or above this are refused: a shard keeps
#: per-robot arrays indexed by frame, so one absurd index must not allocate gigabytes.
#: 2**20 frames is 9.7 hours at 30 frames a second.
MAX_FRAME_INDEX = 1 << 20

#: A robot's frames arrive in order; a shard refuses a frame (or lock-step step) more
#: than this far past the robot's highest stored frame, so one absurd index cannot
#: make every later query scan millions of empty slots.
MAX_FRAME_GAP = 4096


def label_bounds_of(settings: ServiceSettings) -> IntArray:
    """The swarm's label range boundaries: explicit, or even over the robots."""
    if settings.label_bounds:
        return np.asarray(settings.label_bounds, np.int64)
    if settings.preset == "balanced":
        raise ConfigError("the balanced preset needs explicit --label-bounds (computed from label loads)")
    return even_ranges(settings.n_labels, settings.n_robots)


def wire_error(e: WireError) -> RequestError:
    """The error reply for a message that decoded but does not validate."""
    # A label outside the list, or a label range ending past it, names labels the
    # receiver does not know.
    text = str(e)
    code = (
        pb.ErrorCode.ERROR_CODE_UNKNOWN_LABEL
        if "outside the label list" in text or "past the label list" in text
        else pb.ErrorCode.ERROR_CODE_INVALID_ARGUMENT
    )
    return RequestError(code, str(e))


def invalid(message: str) -> RequestError:
    return RequestError(pb.ErrorCode.ERROR_CODE_INVALID_ARGUMENT, message)
