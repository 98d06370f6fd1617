"""The landmark classifier's training script runs, end to end, in its own torch environment.

``models/landmarks/train.py`` is run as a subprocess with ``.venv-train/bin/python``
(PyPI's torch is the multi-GB CUDA build, kept out of the services' ``.venv``; ``make
test`` builds that environment first, ``make train-env`` alone). A few optimiser steps
on a tiny set must export an ONNX model that this process, which has onnxruntime but
no torch, loads as a landmark classifier, and whose outputs equal the ones torch
computed for the same inputs (saved by the script beside the model).
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import onnxruntime as ort  # type: ignore[import-untyped]  # no type hints
import pytest

from swarmrec.fusion.classifier import LandmarkClassifier

ROOT = Path(__file__).resolve().parents[2]
TRAIN_PYTHON = ROOT / ".venv-train" / "bin" / "python"

pytestmark = pytest.mark.slow


def test_a_few_training_steps_export_an_onnx_model_that_matches_torch(tmp_path: Path) -> None:
    assert TRAIN_PYTHON.is_file(), (
        f"{TRAIN_PYTHON} is missing: `make train-env` builds the training environment"
    )
    out = tmp_path / "model"
    cmd = [
        str(TRAIN_PYTHON),
        str(ROOT / "models" / "landmarks" / "train.py"),
        "--out", str(out),
        "--per-class", "4",
        "--val-per-class", "1",
        "--test-per-class", "2",
        "--epochs", "2",
        "--max-steps", "3",
        "--workers", "1",
        "--threads", "2",
        "--check-arrays",
    ]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600, check=False)
    assert done.returncode == 0, done.stderr[-3000:]

    onnx_path = out / "landmark_cnn.onnx"
    LandmarkClassifier(onnx_path)  # loads it as the services do: shapes, dynamic batch, a softmax
    inputs = np.load(out / "check_inputs.npy")  # the model's float input, [N, 3, 64, 64] in 0..1
    expected = np.load(out / "check_torch_probabilities.npy")
    assert inputs.dtype == np.float32 and inputs.shape[1:] == (3, 64, 64) and len(inputs) >= 2
    session = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    got = session.run(None, {session.get_inputs()[0].name: inputs})[0]
    assert expected.shape == got.shape == (len(inputs), 19)
    np.testing.assert_allclose(got, expected, atol=1e-4)
    assert not np.allclose(got, got[0]), "every input got the same output: the export lost the image"

    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["steps"] == 3
    assert 0.0 <= metrics["test_accuracy"] <= 1.0
    assert (out / "confusion_matrix.png").stat().st_size > 0
