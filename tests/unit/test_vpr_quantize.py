"""Descriptor codes for the wire: int8 error bound by hand, PQ exactness on few points, bad codes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from swarmrec.errors import ConfigError
from swarmrec.vpr.errors import DescriptorError, StateFileError
from swarmrec.vpr.quantize import Int8Quantizer, PQQuantizer


def test_int8_codes_a_vector_as_worked_out_by_hand() -> None:
    q = Int8Quantizer(4)
    assert q.code_bytes == 8  # a float32 scale and 4 signed bytes
    code = q.encode(np.array([0.5, -0.25, 0.1, 0.0]))
    step = np.float32(0.5) / np.float32(127.0)  # the largest component maps to 127
    assert code[0, :4].view("<f4")[0] == pytest.approx(step, rel=1e-7)
    # 0.5 / step = 127; -0.25 / step = -63.5 -> -64 (half to even); 0.1 / step = 25.4 -> 25.
    assert code[0, 4:].view(np.int8).tolist() == [127, -64, 25, 0]
    np.testing.assert_allclose(q.decode(code)[0], np.array([127, -64, 25, 0]) * step, rtol=1e-6)


def test_int8_keeps_every_component_within_half_a_step() -> None:
    rng = np.random.default_rng(0)
    x = rng.normal(size=(500, 128)).astype(np.float32)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    q = Int8Quantizer(128)
    assert q.code_bytes == 132
    error = np.abs(q.decode(q.encode(x)) - x)
    half_step = np.abs(x).max(axis=1, keepdims=True) / 127 / 2
    assert (error <= half_step * (1 + 1e-5)).all()
    np.testing.assert_array_equal(q.decode(q.encode(np.zeros((1, 128)))), np.zeros((1, 128)))


def test_bad_codes_and_descriptors_are_refused() -> None:
    q = Int8Quantizer(4)
    with pytest.raises(DescriptorError, match="8 bytes"):
        q.decode(np.zeros((1, 7), np.uint8))
    with pytest.raises(DescriptorError, match="uint8"):
        q.decode(np.zeros((1, 8), np.int64))  # type: ignore[arg-type]
    negative = q.encode(np.array([1.0, 0, 0, 0]))
    negative[0, :4] = np.array([-1.0], "<f4").view(np.uint8)
    with pytest.raises(DescriptorError, match="negative or non-finite scale"):
        q.decode(negative)
    with pytest.raises(DescriptorError, match="length 4"):
        q.encode(np.zeros((2, 5)))
    with pytest.raises(DescriptorError, match="NaN or inf"):
        q.encode(np.array([np.inf, 0, 0, 0]))


def test_product_quantisation_is_exact_when_each_subvector_takes_few_values(tmp_path: Path) -> None:
    # Four distinct descriptors repeated: each sub-quantiser has 256 centres for 4 distinct points.
    rng = np.random.default_rng(2)
    base = rng.normal(size=(4, 16)).astype(np.float32)
    x = np.repeat(base, 100, axis=0)
    pq = PQQuantizer(16, 4)
    with pytest.raises(ConfigError, match="not trained"):
        pq.encode(x)
    pq.train(x, seed=0)
    assert pq.code_bytes == 4
    codes = pq.encode(base)
    assert codes.shape == (4, 4) and codes.dtype == np.uint8
    np.testing.assert_allclose(pq.decode(codes), base, atol=1e-5)
    pq.save(tmp_path / "pq.npz")
    again = PQQuantizer.load(tmp_path / "pq.npz")
    np.testing.assert_array_equal(again.encode(base), codes)
    (tmp_path / "junk.npz").write_bytes(b"junk")
    with pytest.raises(StateFileError, match="not a saved product quantiser"):
        PQQuantizer.load(tmp_path / "junk.npz")


def test_product_quantisation_settings_are_checked() -> None:
    with pytest.raises(ConfigError, match="m must divide"):
        PQQuantizer(128, 24)
    with pytest.raises(ConfigError, match="at least 256"):
        PQQuantizer(8, 2).train(np.zeros((100, 8), np.float32))
