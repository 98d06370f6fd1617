"""Full-image descriptors on the wire: sizes, round trips, and what a receiver refuses."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from swarmrec.errors import ConfigError, WireError
from swarmrec.wire import messages as pb
from swarmrec.wire.vpr import descriptor_from_wire, descriptor_to_wire, encoding_name, encoding_of

D = 128


def _unit(seed: int) -> np.ndarray:
    v = np.random.default_rng(seed).normal(size=D).astype(np.float32)
    return v / np.linalg.norm(v)


def test_float32_is_4d_bytes_little_endian_and_comes_back_bit_for_bit() -> None:
    x = _unit(0)
    data, encoding = descriptor_to_wire(x, "float32")
    assert encoding == pb.DescriptorEncoding.DESCRIPTOR_ENCODING_FLOAT32
    assert len(data) == 512
    assert struct.unpack("<f", data[:4])[0] == x[0]
    np.testing.assert_array_equal(descriptor_from_wire(data, encoding, D), x)


def test_int8_is_a_scale_and_d_bytes_within_half_a_step_of_the_descriptor() -> None:
    x = _unit(1)
    data, encoding = descriptor_to_wire(x, "int8")
    assert encoding == pb.DescriptorEncoding.DESCRIPTOR_ENCODING_INT8
    assert len(data) == 132
    scale = struct.unpack("<f", data[:4])[0]
    assert scale == pytest.approx(np.abs(x).max() / 127, rel=1e-6)
    back = descriptor_from_wire(data, encoding, D)
    assert np.abs(back - x).max() <= scale / 2 + 1e-7
    # The bytes after the scale are the rounded components, as signed bytes.
    q = np.frombuffer(data[4:], np.int8)
    assert q.tolist() == np.rint(x / np.float32(scale)).astype(np.int64).tolist()


@pytest.mark.parametrize(
    ("data", "encoding", "message"),
    [
        (b"\x00" * 131, 2, "are 132 bytes, got 131"),
        (b"\x00" * 512, 2, "are 132 bytes, got 512"),
        (b"\x00" * 132, 1, "are 512 bytes, got 132"),
        (b"\x00" * 132, 0, "encoding 0 is not one of"),
        (b"\x00" * 132, 7, "encoding 7 is not one of"),
    ],
)
def test_a_descriptor_of_the_wrong_length_or_encoding_is_refused(
    data: bytes, encoding: int, message: str
) -> None:
    with pytest.raises(WireError, match=message):
        descriptor_from_wire(data, encoding, D)


def test_nan_inf_a_negative_scale_or_a_vector_that_is_not_unit_are_refused() -> None:
    x = _unit(2)
    nan = x.copy()
    nan[5] = np.nan
    with pytest.raises(WireError, match="NaN or inf"):
        descriptor_from_wire(nan.astype("<f4").tobytes(), 1, D)
    inf = x.copy()
    inf[0] = np.inf
    with pytest.raises(WireError, match="NaN or inf"):
        descriptor_from_wire(inf.astype("<f4").tobytes(), 1, D)
    code, _ = descriptor_to_wire(x, "int8")
    with pytest.raises(WireError, match="non-finite scale"):
        descriptor_from_wire(struct.pack("<f", float("nan")) + code[4:], 2, D)
    with pytest.raises(WireError, match="negative"):
        descriptor_from_wire(struct.pack("<f", -0.01) + code[4:], 2, D)
    with pytest.raises(WireError, match="L2 norm 0"):
        descriptor_from_wire(bytes(512), 1, D)
    with pytest.raises(WireError, match="L2 norm 2"):
        descriptor_from_wire((2 * x).astype("<f4").tobytes(), 1, D)
    # Ten times the scale: every component ten times too large.
    ten = struct.pack("<f", 10 * struct.unpack("<f", code[:4])[0]) + code[4:]
    with pytest.raises(WireError, match="unit vectors"):
        descriptor_from_wire(ten, 2, D)


def test_encoding_names_map_both_ways_and_an_unknown_name_is_a_config_error() -> None:
    assert encoding_of("int8") == 2 and encoding_of("float32") == 1
    assert encoding_name(2) == "int8" and encoding_name(9) == "unknown(9)"
    with pytest.raises(ConfigError, match="float32, int8"):
        encoding_of("pq32")
