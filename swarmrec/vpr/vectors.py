"""Checking descriptors at the edge: everything past this point may assume finite float32 rows."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from swarmrec.vpr.errors import DescriptorError

__all__ = ["as_descriptor", "as_descriptors"]

Float32Array = npt.NDArray[np.float32]


def as_descriptors(values: object, dimension: int) -> Float32Array:
    """``values`` as a C-contiguous float32 ``(N, dimension)`` array, or :class:`DescriptorError`
    (not a real-valued array, the wrong length, NaN or inf). One row ``(dimension,)`` is taken as N = 1."""
    if not isinstance(values, np.ndarray) or not (
        np.issubdtype(values.dtype, np.floating) or np.issubdtype(values.dtype, np.integer)
    ):
        kind = values.dtype if isinstance(values, np.ndarray) else type(values).__name__
        raise DescriptorError(f"expected a real-valued numpy array of descriptors, got {kind}")
    batch = values[None] if values.ndim == 1 else values
    if batch.ndim != 2 or batch.shape[1] != dimension:
        raise DescriptorError(
            f"expected descriptors of length {dimension}, got an array of shape {values.shape}"
        )
    # A float64 beyond float32's range turns into inf in the cast, and is as unusable as a NaN.
    with np.errstate(over="ignore", invalid="ignore"):
        out = np.ascontiguousarray(batch, np.float32)
    if not np.isfinite(out).all():
        raise DescriptorError("descriptors hold NaN or inf")
    return out


def as_descriptor(values: object, dimension: int) -> Float32Array:
    """One descriptor as float32 ``(dimension,)``, checked as :func:`as_descriptors`."""
    batch = as_descriptors(values, dimension)
    if len(batch) != 1:
        raise DescriptorError(f"expected one descriptor, got {len(batch)}")
    one: Float32Array = batch[0]
    return one
