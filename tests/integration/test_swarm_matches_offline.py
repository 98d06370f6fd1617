"""The main job with real processes: a lock-step swarm's pair scores equal
the offline decentralized evaluation, on the synthetic world and the real
TUM constellations, and the report carries measured bytes and load."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from swarmrec.core.presets import get_preset
from swarmrec.datasets.constellations import read_constellations
from swarmrec.datasets.labels import COCO_NAMES
from swarmrec.deployments.local import LocalDeployment
from swarmrec.evaluation.bandwidth import holder_load
from swarmrec.evaluation.scoring import score_decentralized
from swarmrec.evaluation.source import DatasetSource
from swarmrec.experiments.places import PlacesSettings, main
from swarmrec.experiments.places.pipeline import as_on_the_wire
from swarmrec.runtime.settings import DataPlane
from swarmrec.services.settings import IndexSettings
from tests.published import rows_differing


def _positive_pairs(lo: np.ndarray, hi: np.ndarray, scores: np.ndarray) -> dict[tuple[int, int], float]:
    keep = scores > 0
    return {(int(i), int(j)): float(s) for i, j, s in zip(lo[keep], hi[keep], scores[keep], strict=True)}


def _swarm_pairs(out: Path) -> dict[tuple[int, int], float]:
    rows = (out / "pairs.csv").read_text().splitlines()[1:]
    return {(int(r.split(",")[0]), int(r.split(",")[1])): float(r.split(",")[-1]) for r in rows}


@pytest.mark.slow
@pytest.mark.parametrize("data_plane", ["python", "compiled"])
def test_synthetic_swarm_of_four_scores_every_pair_as_the_offline_evaluation(
    tmp_path: Path, data_plane: DataPlane
) -> None:
    settings = PlacesSettings(
        source=DatasetSource(frames=600),
        robots=4,
        out=tmp_path / "run",
        progress=False,
        plots=True,
        data_plane=data_plane,
    )
    summary = main(settings, LocalDeployment.for_run(settings.out))

    # Positions travel in millimetres: the offline evaluation of the frames as they travel.
    seq = as_on_the_wire(read_constellations(tmp_path / "run" / "dataset", COCO_NAMES))
    offline = score_decentralized(seq, 4, get_preset("paper"))
    expected = _positive_pairs(offline.matrix.pairs_i, offline.matrix.pairs_j, offline.matrix.scores)
    got = _swarm_pairs(tmp_path / "run")
    assert len(expected) > 100  # the comparison is about something
    assert got == expected
    assert summary.offline_check is not None and summary.offline_check.identical is True
    # The run's certificates stay in its folder, its CA's private key does not.
    assert list((tmp_path / "run").rglob("ca.pem")) and not list((tmp_path / "run").rglob("ca.key"))
    # Two replicas a group (the default): every partial query the offline run counts was
    # answered by one of its group's two owners.
    assert sum(summary.shard_load.partial_queries) == sum(holder_load(offline).partial_queries)
    assert summary.shard_load.scraped == summary.shard_load.partial_queries  # nobody restarted
    assert summary.queries.missing_slots == 0 and not summary.queries.errors
    assert 0 < summary.bytes.per_query < 1000
    assert {"PartialQuery", "CandidatesReply", "VerifyRequest", "VerifyReply"} <= set(
        summary.bytes.per_query_by_message
    )
    assert summary.bytes.replication_per_query > 0  # the second replica of each slice
    assert summary.auc is not None and summary.auc > 0.3
    # What millimetres cost, measured offline on the same frames, is in the report.
    assert summary.positions_effect is not None and summary.swarm.wire_positions == "mm"
    assert abs(summary.positions_effect.auc_offline_exact_positions - summary.auc) < 0.01
    assert all(code == 0 for code in summary.exit_codes.values()), summary.exit_codes
    for name in (
        "summary.json",
        "similarity.png",
        "precision_recall.png",
        "shard_load.png",
        "bytes_per_query.png",
        "closures_map.png",  # the synthetic world's camera poses are known
        "loop_closures.csv",
    ):
        assert (tmp_path / "run" / name).stat().st_size > 0
    assert json.loads((tmp_path / "run" / "summary.json").read_text())["auc"] == summary.auc


@pytest.mark.slow
@pytest.mark.parametrize("data_plane", ["python", "compiled"])
def test_tum_swarm_of_ten_scores_every_pair_as_the_offline_evaluation(
    tmp_path: Path, tum_zip: Path, data_plane: DataPlane
) -> None:
    settings = PlacesSettings(
        data_plane=data_plane,
        source=DatasetSource(str(tum_zip)),
        robots=10,
        out=tmp_path / "run",
        progress=False,
        plots=False,
        check_offline=False,
        wire_positions="exact",
        # One replica a group and no rebalancing: the paper's layout, whose load the published
        # figure measures (rebalancing would add replicas of the hot groups and lower it).
        index=IndexSettings(replicas=1, rebalance_target=1000.0),
    )
    summary = main(settings, LocalDeployment.for_run(settings.out))

    seq = read_constellations(tum_zip, COCO_NAMES)
    offline = score_decentralized(seq, 10, get_preset("paper"))
    expected = _positive_pairs(offline.matrix.pairs_i, offline.matrix.pairs_j, offline.matrix.scores)
    assert len(expected) > 5000
    got = _swarm_pairs(tmp_path / "run")
    assert got == expected
    # The live swarm's scores are the published scripts' own, row for row.
    dense = np.zeros((len(seq), len(seq)))
    for (i, j), score in got.items():
        dense[i, j] = dense[j, i] = score
    marked = offline.matrix.dense()  # the scripts mark ignored frames -2; the swarm never sees them
    dense[marked < 0] = marked[marked < 0]
    assert rows_differing("decentralized_10", dense) == []
    # The published load imbalance of even label ranges on this data, now measured.
    assert summary.shard_load.balance_ratio == pytest.approx(2.67, abs=0.005)
    assert summary.swarm.wire_positions == "exact"
