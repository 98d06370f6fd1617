"""The paper preset against the published scripts' own output on the real
TUM constellations, pair by pair (via per-row digests, see the fixture's
"about"). A difference names the first rows that differ."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from swarmrec.core.association import build_table
from swarmrec.core.presets import get_preset
from swarmrec.datasets.constellations import read_constellations
from swarmrec.evaluation.scoring import score_centralized, score_decentralized
from tests.published import positive_entries, rows_differing


def _assert_same(name: str, dense: np.ndarray) -> None:
    assert int((dense > 0).sum()) == positive_entries(name)
    differ = rows_differing(name, dense)
    assert not differ, f"{name}: {len(differ)} rows differ from the published output, first {differ[:10]}"


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
