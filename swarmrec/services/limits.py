"""Bounds on the work and memory one request can cause, whatever it claims."""

from __future__ import annotations

__all__ = ["MAX_FRAME_GAP", "MAX_FRAME_INDEX", "MAX_N_RET"]

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
