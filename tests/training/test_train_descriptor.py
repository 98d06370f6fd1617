"""The place descriptor's training script (models/descriptor/train.py), run for a few steps in
the training environment (.venv-train, which has torch), and its ONNX export checked here, in
the service environment (onnxruntime, no torch): it loads as a descriptor model, and
onnxruntime's descriptors equal torch's on the same inputs."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort  # type: ignore[import-untyped]  # onnxruntime ships no type hints
import pytest

from swarmrec.vpr.model import DescriptorModel

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]
TRAIN_PYTHON = REPO / ".venv-train" / "bin" / "python"
SCRIPT = REPO / "models" / "descriptor" / "train.py"
SMOKE = [
    "--steps", "3", "--val-every", "2", "--train-worlds", "1", "--val-worlds", "1", "--test-worlds", "1",
    "--world-frames", "400", "--frame-stride", "8", "--workers", "1", "--threads", "2", "--check-arrays",
]  # fmt: skip


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    if not TRAIN_PYTHON.exists():
        pytest.fail(
            f"{TRAIN_PYTHON.relative_to(REPO)} is missing: `make train-env` builds the training environment"
        )
    out = tmp_path_factory.mktemp("descriptor-smoke")
    proc = subprocess.run(
        # --cache too: its setting must survive into metrics.json like every other.
        [str(TRAIN_PYTHON), str(SCRIPT), *SMOKE, "--out", str(out), "--cache", str(out / "cache")],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert proc.returncode == 0, f"train.py failed:\n{proc.stdout[-4000:]}\n{proc.stderr[-4000:]}"
    assert "test recall@1" in proc.stdout
    return out


@pytest.fixture(scope="module")
def metrics(smoke_run: Path) -> dict[str, Any]:
    data: dict[str, Any] = json.loads((smoke_run / "metrics.json").read_text())
    return data


def test_the_smoke_run_writes_a_small_model_and_its_metrics(smoke_run: Path, metrics: dict[str, Any]) -> None:
    assert metrics["steps"] == 3
    assert metrics["model_bytes"] == (smoke_run / "descriptor.onnx").stat().st_size < 5_000_000
    for split in ("test", "baseline"):
        assert 0.0 <= metrics[split]["recall_at_1"] <= metrics[split]["recall_at_5"] <= 1.0
        assert 0.0 <= metrics[split]["auc"] <= 1.0
    worlds = metrics["worlds"]
    assert not set(worlds["train"]) & set(worlds["test"]) and not set(worlds["val"]) & set(worlds["test"])
    assert [h["step"] for h in metrics["history"]] == [2, 3]
    assert metrics["settings"]["cache"] == str(smoke_run / "cache")


def test_the_export_loads_as_a_descriptor_model(smoke_run: Path) -> None:
    model = DescriptorModel(smoke_run / "descriptor.onnx")  # shapes, dynamic batch, unit rows
    assert model.image_hw == (96, 128) and model.dimension == 128


def test_onnxruntime_gives_torchs_descriptors(smoke_run: Path) -> None:
    inputs = np.load(smoke_run / "check_inputs.npy")
    expected = np.load(smoke_run / "check_torch_descriptors.npy")
    assert inputs.dtype == np.float32 and inputs.shape[1:] == (3, 96, 128) and len(inputs) >= 2
    session = ort.InferenceSession(str(smoke_run / "descriptor.onnx"), providers=["CPUExecutionProvider"])
    got = session.run(["descriptor"], {"image": inputs})[0]
    assert got.shape == expected.shape == (len(inputs), 128)
    np.testing.assert_allclose(got, expected, atol=1e-4)
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-5)
    assert not np.allclose(got, got[0]), "every input got the same descriptor: the export lost the image"
