"""Smaller descriptors for the wire: int8 with a per-vector scale, or product quantisation.

The paper sends the 128 float32 of a query, 512 B. Both codes here are decoded by the owner,
which stores and searches the decoded vector, so query and database are both quantised
(symmetric); the router still uses the robot's own float descriptor, which never leaves it.

* :class:`Int8Quantizer` (``4 + d`` B, 132 B for d = 128): a float32 scale
  ``s = max_i |x_i| / 127`` and ``q_i = round(x_i / s)`` in int8. Every component comes
  back within ``s / 2`` (rounding to the nearest step), up to float32 rounding of the
  product; no training, any descriptor.
* :class:`PQQuantizer` (``m`` B): faiss's product quantiser, ``m`` sub-vectors of
  ``d / m`` components, each replaced by the nearest of 256 centres trained on other
  data (:meth:`PQQuantizer.train`); the codebook ships with the model like the k-means centres.

Wire layout (:meth:`encode` returns one ``uint8`` row per descriptor): int8: the scale as
little-endian float32, then the d signed bytes; PQ: the m code bytes.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Protocol

import faiss
import numpy as np
import numpy.typing as npt

from swarmrec.errors import ConfigError
from swarmrec.vpr.errors import DescriptorError, StateFileError
from swarmrec.vpr.vectors import as_descriptors

__all__ = ["PQ_FORMAT", "Int8Quantizer", "PQQuantizer", "Quantizer"]

Float32Array = npt.NDArray[np.float32]
CodeArray = npt.NDArray[np.uint8]

PQ_FORMAT = "swarmrec.vpr.pq/1"
_SCALE_BYTES = 4


class Quantizer(Protocol):
    """Encodes descriptors ``(N, d)`` into ``code_bytes`` bytes each and back."""

    dimension: int

    @property
    def code_bytes(self) -> int: ...

    def encode(self, descriptors: npt.NDArray[np.floating]) -> CodeArray: ...

    def decode(self, codes: CodeArray) -> Float32Array: ...


def _check_codes(codes: object, width: int) -> CodeArray:
    if not isinstance(codes, np.ndarray) or codes.dtype != np.uint8:
        raise DescriptorError("codes must be a uint8 array")
    batch = codes[None] if codes.ndim == 1 else codes
    if batch.ndim != 2 or batch.shape[1] != width:
        raise DescriptorError(f"expected codes of {width} bytes, got an array of shape {codes.shape}")
    return np.ascontiguousarray(batch)


class Int8Quantizer:
    """Signed bytes with one float32 scale per vector (see the module docstring)."""

    def __init__(self, dimension: int) -> None:
        if dimension < 1:
            raise ConfigError(f"dimension must be >= 1, got {dimension}")
        self.dimension = dimension

    @property
    def code_bytes(self) -> int:
        return _SCALE_BYTES + self.dimension

    def encode(self, descriptors: npt.NDArray[np.floating]) -> CodeArray:
        x = as_descriptors(descriptors, self.dimension)
        peak = np.abs(x).max(axis=1)
        # A zero vector keeps scale 0 and decodes to zeros exactly.
        scale = (peak / np.float32(127.0)).astype(np.float32)
        safe = np.where(scale > 0, scale, np.float32(1.0))
        q = np.clip(np.rint(x / safe[:, None]), -127, 127).astype(np.int8)
        out = np.empty((len(x), self.code_bytes), np.uint8)
        out[:, :_SCALE_BYTES] = scale.astype("<f4").view(np.uint8).reshape(len(x), _SCALE_BYTES)
        out[:, _SCALE_BYTES:] = q.view(np.uint8)
        return out

    def decode(self, codes: CodeArray) -> Float32Array:
        c = _check_codes(codes, self.code_bytes)
        scale = np.ascontiguousarray(c[:, :_SCALE_BYTES]).view("<f4").reshape(len(c)).astype(np.float32)
        if not np.isfinite(scale).all() or (scale < 0).any():
            raise DescriptorError("an int8 code with a negative or non-finite scale")
        q = np.ascontiguousarray(c[:, _SCALE_BYTES:]).view(np.int8).astype(np.float32)
        decoded: Float32Array = q * scale[:, None]
        return decoded


class PQQuantizer:
    """faiss's product quantiser: ``m`` bytes per descriptor (8 bits per sub-vector)."""

    def __init__(self, dimension: int, m: int) -> None:
        if dimension < 1 or m < 1 or dimension % m:
            raise ConfigError(f"m must divide the dimension, got dimension {dimension}, m {m}")
        self.dimension, self.m = dimension, m
        # Any: faiss's stubs give the C++ signatures (decode(code, x) -> None), not the numpy
        # wrappers the Python module installs (decode(codes) -> array).
        self._pq: Any = faiss.ProductQuantizer(dimension, m, 8)
        self.trained = False

    @property
    def code_bytes(self) -> int:
        return int(self._pq.code_size)

    def train(self, descriptors: npt.NDArray[np.floating], seed: int = 0) -> PQQuantizer:
        """Train the 256 centres of each sub-vector on ``descriptors`` (other data than a mission's)."""
        x = as_descriptors(descriptors, self.dimension)
        if len(x) < 256:
            raise ConfigError(f"product quantisation needs at least 256 training descriptors, got {len(x)}")
        self._pq.cp.seed = int(seed)
        # faiss warns below 39 points per centre; a few thousand descriptors train 256 centres well.
        self._pq.cp.min_points_per_centroid = 1
        self._pq.train(x)
        self.trained = True
        return self

    def _require_trained(self) -> None:
        if not self.trained:
            raise ConfigError("the product quantiser is not trained: call train() or load()")

    def encode(self, descriptors: npt.NDArray[np.floating]) -> CodeArray:
        self._require_trained()
        codes: CodeArray = self._pq.compute_codes(as_descriptors(descriptors, self.dimension))
        return codes

    def decode(self, codes: CodeArray) -> Float32Array:
        self._require_trained()
        decoded: Float32Array = self._pq.decode(_check_codes(codes, self.code_bytes))
        return decoded

    def save(self, path: str | Path) -> None:
        self._require_trained()
        path = Path(path)
        meta = json.dumps({"format": PQ_FORMAT, "dimension": self.dimension, "m": self.m})
        tmp = path.with_name(path.name + ".tmp.npz")
        np.savez(tmp, centroids=faiss.vector_to_array(self._pq.centroids), meta=np.array(meta))
        os.replace(tmp, path)

    @classmethod
    def load(cls, path: str | Path) -> PQQuantizer:
        try:
            with np.load(path, allow_pickle=False) as data:
                meta = json.loads(str(data["meta"]))
                centroids = np.asarray(data["centroids"], np.float32)
        except (OSError, KeyError, ValueError) as exc:
            raise StateFileError(path, f"not a saved product quantiser: {exc}") from exc
        if not isinstance(meta, dict) or meta.get("format") != PQ_FORMAT:
            raise StateFileError(path, f"not a saved product quantiser (expected format {PQ_FORMAT!r})")
        pq = cls(int(meta["dimension"]), int(meta["m"]))
        if centroids.size != pq._pq.centroids.size():
            raise StateFileError(
                path, f"{centroids.size} codebook values, expected {pq._pq.centroids.size()}"
            )
        faiss.copy_array_to_vector(centroids.ravel(), pq._pq.centroids)
        pq.trained = True
        return pq
