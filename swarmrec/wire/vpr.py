"""Full-image descriptors on the wire, and the checks a receiver makes before using one.

A descriptor travels as bytes with an encoding (``swarmrec.v1.DescriptorEncoding``):
``float32`` (``4 d`` bytes, the paper's query) or ``int8`` (a float32 scale and ``d``
signed bytes, :class:`swarmrec.vpr.quantize.Int8Quantizer`). :func:`descriptor_from_wire`
refuses, with a :class:`~swarmrec.errors.WireError` naming the problem (so the runner
answers ``INVALID_ARGUMENT``), every descriptor a service must not store or search with:
an unknown encoding, a length that is not the swarm's ``d`` in that encoding, NaN or inf
(a float32 value or an int8 scale), a negative scale, and a vector whose norm is not 1
within :data:`NORM_TOLERANCE` (the model's rows are unit vectors; an int8 code of one is
within 0.045 of unit length, so a zero vector or a scaled one is not a descriptor).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import numpy.typing as npt

from swarmrec.errors import ConfigError, WireError
from swarmrec.vpr.errors import DescriptorError
from swarmrec.vpr.quantize import Int8Quantizer
from swarmrec.vpr.vectors import as_descriptor
from swarmrec.wire import messages as pb

__all__ = [
    "ENCODINGS",
    "NORM_TOLERANCE",
    "WireCode",
    "descriptor_from_wire",
    "descriptor_to_wire",
    "encoding_name",
    "encoding_of",
]

Float32Array = npt.NDArray[np.float32]
WireCode = Literal["float32", "int8"]

#: The settings' names of the encodings, and their wire values.
ENCODINGS: dict[str, int] = {
    "float32": pb.DescriptorEncoding.DESCRIPTOR_ENCODING_FLOAT32,
    "int8": pb.DescriptorEncoding.DESCRIPTOR_ENCODING_INT8,
}
#: How far a received descriptor's L2 norm may be from 1. An int8 code keeps each component
#: within half a step (max |x| / 254), at most sqrt(d) / 254 = 0.045 off for d = 128.
NORM_TOLERANCE = 0.05


def encoding_of(name: str) -> int:
    """The wire value of an encoding name (``float32``, ``int8``)."""
    try:
        return ENCODINGS[name]
    except KeyError:
        known = ", ".join(ENCODINGS)
        raise ConfigError(f"descriptor encoding must be one of {known}, got {name!r}") from None


def encoding_name(value: int) -> str:
    """The name of a wire value; ``unknown(<n>)`` for one this version does not know."""
    for name, v in ENCODINGS.items():
        if v == value:
            return name
    return f"unknown({value})"


def descriptor_to_wire(descriptor: npt.NDArray[np.floating], code: str) -> tuple[bytes, int]:
    """``descriptor`` (one row) as bytes in ``code`` and the encoding's wire value."""
    x = as_descriptor(descriptor, descriptor.shape[-1] if descriptor.ndim else -1)
    encoding = encoding_of(code)
    if code == "float32":
        return x.astype("<f4").tobytes(), encoding
    return Int8Quantizer(len(x)).encode(x)[0].tobytes(), encoding


def descriptor_from_wire(data: bytes, encoding: int, dimension: int) -> Float32Array:
    """The float32 descriptor ``(dimension,)`` that ``data`` encodes; WireError when it is not
    one (see the module docstring)."""
    if encoding == ENCODINGS["float32"]:
        expected = 4 * dimension
    elif encoding == ENCODINGS["int8"]:
        expected = 4 + dimension
    else:
        known = ", ".join(f"{n} ({v})" for n, v in ENCODINGS.items())
        raise WireError(f"descriptor encoding {encoding} is not one of {known}")
    if len(data) != expected:
        name = encoding_name(encoding)
        raise WireError(f"{name} descriptors of length {dimension} are {expected} bytes, got {len(data)}")
    raw = np.frombuffer(data, np.uint8)
    try:
        if encoding == ENCODINGS["float32"]:
            x = as_descriptor(raw.view("<f4").astype(np.float32), dimension)
        else:
            x = as_descriptor(Int8Quantizer(dimension).decode(raw.copy()), dimension)
    except DescriptorError as e:
        raise WireError(f"descriptor: {e}") from None
    norm = float(np.linalg.norm(x.astype(np.float64)))
    if abs(norm - 1.0) > NORM_TOLERANCE:
        raise WireError(
            f"descriptor has L2 norm {norm:.4g}; descriptors are unit vectors (within {NORM_TOLERANCE})"
        )
    return x
