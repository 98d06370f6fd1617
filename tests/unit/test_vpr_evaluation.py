"""The offline evaluation end to end on a tiny setting (the committed model, a 300-frame
deployment): what it writes is complete, and a run's load and assignment can be re-derived
from the written centres, table and descriptors alone."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from swarmrec.errors import ConfigError
from swarmrec.vpr.clusters import Assignment, Router
from swarmrec.vpr.evaluation import EvaluationSettings, EvaluationSummary, main

pytestmark = pytest.mark.slow  # renders ~900 frames: about 15 s alone, a minute on a busy machine

TINY = {
    "deployment_frames": 300,
    "other_worlds": 1,
    "robots": (2, 3),
    "fig7_robots": 3,
    "clusters_per_robot": (1, 2),
    "runs": 2,
    "balance_clusters_per_robot": 2,
    "pq_bytes": (16,),
    "threads": 2,
}


@pytest.fixture(scope="module")
def evaluated(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, EvaluationSummary]:
    out = tmp_path_factory.mktemp("vpr-eval")
    return out, main(EvaluationSettings(out=out, **TINY))  # type: ignore[arg-type]


def test_every_file_is_written(evaluated: tuple[Path, EvaluationSummary]) -> None:
    out, summary = evaluated
    for name in ("descriptors.npz", "runs.npz", "runs.json", "summary.json", "fig6.png", "fig7.png"):
        assert (out / name).stat().st_size > 0, name
    with np.load(out / "descriptors.npz") as data:
        assert data["deployment"].shape == (300, 128) and data["frames"].tolist() == list(range(300))
        np.testing.assert_allclose(np.linalg.norm(data["deployment"], axis=1), 1.0, atol=1e-4)
        assert data["other"].shape == (625, 128) and data["other_worlds"].tolist() == [14_000]
    saved = json.loads((out / "summary.json").read_text())
    assert [row["n_robots"] for row in saved["fig6"]] == [2, 3]
    assert [row["clusters_per_robot"] for row in saved["fig7"]] == [1, 2]
    assert [row["code"] for row in saved["quantisation"]] == ["float32", "int8", "pq16"]
    assert [row["query_bytes"] for row in saved["quantisation"]] == [517, 137, 21]
    assert len(summary.runs) == 2 * 2 + 2 * 2 + 2  # fig6, fig7, balance


def test_each_run_can_be_rechecked_from_the_files(evaluated: tuple[Path, EvaluationSummary]) -> None:
    out, _ = evaluated
    runs: list[dict[str, Any]] = json.loads((out / "runs.json").read_text())
    with np.load(out / "descriptors.npz") as data:
        x = data["deployment"]
    with np.load(out / "runs.npz") as centres:
        for run in runs:
            assert sum(run["load"]) == 300
            assert run["relative_auc"] == pytest.approx(run["auc"] / run["centralized_auc"])
            table = Assignment.from_json(run["assignment"])
            if run["experiment"] != "balance":
                # The paper's assignment: exactly c clusters per robot; routing the written
                # descriptors with the written centres and table gives the written load.
                assert table.clusters_per_robot().tolist() == [run["clusters_per_robot"]] * run["n_robots"]
                _, owners = Router(centres[run["name"]], table).route_many(x)
                assert np.bincount(owners, minlength=run["n_robots"]).tolist() == run["load"]
                expected = max(run["load"]) * run["n_robots"] / 300
                assert run["worst_balance_ratio"] == pytest.approx(expected)
            else:
                assert len(centres[run["name"]]) == table.n_clusters


def test_bad_settings_are_refused(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="robots must be counts >= 2"):
        EvaluationSettings(out=tmp_path, robots=(1, 2))
    with pytest.raises(ConfigError, match="rebalance_share"):
        EvaluationSettings(out=tmp_path, rebalance_share=1.0)
    with pytest.raises(ConfigError, match="pq_bytes must divide 128"):
        EvaluationSettings(out=tmp_path, pq_bytes=(24,))
    with pytest.raises(ConfigError, match="copy_neighbours"):
        EvaluationSettings(out=tmp_path, copy_neighbours=0)


def test_the_printed_summary_heads_each_table_and_shows_rebalancing_and_codes(
    evaluated: tuple[Path, EvaluationSummary], capsys: pytest.CaptureFixture[str]
) -> None:
    from swarmrec.cli.vpr import print_evaluation

    out, summary = evaluated
    print_evaluation(summary, EvaluationSettings(out=out, **TINY))  # type: ignore[arg-type]
    lines = capsys.readouterr().out.splitlines()

    headings = [line for line in lines if not line.startswith("  ")]
    assert len(headings) == 6 and headings[5].startswith(f"written to {out}/")
    assert headings[1] == "Fig. 6: one k-means cluster per robot"
    assert headings[2] == "Fig. 7: 3 robots, c clusters per robot"
    assert headings[3].startswith("re-balancing (3 robots, 2 clusters each to start")
    assert headings[4].startswith("descriptor codes")
    fig6 = summary.fig6[0]
    assert f"{2:>8} {fig6['relative_auc_mean']:>13.3f}" in lines[lines.index(headings[1]) + 2]
    codes = [line.split()[0] for line in lines[lines.index(headings[4]) + 2 :] if line.startswith("  ")]
    assert codes == ["float32", "int8", "pq16"]
