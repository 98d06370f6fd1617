"""The published evaluation scripts' own output on the real TUM constellations, as
per-row digests of each dense score matrix (tests/fixtures/published_scores_tum_fr3.json,
its "about" says how they were made), and the helper that compares a matrix with them."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import numpy.typing as npt

FIXTURE = Path(__file__).parent / "fixtures" / "published_scores_tum_fr3.json"
PUBLISHED = json.loads(FIXTURE.read_text())["matrices"]


def row_digests(dense: npt.NDArray[np.float64]) -> list[str]:
    return [hashlib.sha256(np.ascontiguousarray(r, "<f8").tobytes()).hexdigest()[:16] for r in dense]


def rows_differing(name: str, dense: npt.NDArray[np.float64]) -> list[int]:
    """The rows of ``dense`` that differ from the published matrix ``name`` (empty: identical)."""
    expected = PUBLISHED[name]
    return [i for i, (a, b) in enumerate(zip(row_digests(dense), expected["rows"], strict=True)) if a != b]


def positive_entries(name: str) -> int:
    return int(PUBLISHED[name]["positive_entries"])
