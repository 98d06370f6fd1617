"""The paper preset against the published scripts' own output on the real
TUM constellations, pair by pair (via per-row digests, see the fixture's
"about"). A difference names the first rows that differ."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from swarmrec.core.association import build_table
from swarmrec.core.presets import get_preset
from swarmrec.datasets.constellations import read_constellations
from swarmrec.evaluation.scoring import score_centralized, score_decentralized

FIXTURE = Path(__file__).parents[1] / "fixtures" / "published_scores_tum_fr3.json"
PUBLISHED = json.loads(FIXTURE.read_text())["matrices"]


def _row_digests(dense: np.ndarray) -> list[str]:
    return [
        hashlib.sha256(np.ascontiguousarray(r, "<f8").tobytes()).hexdigest()[:16] for r in dense
    ]


def _assert_same(name: str, dense: np.ndarray) -> None:
    expected = PUBLISHED[name]
    assert int((dense > 0).sum()) == expected["positive_entries"]
    differ = [
        i
        for i, (a, b) in enumerate(zip(_row_digests(dense), expected["rows"], strict=True))
        if a != b
    ]
    assert not differ, (
        f"{name}: {len(differ)} rows differ from the published output, first {differ[:10]}"
    )


@pytest.fixture(scope="module")
def tum(tum_zip: Path):  # type: ignore[no-untyped-def]
    seq = read_constellations(tum_zip)
    return seq, build_table(seq.constellations, seq.n_labels)


def test_paper_preset_centralized_scores_equal_the_published_ones(tum) -> None:  # type: ignore[no-untyped-def]
    seq, table = tum
    _assert_same("centralized", score_centralized(seq, get_preset("paper"), table=table).dense())


@pytest.mark.parametrize("robots", [3, 4, 10, 20])
def test_paper_preset_decentralized_scores_equal_the_published_ones(tum, robots: int) -> None:  # type: ignore[no-untyped-def]
    seq, table = tum
    run = score_decentralized(seq, robots, get_preset("paper"), table=table)
    _assert_same(f"decentralized_{robots}", run.matrix.dense())
