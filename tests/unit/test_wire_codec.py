"""The v1 wire codec: round-trips, rounding, validation and measured sizes."""

from __future__ import annotations

import math
import pickle
from typing import Any

import numpy as np
import pytest

# protobuf ships no type stubs; with types-protobuf installed the ignore is unused.
from google.protobuf import (  # type: ignore[import-untyped, unused-ignore]
    descriptor_pb2,
    descriptor_pool,
    message_factory,
)

import swarmrec.wire
from swarmrec.core.types import Constellation
from swarmrec.errors import ErrorCode, LimitExceededError, MalformedMessageError, MissingFieldError, WireError
from swarmrec.wire import (
    MAX_ERROR_MESSAGE_CHARS,
    Candidate,
    candidates_from_proto,
    candidates_to_proto,
    constellation_from_proto,
    constellation_to_proto,
    decode,
    descriptor_from_proto,
    descriptor_to_proto,
    encode,
    error_reply,
    matched_pairs_from_proto,
    message_class,
    partial_descriptor_from_proto,
    partial_descriptor_to_proto,
    schema_name,
    verify_match_to_proto,
)
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import FrameLimits, check_fields, match_scores

N_LABELS = 80  # a COCO-sized label list


def typical_constellation(seed: int = 0) -> Constellation:
    """10 objects with labels < 80, within +-3 m sideways and up to 3 m ahead."""
    rng = np.random.default_rng(seed)
    labels = rng.integers(0, N_LABELS, size=10)
    positions = np.column_stack([rng.uniform(-3, 3, 10), rng.uniform(-1.5, 1.5, 10), rng.uniform(0.3, 3, 10)])
    return Constellation(labels, positions)


def typical_counts() -> np.ndarray:
    counts = np.zeros(N_LABELS, dtype=np.int64)
    np.add.at(counts, typical_constellation().labels, 1)
    return counts


def round_trip_constellation(c: Constellation) -> Constellation:
    data = encode(constellation_to_proto(c, robot=3, frame=1234))
    return constellation_from_proto(decode(data, pb.Constellation), N_LABELS)


# --- constellations -----------------------------------------------------------


def test_constellation_round_trips_to_the_millimetre() -> None:
    c = typical_constellation()
    data = encode(constellation_to_proto(c, robot=3, frame=1234, frame_id="1305031102.175304"))
    msg = decode(data, pb.Constellation)
    back = constellation_from_proto(msg, N_LABELS)

    assert (msg.robot_id, msg.frame_index, msg.frame_id) == (3, 1234, "1305031102.175304")
    np.testing.assert_array_equal(back.labels, c.labels)
    # Half a millimetre, plus float error of the metre <-> millimetre scaling.
    np.testing.assert_allclose(back.positions, c.positions, rtol=0, atol=0.0005 + 1e-12)


@pytest.mark.parametrize(
    ("metres", "millimetres"),
    [
        (0.0014, 1),
        (0.0016, 2),
        (-0.0016, -2),
        (1.234, 1234),
        (-2.9996, -3000),
        # 0.0625 and 0.1875 are exact in binary, so these are true ties: to even.
        (0.0625, 62),
        (0.1875, 188),
        (-0.0625, -62),
    ],
)
def test_positions_round_to_the_nearest_millimetre_with_ties_to_even(metres: float, millimetres: int) -> None:
    c = Constellation(np.array([0]), np.array([[metres, 0.0, 0.0]]))
    assert list(constellation_to_proto(c, robot=0, frame=0).positions_mm) == [millimetres, 0, 0]


def test_decoded_millimetres_are_the_nearest_float_to_the_decimal_metres() -> None:
    msg = pb.Constellation(labels=[1], positions_mm=[1234, -7, 2999])
    c = constellation_from_proto(msg, N_LABELS)
    assert c.positions.tolist() == [[1.234, -0.007, 2.999]]


def test_constellation_keeps_the_detector_object_order() -> None:
    c = Constellation(np.array([5, 2, 5, 0]), np.arange(12, dtype=np.float64).reshape(4, 3))
    back = round_trip_constellation(c)
    np.testing.assert_array_equal(back.labels, [5, 2, 5, 0])
    np.testing.assert_array_equal(back.positions, c.positions)


def test_empty_constellation_round_trips() -> None:
    assert len(round_trip_constellation(Constellation.empty())) == 0


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_constellation_encoding_rejects_a_non_finite_position(bad: float) -> None:
    positions = np.zeros((3, 3))
    positions[1, 2] = bad
    with pytest.raises(WireError, match="object 1 has a non-finite position"):
        constellation_to_proto(Constellation(np.zeros(3, dtype=np.int64), positions), robot=0, frame=0)


@pytest.mark.parametrize("metres", [2147484.0, -2147484.0, 1e308])
def test_constellation_encoding_rejects_a_position_beyond_int32_millimetres(metres: float) -> None:
    c = Constellation(np.array([0]), np.array([[0.0, metres, 0.0]]))
    with pytest.raises(WireError, match="out of the int32 millimetre range"):
        constellation_to_proto(c, robot=0, frame=0)


def test_constellation_encoding_accepts_the_largest_int32_millimetre_position() -> None:
    c = Constellation(np.array([0]), np.array([[2147483.647, -2147483.648, 0.0]]))
    msg = constellation_to_proto(c, robot=0, frame=0)
    assert list(msg.positions_mm) == [2**31 - 1, -(2**31), 0]


@pytest.mark.parametrize(
    ("robot", "frame", "match"),
    [(-1, 0, "robot id -1"), (0, 2**32, "frame index 4294967296"), (0, 1.5, "frame index must")],
)
def test_constellation_encoding_rejects_ids_that_are_not_uint32(robot: int, frame: int, match: str) -> None:
    with pytest.raises(WireError, match=match):
        constellation_to_proto(typical_constellation(), robot=robot, frame=frame)


def test_constellation_encoding_rejects_a_negative_label() -> None:
    c = Constellation(np.array([0, -1]), np.zeros((2, 3)))
    with pytest.raises(WireError, match="object 1 has a negative label"):
        constellation_to_proto(c, robot=0, frame=0)


def test_constellation_decoding_rejects_an_unknown_label() -> None:
    msg = pb.Constellation(labels=[3, N_LABELS], positions_mm=[0] * 6)
    with pytest.raises(WireError, match=f"object 1 has label {N_LABELS}, outside"):
        constellation_from_proto(msg, N_LABELS)


@pytest.mark.parametrize("n_coordinates", [0, 5, 7, 9])
def test_constellation_decoding_rejects_coordinates_not_three_per_label(
    n_coordinates: int,
) -> None:
    msg = pb.Constellation(labels=[1, 2], positions_mm=[0] * n_coordinates)
    with pytest.raises(WireError, match="expected 3 per label"):
        constellation_from_proto(msg, N_LABELS)


def test_exact_positions_round_trip_bit_for_bit() -> None:
    # The TUM files' positions carry 16-17 significant digits; millimetres would drop them.
    positions = np.array(
        [[-0.32184009523809526, -0.00016391428571430056, 2.10052], [0.1 + 0.2, 1e-300, -7.5]]
    )
    c = Constellation(np.array([32, 39]), positions)
    msg = constellation_to_proto(c, 3, 9, exact=True)
    assert list(msg.positions_mm) == [] and len(msg.positions_m) == 6
    back = constellation_from_proto(pb.Constellation.FromString(msg.SerializeToString()), 80)
    assert back.positions.tobytes() == positions.tobytes() and back.labels.tolist() == [32, 39]
    # Eight bytes a coordinate, against two for millimetres.
    assert msg.ByteSize() - constellation_to_proto(c, 3, 9).ByteSize() > 6 * 5


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"positions_mm": [1, 2, 3], "positions_m": [1.0, 2.0, 3.0]}, "both positions_mm and positions_m"),
        ({"positions_m": [1.0, 2.0]}, "2 coordinates in positions_m; expected 3"),
        ({"positions_m": [1.0, math.nan, 3.0]}, "non-finite position"),
        ({"positions_m": [1.0, 2.0, -math.inf]}, "non-finite position"),
    ],
)
def test_exact_positions_that_do_not_make_a_constellation_are_refused(
    fields: dict[str, Any], message: str
) -> None:
    msg = pb.Constellation(robot_id=1, labels=[3], **fields)
    with pytest.raises(WireError, match=message):
        constellation_from_proto(msg, 80)


def test_typical_constellation_encodes_in_at_most_79_bytes() -> None:
    # By hand, from protobuf's encoding rules (tag = 1 byte for fields 1-15;
    # a varint carries 7 bits a byte; sint32 zigzags v to 2|v| or 2|v| - 1):
    #   robot_id 3            tag 1 + varint 1                     =  2
    #   frame_index 1234      tag 1 + varint 2 (1234 < 2^14)       =  3
    #   labels, 10 x < 128    tag 1 + length 1 + 10 x 1            = 12
    #   positions_mm, 30 values with |v| <= 3000 mm:
    #                         zigzag <= 6000 < 2^14, so <= 2 bytes each;
    #                         tag 1 + length 1 (<= 60 < 128) + 30 x 2 = 62
    #   frame_id empty        not sent                             =  0
    #                                                        total <= 79
    # (A float32 per coordinate would be 120 bytes for positions alone.)
    for seed in range(20):
        size = len(encode(constellation_to_proto(typical_constellation(seed), 3, 1234)))
        assert size <= 79, f"seed {seed}: {size} bytes"


def per_object_constellation_class() -> type:
    """The rejected schema with one sub-message per object, built in a private pool."""
    fdp = descriptor_pb2.FileDescriptorProto(
        name="size_comparison.proto", package="size_comparison", syntax="proto3"
    )
    obj = fdp.message_type.add(name="Object")
    fields = [("label", "TYPE_UINT32"), ("x_mm", "TYPE_SINT32")]
    fields += [("y_mm", "TYPE_SINT32"), ("z_mm", "TYPE_SINT32")]
    for number, (name, kind) in enumerate(fields, start=1):
        obj.field.add(
            name=name,
            number=number,
            type=descriptor_pb2.FieldDescriptorProto.Type.Value(kind),
            label=descriptor_pb2.FieldDescriptorProto.LABEL_OPTIONAL,
        )
    outer = fdp.message_type.add(name="Constellation")
    for number, name in enumerate(["robot_id", "frame_index"], start=1):
        outer.field.add(
            name=name,
            number=number,
            type=descriptor_pb2.FieldDescriptorProto.TYPE_UINT32,
            label=descriptor_pb2.FieldDescriptorProto.LABEL_OPTIONAL,
        )
    outer.field.add(
        name="objects",
        number=3,
        type=descriptor_pb2.FieldDescriptorProto.TYPE_MESSAGE,
        type_name=".size_comparison.Object",
        label=descriptor_pb2.FieldDescriptorProto.LABEL_REPEATED,
    )
    pool = descriptor_pool.DescriptorPool()
    pool.Add(fdp)
    cls: type = message_factory.GetMessageClass(pool.FindMessageTypeByName("size_comparison.Constellation"))
    return cls


def test_packed_arrays_are_far_smaller_than_a_sub_message_per_object() -> None:
    # Why the schema uses parallel packed arrays. A sub-message per object costs,
    # per object, its own tag and length (2) plus a tag for each of its 4 fields
    # (4), while the packed form pays 2 tags and 2 lengths once: 6 k - 4 bytes
    # more for k objects. Measured on these frames: 77-79 bytes against 133-135.
    per_object = per_object_constellation_class()
    for seed in range(20):
        c = typical_constellation(seed)
        packed = constellation_to_proto(c, robot=3, frame=1234)
        alternative = per_object(robot_id=3, frame_index=1234)
        for k in range(len(c)):
            x, y, z = packed.positions_mm[3 * k : 3 * k + 3]
            alternative.objects.add(label=packed.labels[k], x_mm=x, y_mm=y, z_mm=z)
        assert alternative.ByteSize() - packed.ByteSize() == 6 * len(c) - 4


# --- descriptors --------------------------------------------------------------


def test_descriptor_round_trips_through_its_sparse_form() -> None:
    counts = typical_counts()
    msg = decode(encode(descriptor_to_proto(counts)), pb.SemanticDescriptor)
    back = descriptor_from_proto(msg, N_LABELS)
    assert back.dtype == np.int64
    np.testing.assert_array_equal(back, counts)


def test_descriptor_sends_only_the_non_zero_bins_in_ascending_order() -> None:
    counts = np.zeros(N_LABELS, dtype=np.int64)
    counts[[70, 4, 9]] = [1, 3, 2]
    msg = descriptor_to_proto(counts)
    assert (msg.n_labels, list(msg.labels), list(msg.counts)) == (N_LABELS, [4, 9, 70], [3, 2, 1])


@pytest.mark.parametrize(
    ("counts", "match"),
    [
        (np.array([1, -1, 0]), "label 1 is negative"),
        (np.array([1.0, 2.0]), "must be integers"),
        (np.array([[1, 2]]), "1-D count vector"),
        (np.array([2**32]), "does not fit in 32 unsigned bits"),
    ],
)
def test_descriptor_encoding_rejects_counts_the_wire_cannot_carry(counts: np.ndarray, match: str) -> None:
    with pytest.raises(WireError, match=match):
        descriptor_to_proto(counts)


def test_descriptor_decoding_rejects_a_descriptor_over_another_label_list() -> None:
    msg = descriptor_to_proto(np.ones(N_LABELS + 1, dtype=np.int64))
    with pytest.raises(WireError, match=f"over {N_LABELS + 1} labels but the label list has 80"):
        descriptor_from_proto(msg, N_LABELS)


@pytest.mark.parametrize(
    ("labels", "counts", "match"),
    [
        ([1, 80], [1, 1], r"bin 1: label 80 is outside \[0, 80\)"),
        ([1, 2], [1, 0], "label 2 has count 0"),
        ([5, 1, 5], [1, 1, 2], "lists label 5 more than once"),
        ([1, 2], [1], "lists 2 labels but 1 counts"),
    ],
)
def test_descriptor_decoding_rejects_bins_no_count_vector_has(
    labels: list[int], counts: list[int], match: str
) -> None:
    msg = pb.SemanticDescriptor(n_labels=N_LABELS, labels=labels, counts=counts)
    with pytest.raises(WireError, match=match):
        descriptor_from_proto(msg, N_LABELS)


def test_partial_descriptor_round_trips_its_slice() -> None:
    counts = typical_counts()
    msg = partial_descriptor_to_proto(counts, 20, 40, robot=3, frame=1234, query_step=77)
    msg = decode(encode(msg), pb.PartialDescriptor)
    part = partial_descriptor_from_proto(msg, N_LABELS)

    assert (msg.robot_id, msg.frame_index, msg.query_step) == (3, 1234, 77)
    assert (part.lo, part.hi) == (20, 40)
    np.testing.assert_array_equal(part.counts, counts[20:40])


def test_partial_descriptor_sends_labels_as_offsets_from_lo() -> None:
    counts = np.zeros(N_LABELS, dtype=np.int64)
    counts[[59, 62, 70]] = [2, 1, 5]  # 59 and 70 are outside the slice
    msg = partial_descriptor_to_proto(counts, 60, 70, robot=0, frame=0, query_step=0)
    assert (list(msg.label_offsets), list(msg.counts)) == ([2], [1])


@pytest.mark.parametrize(
    ("lo", "hi", "match"),
    [
        (10, 10, r"\[10, 10\) is empty"),
        (11, 10, r"\[11, 10\) is empty"),
        (70, 81, r"\[70, 81\) ends past the label list of 80 labels"),
        (-1, 10, "label_lo -1 does not fit"),
    ],
)
def test_partial_descriptor_encoding_rejects_a_bad_label_range(lo: int, hi: int, match: str) -> None:
    with pytest.raises(WireError, match=match):
        partial_descriptor_to_proto(typical_counts(), lo, hi, robot=0, frame=0, query_step=0)


@pytest.mark.parametrize(
    ("lo", "hi", "offsets", "counts", "match"),
    [
        (10, 10, [], [], "is empty"),
        (0, 0, [], [], "is empty"),  # an all-default message
        (20, 30, [], [], ""),  # an empty slice is a valid query
        (70, 81, [0], [1], "ends past the label list"),
        (20, 30, [10], [1], r"label 30 is outside \[20, 30\)"),
        (20, 30, [3, 3], [1, 1], "lists label 23 more than once"),
        (20, 30, [3], [0], "label 23 has count 0"),
        (20, 30, [3, 4], [1], "lists 2 labels but 1 counts"),
    ],
)
def test_partial_descriptor_decoding_checks_its_range_and_bins(
    lo: int, hi: int, offsets: list[int], counts: list[int], match: str
) -> None:
    msg = pb.PartialDescriptor(label_lo=lo, label_hi=hi, label_offsets=offsets, counts=counts)
    if not match:
        assert partial_descriptor_from_proto(msg, N_LABELS).counts.tolist() == [0] * (hi - lo)
        return
    with pytest.raises(WireError, match=match):
        partial_descriptor_from_proto(msg, N_LABELS)


def test_typical_partial_query_encodes_in_29_bytes() -> None:
    # Each field is a 1-byte tag plus its varint:
    #   query_id 1234 (3) + n_ret 10 (2) + descriptor tag and length (2)
    #   + robot 3 (2) + frame 1234 (3) + step 1234 (3) + lo 20 (2) + hi 40 (2)
    #   + offsets and counts of the 3 bins in the slice, 1-byte varints each:
    #     2 x (tag 1 + length 1 + 3) = 10                          total 29.
    counts = np.zeros(N_LABELS, dtype=np.int64)
    counts[[3, 21, 25, 33, 60]] = [1, 2, 1, 4, 2]
    descriptor = partial_descriptor_to_proto(counts, 20, 40, robot=3, frame=1234, query_step=1234)
    query = pb.PartialQuery(query_id=1234, n_ret=10, descriptor=descriptor)
    assert len(encode(query)) == 29


# --- candidates and matches ---------------------------------------------------


FOUR_CANDIDATES = [
    Candidate(robot_id=1, frame_index=310, score=0.75),
    Candidate(robot_id=0, frame_index=12, score=0.5),
    Candidate(robot_id=7, frame_index=2047, score=0.25),
    Candidate(robot_id=1, frame_index=0, score=0.125),
]


def test_candidates_round_trip_in_order() -> None:
    msg = candidates_to_proto(42, FOUR_CANDIDATES)
    msg = decode(encode(msg), pb.CandidatesReply)
    assert (msg.query_id, msg.label_lo, msg.label_hi) == (42, 0, 0)  # the request names the range
    # The scores are exact in float32, so equality holds.
    assert candidates_from_proto(msg, N_LABELS) == FOUR_CANDIDATES


def test_candidates_reply_with_four_candidates_encodes_in_35_bytes() -> None:
    # query_id 1234 (3) + robot_ids (tag, length, 4 x 1: 6)
    # + frame_indices 310, 12, 2047, 0 (tag, length, 2 + 1 + 2 + 1: 8)
    # + scores (tag, length, 4 x 4: 18) = 35 bytes; frame indices below 2^14
    # keep it at most 37. A sub-message per candidate would cost 12 bytes each
    # (tag, length, robot 2, frame 3, score 5) against 7 here. The label range (4 bytes
    # here) is not echoed: the request names it.
    assert len(encode(candidates_to_proto(1234, FOUR_CANDIDATES))) == 35


def test_a_reply_that_names_a_range_still_has_it_checked() -> None:
    ok = pb.CandidatesReply(label_lo=20, label_hi=40, robot_ids=[1], frame_indices=[3])
    assert [(c.robot_id, c.frame_index) for c in candidates_from_proto(ok, N_LABELS)] == [(1, 3)]
    with pytest.raises(WireError, match="ends past the label list"):
        candidates_from_proto(pb.CandidatesReply(label_lo=20, label_hi=N_LABELS + 1), N_LABELS)


@pytest.mark.parametrize(
    ("fields", "match"),
    [
        ({"frame_indices": [1]}, "2 robot ids, 1 frame indices and 2 scores"),
        ({"scores": [0.5, float("nan")]}, "candidate 1 has a non-finite score"),
        ({"label_lo": 40}, r"\[40, 40\) is empty"),
        ({"scores": [0.5]}, "2 robot ids, 2 frame indices and 1 scores"),
        ({"scores": [0.5, float("inf")]}, "candidate 1 has a non-finite score"),
    ],
)
def test_candidates_decoding_rejects_an_inconsistent_reply(fields: dict[str, Any], match: str) -> None:
    values: dict[str, Any] = {
        "label_lo": 20,
        "label_hi": 40,
        "robot_ids": [1, 2],
        "frame_indices": [3, 4],
        "scores": [0.5, 0.25],
    }
    msg = pb.CandidatesReply(**(values | fields))
    with pytest.raises(WireError, match=match):
        candidates_from_proto(msg, N_LABELS)


def test_candidates_encoding_rejects_a_non_finite_score() -> None:
    with pytest.raises(WireError, match="non-finite score"):
        candidates_to_proto(1, [Candidate(0, 0, float("inf"))])


def test_candidates_without_scores_send_no_score_bytes_and_decode_as_nan() -> None:
    # The 35-byte reply above less its scores field (tag, length, 4 x 4 = 18): 17 bytes.
    msg = candidates_to_proto(1234, FOUR_CANDIDATES, include_scores=False)
    data = encode(msg)
    assert len(data) == 17
    back = candidates_from_proto(decode(data, pb.CandidatesReply), N_LABELS)
    assert [(c.robot_id, c.frame_index) for c in back] == [(1, 310), (0, 12), (7, 2047), (1, 0)]
    assert all(math.isnan(c.score) for c in back)


def test_candidates_without_scores_still_refuse_a_non_finite_score_on_encoding() -> None:
    with pytest.raises(WireError, match="non-finite score"):
        candidates_to_proto(1, [Candidate(0, 0, float("nan"))], include_scores=False)


def test_verify_reply_round_trips_matched_object_pairs() -> None:
    pairs = np.array([[0, 4], [2, 1], [5, 0]])
    match = verify_match_to_proto(17, 3, 4, 9, pairs=pairs)
    reply = pb.VerifyReply(query_id=5, robot_id=2, matches=[match])
    back = decode(encode(reply), pb.VerifyReply).matches[0]
    assert (back.frame_index, back.n_matched, back.n_common, back.n_union) == (17, 3, 4, 9)
    np.testing.assert_array_equal(matched_pairs_from_proto(back, n_query=6), pairs)


def test_verify_match_without_pairs_has_an_empty_pair_array() -> None:
    match = verify_match_to_proto(17, 3, 4, 9)
    assert matched_pairs_from_proto(match, n_query=6).shape == (0, 2)


def test_verify_match_without_pairs_encodes_in_9_bytes() -> None:
    # frame_index 1234 (tag 1 + 2) + n_matched 3, n_common 4, n_union 9 (tag 1 + 1 each):
    # 9 bytes, where the two doubles it replaced cost 18 on their own.
    assert len(encode(verify_match_to_proto(1234, 3, 4, 9))) == 9


def test_match_scores_are_the_ratios_of_the_counts() -> None:
    # 4 objects in common out of 9: semantic 4/9; 3 of the 4 matched: score 4/9 * 3/4 = 1/3.
    score, semantic = match_scores(verify_match_to_proto(17, 3, 4, 9))
    assert semantic == 4 / 9
    assert score == pytest.approx(1 / 3, rel=1e-15)
    assert match_scores(verify_match_to_proto(17, 0, 2, 9)) == (0.0, 2 / 9)


@pytest.mark.parametrize(
    ("n_matched", "n_common", "n_union", "match"),
    [
        (4, 3, 9, "got 4, 3, 9"),
        (1, 5, 4, "got 1, 5, 4"),
        (0, 0, 0, "got 0, 0, 0"),
        (-1, 2, 3, "got -1, 2, 3"),
    ],
)
def test_verify_match_encoding_rejects_impossible_counts(
    n_matched: int, n_common: int, n_union: int, match: str
) -> None:
    with pytest.raises(WireError, match=match):
        verify_match_to_proto(17, n_matched, n_common, n_union)


def test_verify_match_encoding_rejects_a_pair_count_other_than_n_matched() -> None:
    with pytest.raises(WireError, match="2 object pairs for 3 matched objects"):
        verify_match_to_proto(17, 3, 4, 9, pairs=np.array([[0, 1], [1, 0]]))


@pytest.mark.parametrize(
    ("n_matched", "n_common", "n_union"),
    [(0, 0, 5), (0, 0, 0), (3, 2, 9), (1, 6, 5)],
)
def test_match_scores_rejects_counts_that_no_verifier_sends(
    n_matched: int, n_common: int, n_union: int
) -> None:
    msg = pb.VerifyMatch(frame_index=17, n_matched=n_matched, n_common=n_common, n_union=n_union)
    with pytest.raises(WireError, match="match of frame 17 has inconsistent counts"):
        match_scores(msg)


@pytest.mark.parametrize(
    ("flat", "n_matched", "match"),
    [
        ([0, 1, 2], 1, "expected an even number"),
        ([0, 1, 2, 3], 3, "2 pairs but n_matched=3"),
        ([0, 1, 6, 3], 2, "pair 1 names query object 6 of a 6-object query"),
        ([0, 1, 0, 3], 2, "a query object appears in more than one pair"),
        ([0, 1, 2, 1], 2, "a matched object appears in more than one pair"),
    ],
)
def test_matched_pairs_decoding_rejects_what_no_association_gives(
    flat: list[int], n_matched: int, match: str
) -> None:
    msg = pb.VerifyMatch(n_matched=n_matched, object_pairs=flat)
    with pytest.raises(WireError, match=match):
        matched_pairs_from_proto(msg, n_query=6)


def test_verify_request_tells_an_unset_distance_threshold_from_zero() -> None:
    query = constellation_to_proto(typical_constellation(), robot=3, frame=1234)
    unset = decode(encode(pb.VerifyRequest(query=query)), pb.VerifyRequest)
    zero = decode(encode(pb.VerifyRequest(query=query, distance_threshold_m=0.0)), pb.VerifyRequest)
    assert not unset.HasField("distance_threshold_m")
    assert zero.HasField("distance_threshold_m")


# --- bytes --------------------------------------------------------------------


def test_decode_rejects_a_truncated_constellation() -> None:
    data = encode(constellation_to_proto(typical_constellation(), robot=3, frame=1234))
    # Cut inside the packed coordinates, whose length prefix then overruns.
    with pytest.raises(WireError, match=r"bytes do not decode as swarmrec\.v1\.Constellation"):
        decode(data[:-5], pb.Constellation)


@pytest.mark.parametrize(
    "garbage",
    [
        b"\x0f",  # field 1 with wire type 7, which does not exist
        b"\x08" + b"\xff" * 10 + b"\x01",  # a varint longer than 10 bytes
        b"\x22\x05\x01",  # field 4 claims 5 bytes, 1 follows
        b"\x00",  # field number 0 is invalid
    ],
)
def test_decode_rejects_garbage_bytes(garbage: bytes) -> None:
    with pytest.raises(WireError, match="do not decode"):
        decode(garbage, pb.Constellation)


def test_decode_rejects_invalid_utf8_in_a_string_field() -> None:
    frame_id_field = b"\x2a\x02\xc3\x28"  # field 5, length 2, not UTF-8
    with pytest.raises(WireError, match="do not decode"):
        decode(frame_id_field, pb.Constellation)


def test_decode_rejects_an_oversize_payload_before_parsing() -> None:
    with pytest.raises(WireError, match="message of 101 bytes exceeds the limit of 100"):
        decode(b"\xff" * 101, pb.Constellation, max_size=100)


def test_encode_rejects_a_message_over_max_size() -> None:
    msg = constellation_to_proto(typical_constellation(), robot=3, frame=1234)
    size = len(encode(msg))
    assert encode(msg, max_size=size) == encode(msg)
    with pytest.raises(WireError, match=f"message of {size} bytes exceeds the limit of {size - 1}"):
        encode(msg, max_size=size - 1)


def test_schema_name_is_the_full_message_name() -> None:
    assert schema_name(pb.Constellation) == "swarmrec.v1.Constellation"
    assert schema_name(pb.ErrorReply(code=pb.ErrorCode.ERROR_CODE_MALFORMED)) == ("swarmrec.v1.ErrorReply")
    with pytest.raises(TypeError, match="not a protobuf message"):
        schema_name(Constellation)


def test_message_class_maps_every_schema_name_back_to_its_class() -> None:
    for name, cls in pb.MESSAGE_TYPES.items():
        assert message_class(name) is cls
        assert schema_name(cls) == name
    with pytest.raises(WireError, match=r"unknown message schema 'swarmrec\.v2\.Constellation'"):
        message_class("swarmrec.v2.Constellation")


def test_error_reply_cuts_a_long_message() -> None:
    reply = error_reply(pb.ErrorCode.ERROR_CODE_INVALID_ARGUMENT, "x" * 10_000)
    assert reply.code == pb.ErrorCode.ERROR_CODE_INVALID_ARGUMENT
    assert len(reply.message) == MAX_ERROR_MESSAGE_CHARS


def test_messages_pickle_for_multiprocessing() -> None:
    msg = constellation_to_proto(typical_constellation(), robot=3, frame=1234)
    assert pickle.loads(pickle.dumps(msg)) == msg


@pytest.mark.parametrize("module", [swarmrec.wire, pb])
def test_every_name_in_dunder_all_exists(module: object) -> None:
    names = module.__all__  # type: ignore[attr-defined]
    assert names, "empty __all__"
    assert sorted(names) == sorted(set(names)), "duplicate names in __all__"
    missing = [name for name in names if not hasattr(module, name)]
    assert missing == []


# --- required fields, other messages' bytes, frame bounds ----------------------------


def test_an_empty_payload_lacks_the_fields_a_store_requires() -> None:
    empty = pb.Constellation.FromString(b"")
    with pytest.raises(MissingFieldError, match="Constellation has no robot_id") as e:
        check_fields(empty, "robot_id", "frame_index")
    assert (e.value.field, e.value.code) == ("robot_id", ErrorCode.INVALID_ARGUMENT)
    # Robot 0's frame 0 sent on purpose carries both, zeros included (2 bytes each).
    frame0 = pb.Constellation.FromString(
        constellation_to_proto(typical_constellation(), 0, 0).SerializeToString()
    )
    check_fields(frame0, "robot_id", "frame_index")
    assert pb.Constellation(robot_id=0, frame_index=0).ByteSize() == 4


def test_a_required_field_of_a_field_is_named_with_its_path() -> None:
    with pytest.raises(MissingFieldError, match="VerifyRequest has no query;"):
        check_fields(pb.VerifyRequest(), "query", "query.frame_index")
    with pytest.raises(MissingFieldError, match=r"has no query\.frame_index"):
        check_fields(pb.VerifyRequest(query=pb.Constellation(robot_id=1)), "query", "query.frame_index")


@pytest.mark.parametrize(
    ("sent", "as_cls"),
    [
        (pb.StepRequest(step=1), pb.LoopClosuresRequest),  # a varint where a float belongs
        (pb.LoopClosuresRequest(min_score=0.5), pb.StepRequest),  # a fixed32 where a varint belongs
        (pb.ReplayReply(robot_id=1, n_frames=9), pb.StepRequest),  # a field number StepRequest lacks
    ],
)
def test_another_messages_bytes_that_parse_are_refused_as_malformed(sent: Any, as_cls: Any) -> None:
    parsed = as_cls.FromString(sent.SerializeToString())  # protobuf accepts them
    with pytest.raises(MalformedMessageError, match="fields its schema does not have") as e:
        check_fields(parsed)
    assert e.value.code == ErrorCode.MALFORMED


def test_unknown_fields_inside_a_field_are_found_too() -> None:
    inner = pb.Constellation(robot_id=1, frame_index=2).SerializeToString()
    req = pb.VerifyRequest(
        query=pb.Constellation.FromString(inner + b"\x38\x05")
    )  # field 7: not in Constellation
    with pytest.raises(MalformedMessageError, match=r"VerifyRequest\.query holds fields"):
        check_fields(req, "query")


def test_a_frame_over_its_bounds_is_refused_before_it_is_converted() -> None:
    limits = FrameLimits(max_objects=4, max_per_label=2)
    msg = pb.Constellation(robot_id=0, frame_index=1, labels=[1, 2, 3, 4, 5], positions_mm=[0] * 15)
    with pytest.raises(
        LimitExceededError,
        match=r"objects in the frame: 5, more than the limit of 4 \(setting max_objects_per_frame\)",
    ) as e:
        constellation_from_proto(msg, N_LABELS, limits)
    assert (e.value.value, e.value.limit, e.value.code) == (5, 4, ErrorCode.TOO_LARGE)
    same = pb.Constellation(robot_id=0, frame_index=1, labels=[7, 1, 7, 7], positions_mm=[0] * 12)
    with pytest.raises(
        LimitExceededError, match="objects of label 7 in the frame: 3, more than the limit of 2"
    ):
        constellation_from_proto(same, N_LABELS, limits)
    ok = pb.Constellation(robot_id=0, frame_index=1, labels=[7, 1, 7, 2], positions_mm=[0] * 12)
    assert len(constellation_from_proto(ok, N_LABELS, limits)) == 4
    # A frame's bounds apply to a shard's slice of it too (label 40 + 2 = 42).
    part = partial_descriptor_to_proto(
        np.eye(1, N_LABELS, 42, dtype=np.int64)[0] * 3, 40, 80, robot=0, frame=1, query_step=0
    )
    with pytest.raises(LimitExceededError, match="objects of label 42"):
        partial_descriptor_from_proto(part, N_LABELS, limits)


def test_refusing_a_frame_of_100000_objects_takes_no_time() -> None:
    import time

    n = 100_000
    msg = pb.Constellation.FromString(
        pb.Constellation(
            robot_id=0, frame_index=1, labels=[1] * n, positions_mm=[5] * (3 * n)
        ).SerializeToString()
    )
    t0 = time.perf_counter()
    with pytest.raises(LimitExceededError):
        constellation_from_proto(msg, N_LABELS, FrameLimits(300, 100))
    assert time.perf_counter() - t0 < 0.01
