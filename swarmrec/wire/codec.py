"""Conversion between the core types and the v1 wire messages, with validation.

protobuf accepts any well-formed bytes, fills absent fields with zeros and
knows nothing of the label list, so a message that decodes can still be
nonsense: a label past the end of the list, 7 coordinates for 2 objects, a
count of zero. Every ``*_from_proto`` here checks a message against what the
receiver knows and raises :class:`~swarmrec.errors.WireError` naming the first
problem, so a service can answer ``ERROR_CODE_INVALID_ARGUMENT`` instead of
crashing later in numpy. Every ``*_to_proto`` refuses what the schema cannot
carry (NaN, negative ids, values past 32 bits) with the same error, rather
than letting protobuf raise its own exception types or silently clamp.

Two more things protobuf lets through. proto3 reads an absent field as 0, so
an empty payload is "robot 0, frame 0, step 0": fields a request cannot do
without are declared ``optional`` in the schema (presence is then on the wire)
and :func:`check_fields` refuses a request without them. And the bytes of
another message type often parse: their fields land in the unknown-field set
(a field number or wire type this schema does not have), which
:func:`check_fields` refuses as MALFORMED. The work a frame can cause is
bounded too (:class:`FrameLimits`): its objects are counted before anything
is converted, so refusing a huge frame costs next to nothing.

Positions travel as integer millimetres (zigzag varints, 1 to 2 bytes for the
few metres a camera sees) instead of 4-byte floats: a millimetre is finer than
any depth camera's noise, so nothing measurable is lost. A swarm that must
reproduce published scores bit for bit (the ``paper`` preset) sends them as
8-byte doubles instead (``exact``).
"""

from __future__ import annotations

import operator
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, SupportsIndex, TypeVar

import numpy as np
import numpy.typing as npt

# protobuf ships no type stubs and types-protobuf is not a dev dependency; with
# the stubs installed the ignore is unused, hence both codes.
from google.protobuf.message import (  # type: ignore[import-untyped, unused-ignore]
    DecodeError,
    Message,
)
from google.protobuf.unknown_fields import UnknownFieldSet  # type: ignore[import-untyped, unused-ignore]

from swarmrec.core.funnel import CandidateOutcome, Reason
from swarmrec.core.types import Constellation
from swarmrec.errors import (
    LabelOutOfRangeError,
    LimitExceededError,
    MalformedMessageError,
    MessageTooLargeError,
    MissingFieldError,
    WireError,
)
from swarmrec.wire.gen.swarmrec.v1 import (
    constellation_pb2,
    descriptor_pb2,
    errors_pb2,
    events_pb2,
    query_pb2,
    verify_pb2,
)

__all__ = [
    "MAX_ERROR_MESSAGE_CHARS",
    "MM_PER_M",
    "Candidate",
    "DescriptorSlice",
    "FrameLimits",
    "candidates_from_proto",
    "candidates_to_proto",
    "check_fields",
    "constellation_from_proto",
    "constellation_to_proto",
    "decode",
    "descriptor_from_proto",
    "descriptor_to_proto",
    "encode",
    "error_reply",
    "match_scores",
    "matched_pairs_from_proto",
    "outcomes_from_proto",
    "outcomes_to_proto",
    "partial_descriptor_from_proto",
    "partial_descriptor_to_proto",
    "schema_name",
    "verify_match_to_proto",
]

IntArray = npt.NDArray[np.int64]
FloatArray = npt.NDArray[np.float64]
M = TypeVar("M", bound=Message)

MM_PER_M = 1000
"""Wire positions are integer millimetres: ``round(metres * MM_PER_M)``."""

MAX_ERROR_MESSAGE_CHARS = 1000
"""An ErrorReply's message is cut to this length, so that a service echoing a
huge bad input in its error text cannot flood the bus."""

_UINT32_MAX = 2**32 - 1
_INT32_MIN = -(2**31)
_INT32_MAX = 2**31 - 1


# --- helpers ----------------------------------------------------------------


def _uint32(name: str, value: SupportsIndex) -> int:
    """``value`` as an int if it fits a uint32 field, else WireError.

    ``operator.index`` takes Python and numpy integers but refuses floats,
    which protobuf would otherwise reject with a TypeError of its own.
    """
    try:
        v = operator.index(value)
    except TypeError as e:
        raise WireError(f"{name} must be an integer, got {value!r}") from e
    if not 0 <= v <= _UINT32_MAX:
        raise WireError(f"{name} {v} does not fit in 32 unsigned bits")
    return v


def _check_n_labels(n_labels: int) -> None:
    # The receiver's own label list size: a wrong one is a caller bug, not bad input.
    if n_labels <= 0:
        raise ValueError(f"n_labels must be positive, got {n_labels}")


def _check_range(lo: int, hi: int, n_labels: int) -> None:
    if lo >= hi:
        raise WireError(f"label range [{lo}, {hi}) is empty")
    if hi > n_labels:
        raise LabelOutOfRangeError(f"label range [{lo}, {hi}) ends past the label list of {n_labels} labels")


def _dense_counts(counts: npt.ArrayLike) -> IntArray:
    """A dense count vector as int64, checked to fit the uint32 count fields."""
    arr = np.asarray(counts)
    if arr.ndim != 1:
        raise WireError(f"a descriptor is a 1-D count vector, got shape {arr.shape}")
    if arr.size and not np.issubdtype(arr.dtype, np.integer):
        raise WireError(f"descriptor counts must be integers, got {arr.dtype}")
    if arr.size and arr.min() < 0:
        raise WireError(f"descriptor count of label {int(np.argmin(arr))} is negative")
    if arr.size and arr.max() > _UINT32_MAX:
        raise WireError(f"descriptor count of label {int(np.argmax(arr))} does not fit in 32 unsigned bits")
    return arr.astype(np.int64, copy=False)


def _sparse_bins(
    indices: Iterable[int], counts: Iterable[int], lo: int, hi: int
) -> tuple[IntArray, IntArray]:
    """Validated (label - lo, count) arrays of a sparse descriptor over [lo, hi).

    Rejects what a dense vector cannot come from: unequal lengths, a label
    outside the range, a zero count (only non-zero bins are sent) and a label
    listed twice (which of the two counts would be meant?).
    """
    idx = np.fromiter(indices, dtype=np.int64)
    cnt = np.fromiter(counts, dtype=np.int64)
    if idx.shape != cnt.shape:
        raise WireError(f"descriptor lists {idx.size} labels but {cnt.size} counts")
    outside = np.flatnonzero(idx >= hi - lo)
    if outside.size:
        i = int(outside[0])
        raise WireError(f"descriptor bin {i}: label {lo + int(idx[i])} is outside [{lo}, {hi})")
    zero = np.flatnonzero(cnt == 0)
    if zero.size:
        i = int(zero[0])
        raise WireError(
            f"descriptor bin {i}: label {lo + int(idx[i])} has count 0; only non-zero bins are sent"
        )
    seen, times = np.unique(idx, return_counts=True)
    if (times > 1).any():
        raise WireError(f"descriptor lists label {lo + int(seen[times > 1][0])} more than once")
    return idx, cnt


def _unknown_field(msg: Message, path: str) -> str | None:
    """The path of the first (sub)message holding fields its schema does not have."""
    if len(UnknownFieldSet(msg)):
        return path
    for field, value in msg.ListFields():
        if field.message_type is None:
            continue
        items = value if field.is_repeated else (value,)
        for i, item in enumerate(items):
            name = f"{path}.{field.name}" + (f"[{i}]" if field.is_repeated else "")
            found = _unknown_field(item, name)
            if found is not None:
                return found
    return None


def check_fields(msg: Message, *required: str) -> None:
    """Refuse a request that carries fields its schema does not have, or lacks a required one.

    Unknown fields (a field number or wire type the schema does not have, as the
    bytes of another message type usually give) raise MalformedMessageError;
    a field of ``required`` that is not present raises MissingFieldError. A
    required field is a message field or an ``optional`` scalar (proto3 has no
    presence for plain scalars); ``"query.robot_id"`` names a field of a field.
    """
    name = schema_name(msg)
    where = _unknown_field(msg, name)
    if where is not None:
        raise MalformedMessageError(
            f"{where} holds fields its schema does not have (another message's bytes?)"
        )
    for path in required:
        holder = msg
        parts = path.split(".")
        for i, part in enumerate(parts):
            if not holder.HasField(part):
                raise MissingFieldError(name, ".".join(parts[: i + 1]))
            holder = getattr(holder, part)


# --- constellations ---------------------------------------------------------


@dataclass(frozen=True)
class FrameLimits:
    """Bounds on one frame's objects, so that the work a frame causes is bounded.

    ``setting_*`` name the settings the bounds come from, for the error message.
    """

    max_objects: int
    max_per_label: int
    setting_objects: str = "max_objects_per_frame"
    setting_per_label: str = "max_objects_per_label"

    def check_count(self, n: int) -> None:
        """Refuse a frame of ``n`` objects (before anything is converted)."""
        if n > self.max_objects:
            raise LimitExceededError("objects in the frame", n, self.max_objects, self.setting_objects)

    def check_labels(self, counts: npt.NDArray[np.int64], lo: int = 0) -> None:
        """Refuse per-label object counts (bin i is label ``lo + i``) over the bounds."""
        if counts.size and int(counts.max()) > self.max_per_label:
            i = int(np.argmax(counts))
            raise LimitExceededError(
                f"objects of label {lo + i} in the frame", int(counts[i]), self.max_per_label,
                self.setting_per_label,
            )  # fmt: skip
        total = int(counts.sum())
        if total > self.max_objects:
            raise LimitExceededError("objects in the frame", total, self.max_objects, self.setting_objects)


def constellation_to_proto(
    c: Constellation, robot: int, frame: int, frame_id: str = "", *, exact: bool = False
) -> constellation_pb2.Constellation:
    """The wire form of robot ``robot``'s frame ``frame``.

    Positions are rounded to the nearest millimetre with ``np.rint``, which
    rounds exact halves to even (0.0625 m -> 62 mm, 0.1875 m -> 188 mm): it is
    IEEE's default, has no bias, and exact half-millimetres are vanishingly
    rare in measured data. With ``exact`` they travel as the doubles they are
    (``positions_m``, 8 bytes each). Object order is kept (the association uses it).
    """
    robot_id = _uint32("robot id", robot)
    frame_index = _uint32("frame index", frame)
    labels = c.labels
    if labels.size and labels.min() < 0:
        raise WireError(f"object {int(np.argmin(labels))} has a negative label")
    if labels.size and labels.max() > _UINT32_MAX:
        raise WireError(f"object {int(np.argmax(labels))} has a label past 32 unsigned bits")
    finite = np.isfinite(c.positions).all(axis=1)
    if not finite.all():
        k = int(np.flatnonzero(~finite)[0])
        raise WireError(f"object {k} has a non-finite position {c.positions[k].tolist()}")
    msg = constellation_pb2.Constellation(
        robot_id=robot_id, frame_index=frame_index, labels=labels.tolist(), frame_id=frame_id
    )
    if exact:
        msg.positions_m.extend(c.positions.astype(np.float64).ravel().tolist())
        return msg
    # A finite but huge position overflows to inf here; the range check below reports it.
    with np.errstate(over="ignore"):
        mm = np.rint(c.positions * MM_PER_M)
    fits = ((mm >= _INT32_MIN) & (mm <= _INT32_MAX)).all(axis=1)
    if not fits.all():
        k = int(np.flatnonzero(~fits)[0])
        raise WireError(f"object {k} at {c.positions[k].tolist()} m is out of the int32 millimetre range")
    msg.positions_mm.extend(mm.astype(np.int64).ravel().tolist())
    return msg


def constellation_from_proto(
    msg: constellation_pb2.Constellation, n_labels: int, limits: FrameLimits | None = None
) -> Constellation:
    """The constellation in a wire message, checked against a list of ``n_labels`` labels
    and, when given, ``limits`` (the object count first, before anything is converted).

    Millimetres come back as ``mm / 1000``: dividing (rather than multiplying by
    0.001) gives the float nearest the exact decimal, so 1234 mm is 1.234.
    Exact positions come back as the doubles that were sent.
    """
    _check_n_labels(n_labels)
    n = len(msg.labels)
    if limits is not None:
        limits.check_count(n)
    exact = len(msg.positions_m) > 0
    if exact and len(msg.positions_mm):
        raise WireError("constellation carries both positions_mm and positions_m; send one")
    count = len(msg.positions_m) if exact else len(msg.positions_mm)
    if count != 3 * n:
        field = "positions_m" if exact else "positions_mm"
        raise WireError(
            f"constellation has {n} labels but {count} coordinates in {field}; expected 3 per label ({3 * n})"
        )
    labels = np.fromiter(msg.labels, dtype=np.int64, count=n)
    unknown = np.flatnonzero(labels >= n_labels)
    if unknown.size:
        k = int(unknown[0])
        raise LabelOutOfRangeError(
            f"object {k} has label {int(labels[k])}, outside the label list of {n_labels} labels"
        )
    if limits is not None:
        limits.check_labels(np.bincount(labels, minlength=1))
    if exact:
        metres = np.fromiter(msg.positions_m, dtype=np.float64, count=3 * n).reshape(n, 3)
        bad = np.flatnonzero(~np.isfinite(metres).all(axis=1))
        if bad.size:
            raise WireError(f"object {int(bad[0])} has a non-finite position {metres[bad[0]].tolist()}")
        return Constellation(labels, metres)
    mm = np.fromiter(msg.positions_mm, dtype=np.float64, count=3 * n)
    return Constellation(labels, mm.reshape(n, 3) / MM_PER_M)


# --- descriptors ------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class DescriptorSlice:
    """Labels ``[lo, hi)`` of one frame's descriptor: ``counts[i]`` is label ``lo + i``."""

    lo: int
    hi: int
    counts: IntArray


def descriptor_to_proto(counts: npt.ArrayLike) -> descriptor_pb2.SemanticDescriptor:
    """The sparse wire form of a dense count vector (one integer per label)."""
    dense = _dense_counts(counts)
    labels = np.flatnonzero(dense)
    return descriptor_pb2.SemanticDescriptor(
        n_labels=_uint32("label list size", dense.size),
        labels=labels.tolist(),
        counts=dense[labels].tolist(),
    )


def descriptor_from_proto(msg: descriptor_pb2.SemanticDescriptor, n_labels: int) -> IntArray:
    """The dense int64 count vector (length ``n_labels``) of a sparse descriptor.

    A descriptor built over another label list is refused: its bins would be
    read as the wrong labels.
    """
    _check_n_labels(n_labels)
    if msg.n_labels != n_labels:
        raise WireError(f"descriptor is over {msg.n_labels} labels but the label list has {n_labels}")
    labels, counts = _sparse_bins(msg.labels, msg.counts, 0, n_labels)
    dense = np.zeros(n_labels, dtype=np.int64)
    dense[labels] = counts
    return dense


def partial_descriptor_to_proto(
    counts: npt.ArrayLike,
    lo: int,
    hi: int,
    *,
    robot: int,
    frame: int,
    query_step: int,
) -> descriptor_pb2.PartialDescriptor:
    """The slice ``[lo, hi)`` of a dense count vector, for the shard owning those labels."""
    dense = _dense_counts(counts)
    lo, hi = _uint32("label_lo", lo), _uint32("label_hi", hi)
    _check_range(lo, hi, dense.size)
    offsets = np.flatnonzero(dense[lo:hi])
    return descriptor_pb2.PartialDescriptor(
        robot_id=_uint32("robot id", robot),
        frame_index=_uint32("frame index", frame),
        query_step=_uint32("query step", query_step),
        label_lo=lo,
        label_hi=hi,
        label_offsets=offsets.tolist(),
        counts=dense[lo + offsets].tolist(),
    )


def partial_descriptor_from_proto(
    msg: descriptor_pb2.PartialDescriptor, n_labels: int, limits: FrameLimits | None = None
) -> DescriptorSlice:
    """The dense slice in a partial descriptor, checked against a list of ``n_labels`` labels
    and, when given, ``limits`` (no count past a frame's bounds).

    The range must satisfy ``lo < hi <= n_labels``; whether it is the range
    the receiving shard owns is the shard's business.
    """
    _check_n_labels(n_labels)
    lo, hi = msg.label_lo, msg.label_hi
    _check_range(lo, hi, n_labels)
    offsets, counts = _sparse_bins(msg.label_offsets, msg.counts, lo, hi)
    dense = np.zeros(hi - lo, dtype=np.int64)
    dense[offsets] = counts
    if limits is not None:
        limits.check_labels(dense, lo)
    return DescriptorSlice(lo=lo, hi=hi, counts=dense)


# --- candidates and matches -------------------------------------------------


@dataclass(frozen=True)
class Candidate:
    """A stored frame an index shard proposes for a query, with its partial score."""

    robot_id: int
    frame_index: int
    score: float


def candidates_to_proto(
    query_id: int, candidates: Iterable[Candidate], *, include_scores: bool = True
) -> query_pb2.CandidatesReply:
    """A shard's reply; candidates keep their order (best first). The label range is
    left out: zenoh pairs the reply with its request, which names it.

    Scores travel as float32 (about 7 significant digits), enough to rank,
    and only when ``include_scores``.
    """
    items = list(candidates)
    bad = [c for c in items if not np.isfinite(c.score)]
    if bad:
        raise WireError(f"candidate {bad[0]} has a non-finite score")
    return query_pb2.CandidatesReply(
        query_id=_uint32("query id", query_id),
        robot_ids=[_uint32("robot id", c.robot_id) for c in items],
        frame_indices=[_uint32("frame index", c.frame_index) for c in items],
        scores=[c.score for c in items] if include_scores else [],
    )


def candidates_from_proto(msg: query_pb2.CandidatesReply, n_labels: int) -> list[Candidate]:
    """The candidates of a shard's reply, after checking the reply is consistent (its
    label range too, when it names one: replies of this version leave it out)."""
    _check_n_labels(n_labels)
    if msg.label_lo or msg.label_hi:
        _check_range(msg.label_lo, msg.label_hi, n_labels)
    n = len(msg.robot_ids)
    if len(msg.frame_indices) != n or len(msg.scores) not in (0, n):
        raise WireError(
            f"candidates reply has {n} robot ids, {len(msg.frame_indices)} frame indices"
            f" and {len(msg.scores)} scores; they must be equal (or no scores)"
        )
    # Without scores (the querier did not ask for them) every candidate reads as NaN.
    scores = np.fromiter(msg.scores, dtype=np.float64, count=n) if msg.scores else np.full(n, np.nan)
    bad = np.flatnonzero(np.isinf(scores) | (np.isnan(scores) & bool(msg.scores)))
    if bad.size:
        raise WireError(f"candidate {int(bad[0])} has a non-finite score")
    return [
        Candidate(robot_id=r, frame_index=f, score=float(s))
        for r, f, s in zip(msg.robot_ids, msg.frame_indices, scores, strict=True)
    ]


def verify_match_to_proto(
    frame_index: int,
    n_matched: int,
    n_common: int,
    n_union: int,
    pairs: npt.ArrayLike | None = None,
) -> verify_pb2.VerifyMatch:
    """One verified match, as the counts its scores are computed from (see
    :func:`match_scores`); ``pairs`` is an (n_matched, 2) array of
    (query object, matched object) indices, or None when not requested."""
    if not 0 <= n_matched <= n_common <= n_union or n_common == 0:
        raise WireError(f"match counts need 0 <= n_matched <= n_common <= n_union and n_common > 0, got "
                        f"{n_matched}, {n_common}, {n_union}")  # fmt: skip
    msg = verify_pb2.VerifyMatch(
        frame_index=_uint32("frame index", frame_index),
        n_matched=_uint32("matched object count", n_matched),
        n_common=_uint32("common object count", n_common),
        n_union=_uint32("union object count", n_union),
    )
    if pairs is not None:
        arr = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        if arr.shape[0] != n_matched:
            raise WireError(f"{arr.shape[0]} object pairs for {n_matched} matched objects")
        if arr.size and (arr.min() < 0 or arr.max() > _UINT32_MAX):
            raise WireError("object pair indices must fit in 32 unsigned bits")
        msg.object_pairs.extend(arr.ravel().tolist())
    return msg


def match_scores(match: verify_pb2.VerifyMatch) -> tuple[float, float]:
    """(score, semantic score) of a verified match, the same doubles the
    verifier computed: the association kernel evaluates
    ``semantic = n_common / n_union`` and ``score = semantic * (n_matched / n_common)``
    in this order, and IEEE arithmetic gives the same bits here."""
    if not 0 < match.n_common <= match.n_union or match.n_matched > match.n_common:
        raise WireError(
            f"match of frame {match.frame_index} has inconsistent counts: {match.n_matched} matched, "
            f"{match.n_common} common, {match.n_union} in the union"
        )
    semantic = match.n_common / match.n_union
    return semantic * (match.n_matched / match.n_common), semantic


def matched_pairs_from_proto(match: verify_pb2.VerifyMatch, n_query: int) -> IntArray:
    """The (m, 2) int64 array of (query object, matched object) index pairs of a match.

    Empty (shape (0, 2)) when the verifier did not send pairs. Query indices
    must be below ``n_query`` (the asker's own constellation size) and each
    object may be matched once, since the association is one-to-one.
    """
    flat = np.fromiter(match.object_pairs, dtype=np.int64)
    if flat.size % 2:
        raise WireError(f"match lists {flat.size} pair indices; expected an even number")
    pairs = flat.reshape(-1, 2)
    if pairs.shape[0] and pairs.shape[0] != match.n_matched:
        raise WireError(f"match has {pairs.shape[0]} pairs but n_matched={match.n_matched}")
    outside = np.flatnonzero(pairs[:, 0] >= n_query)
    if outside.size:
        i = int(outside[0])
        raise WireError(f"pair {i} names query object {int(pairs[i, 0])} of a {n_query}-object query")
    for column, side in ((0, "query"), (1, "matched")):
        if np.unique(pairs[:, column]).size != pairs.shape[0]:
            raise WireError(f"a {side} object appears in more than one pair")
    return pairs


# --- the loop-closure funnel -------------------------------------------------


def outcomes_to_proto(outcomes: Iterable[CandidateOutcome]) -> list[events_pb2.CandidateOutcome]:
    """A query's candidate outcomes as its report carries them: robot, frame and reason
    (robot 0 and frame 0 cost no byte). The scores are not sent again: a scored
    candidate's score is the report's match of the same robot and frame."""
    return [
        events_pb2.CandidateOutcome(
            robot_id=_uint32("robot id", o.robot),
            frame_index=_uint32("frame index", o.frame),
            reason=events_pb2.FunnelReason.ValueType(o.reason),
        )
        for o in outcomes
    ]


def outcomes_from_proto(report: events_pb2.QueryReport) -> list[CandidateOutcome]:
    """The candidate outcomes of ``report``, each with its score from the report's matches
    (0 for a candidate without a match). A reason this version does not know reads as
    UNSPECIFIED (a newer sender's), never as another one."""
    scores = {(m.match_robot_id, m.match_frame_index): m.score for m in report.matches}
    return [
        CandidateOutcome(
            c.robot_id, c.frame_index, Reason.of(c.reason), scores.get((c.robot_id, c.frame_index), 0.0)
        )
        for c in report.candidates
    ]


# --- errors -----------------------------------------------------------------


def error_reply(code: int, message: str) -> errors_pb2.ErrorReply:
    """An ErrorReply with ``code`` (a :class:`swarmrec.errors.ErrorCode`, the schema's
    numbers) and ``message`` cut to :data:`MAX_ERROR_MESSAGE_CHARS`."""
    if len(message) > MAX_ERROR_MESSAGE_CHARS:
        message = message[: MAX_ERROR_MESSAGE_CHARS - 1] + "…"
    return errors_pb2.ErrorReply(code=code, message=message)  # type: ignore[arg-type]  # an enum value


# --- bytes ------------------------------------------------------------------


def schema_name(msg_or_cls: Any) -> str:
    """The full protobuf name of a message or message class, e.g. ``swarmrec.v1.Constellation``.

    Services send payloads as ``Encoding.APPLICATION_PROTOBUF.with_schema(name)``
    so that a receiver can tell a reply from an ``ErrorReply`` before decoding.
    """
    try:
        name: str = msg_or_cls.DESCRIPTOR.full_name
    except AttributeError as e:
        raise TypeError(f"{msg_or_cls!r} is not a protobuf message or message class") from e
    return name


def encode(msg: Message, *, max_size: int | None = None) -> bytes:
    """The serialized bytes of ``msg``; WireError if they would exceed ``max_size``.

    The size is computed before serializing, so an oversize message is never built.
    """
    if max_size is not None:
        size: int = msg.ByteSize()
        if size > max_size:
            raise MessageTooLargeError(size, max_size)
    data: bytes = msg.SerializeToString()
    return data


def decode(data: bytes, cls: type[M], *, max_size: int | None = None) -> M:
    """Parse ``data`` as a ``cls`` message; WireError if it does not parse or is too large.

    The size is checked before parsing, so an oversize payload costs nothing.
    Parsing only checks the bytes are well-formed; the ``*_from_proto``
    functions check what the fields mean.
    """
    if max_size is not None and len(data) > max_size:
        raise MessageTooLargeError(len(data), max_size)
    try:
        msg: M = cls.FromString(data)
    except DecodeError as e:
        raise MalformedMessageError(f"{len(data)} bytes do not decode as {schema_name(cls)}: {e}") from e
    return msg
