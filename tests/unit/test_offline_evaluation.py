"""The offline evaluation's main() on real files, as the CLI runs it."""

from __future__ import annotations

import json
from pathlib import Path

from swarmrec.cli import main as cli
from swarmrec.evaluation.offline import EvaluationSettings, main
from swarmrec.synthetic import OfficeConfig, generate_office, write_dataset


def test_a_written_synthetic_dataset_evaluates_with_its_own_ground_truth(tmp_path: Path) -> None:
    ds = generate_office(OfficeConfig(n_frames=400))
    write_dataset(ds, tmp_path / "office")
    from_files = main(
        EvaluationSettings(dataset=str(tmp_path / "office"), out=tmp_path / "a", plots=False, progress=False)
    )
    in_memory = main(EvaluationSettings(frames=400, out=tmp_path / "b", plots=False, progress=False))
    assert from_files.dataset.groundtruth is True
    # Same frames, same poses: the same AUCs whether read from disk or generated.
    for mode in ("centralized", "decentralized_10"):
        assert from_files.results[mode].auc == in_memory.results[mode].auc
        assert from_files.results[mode].auc is not None


def test_the_cli_writes_the_documented_files(tmp_path: Path) -> None:
    assert cli(["evaluate", "--frames", "300", "--robots", "3", "--out", str(tmp_path), "--quiet"]) == 0
    names = {p.name for p in tmp_path.iterdir()}
    assert {"summary.json", "precision_recall.png", "holder_load.png"} <= names
    for mode in ("centralized", "decentralized_3"):
        assert {f"scores_{mode}.npz", f"best_matches_{mode}.csv", f"similarity_{mode}.png"} <= names
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["bandwidth"]["holder_load"]["balance_ratio"] >= 1.0


def test_a_bad_dataset_path_is_a_clear_cli_error(tmp_path: Path, capsys) -> None:  # type: ignore[no-untyped-def]
    assert cli(["evaluate", "--dataset", str(tmp_path / "missing"), "--out", str(tmp_path), "--quiet"]) == 2
    assert "no such file or folder" in capsys.readouterr().err
