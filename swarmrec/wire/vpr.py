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

import math
from typing import Literal

import numpy as np
import numpy.typing as npt

from swarmrec.errors import ConfigError, WireError
from swarmrec.vpr.clusters import Assignment, Router
from swarmrec.vpr.errors import DescriptorError
from swarmrec.vpr.live import MAX_CLUSTERS, LiveTable, OwnerLoad
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
    "load_from_proto",
    "load_to_proto",
    "table_from_proto",
    "table_to_proto",
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


# --- the live re-balancing's tables and loads (swarmrec.vpr.live) -----------------------


def table_to_proto(table: LiveTable) -> pb.ClusterTable:
    return pb.ClusterTable(
        version=table.version,
        dimension=table.router.dimension,
        centres=np.ascontiguousarray(table.centres, "<f4").tobytes(),
        owners=list(table.assignment.owners),
        copy_margin=table.copy_margin,
        copy_neighbours=table.copy_neighbours,
    )


def table_from_proto(msg: pb.ClusterTable, dimension: int, n_robots: int, method: str = "live") -> LiveTable:
    """The table a message carries, checked (WireError naming the problem): the swarm's
    dimension and robots, 1 .. :data:`MAX_CLUSTERS` clusters, finite unit-norm-ish centres,
    a margin that is a number, 1 .. n_robots copy holders."""
    k = len(msg.owners)
    if msg.dimension != dimension:
        raise WireError(f"a table of dimension {msg.dimension}, the swarm's is {dimension}")
    if not 1 <= k <= MAX_CLUSTERS:
        raise WireError(f"a table must have 1 to {MAX_CLUSTERS} clusters, got {k}")
    if len(msg.centres) != 4 * k * dimension:
        raise WireError(
            f"{k} centres of length {dimension} are {4 * k * dimension} bytes, got {len(msg.centres)}"
        )
    bad = [o for o in msg.owners if o >= n_robots]
    if bad:
        raise WireError(f"owners must be robots below {n_robots}, got {bad[:3]}")
    centres = np.frombuffer(msg.centres, "<f4").astype(np.float32).reshape(k, dimension)
    if not np.isfinite(centres).all():
        raise WireError("a table's centres must be finite")
    if math.isnan(msg.copy_margin):
        raise WireError("copy_margin must be a number (negative: no copies)")
    if not 1 <= msg.copy_neighbours <= max(1, n_robots):
        raise WireError(f"copy_neighbours must be in [1, {n_robots}], got {msg.copy_neighbours}")
    if msg.version >= 2**63:
        raise WireError(f"version must be below 2^63, got {msg.version}")
    assignment = Assignment(
        tuple(int(o) for o in msg.owners), n_robots, method, None, version=int(msg.version)
    )
    return LiveTable(Router(centres, assignment), float(msg.copy_margin), int(msg.copy_neighbours))


def load_to_proto(load: OwnerLoad) -> pb.ClusterLoad:
    return pb.ClusterLoad(
        robot_id=load.robot,
        version=load.version,
        loads=load.loads.tolist(),
        replaced=list(load.replaced),
        replaced_centres=np.ascontiguousarray(load.replaced_centres, "<f4").tobytes(),
        new_centres=np.ascontiguousarray(load.new_centres, "<f4").tobytes(),
        pair_a=load.pair_a.tolist(),
        pair_b=load.pair_b.tolist(),
        pair_count=load.pair_count.tolist(),
        gaps=load.gaps.tolist(),
    )


def load_from_proto(msg: pb.ClusterLoad, dimension: int) -> OwnerLoad:
    """An owner's load as its message carries it; WireError when the centres are not whole
    float32 rows (the rest is checked against the table when merged)."""

    def rows(data: bytes, name: str) -> npt.NDArray[np.float32]:
        if len(data) % (4 * dimension):
            raise WireError(f"{name} is not whole rows of {dimension} float32")
        return np.frombuffer(data, "<f4").astype(np.float32).reshape(-1, dimension)

    return OwnerLoad(
        int(msg.robot_id),
        int(msg.version),
        np.asarray(msg.loads, np.int64),
        tuple(int(c) for c in msg.replaced),
        rows(msg.replaced_centres, "replaced_centres"),
        rows(msg.new_centres, "new_centres"),
        np.asarray(msg.pair_a, np.int64),
        np.asarray(msg.pair_b, np.int64),
        np.asarray(msg.pair_count, np.int64),
        np.asarray(msg.gaps, np.float32),
    )
