"""The office detector's training script (models/detector/train.py), run for a few steps in the
training environment (.venv-train, which has torch), and its ONNX export checked here, in the
service environment (onnxruntime, no torch): it loads in OnnxDetector with the YOLOv8 layout, and
onnxruntime's outputs equal torch's on the same inputs."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort  # type: ignore[import-untyped]  # onnxruntime ships no type hints
import pytest

from swarmrec.detection import DetectorSettings, Layout, OnnxDetector, detect_layout

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]
TRAIN_PYTHON = REPO / ".venv-train" / "bin" / "python"
SCRIPT = REPO / "models" / "detector" / "train.py"
SMOKE = ["--frames", "16", "--epochs", "1", "--max-steps", "3", "--fps-frames", "8", "--check-arrays"]
#: The classes of the office world (COCO ids) and the COCO class channels of the output.
N_COCO = 80


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    if not TRAIN_PYTHON.exists():
        pytest.fail(
            f"{TRAIN_PYTHON.relative_to(REPO)} is missing: `make train-env` builds the training "
            "environment (torch, onnx; models/requirements-train.txt)"
        )
    out = tmp_path_factory.mktemp("detector-smoke")
    proc = subprocess.run(
        [str(TRAIN_PYTHON), str(SCRIPT), *SMOKE, "--out", str(out)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    if "ModuleNotFoundError" in proc.stderr:
        missing = proc.stderr.strip().splitlines()[-1]
        pytest.fail(
            f"{TRAIN_PYTHON.relative_to(REPO)} lacks a package the training needs ({missing}): "
            "`make train-env` builds it"
        )
    assert proc.returncode == 0, f"train.py failed:\n{proc.stdout[-4000:]}\n{proc.stderr[-4000:]}"
    assert "test mAP@0.5" in proc.stdout
    return out


@pytest.fixture(scope="module")
def metrics(smoke_run: Path) -> dict[str, Any]:
    data: dict[str, Any] = json.loads((smoke_run / "metrics.json").read_text())
    return data


def test_the_smoke_run_writes_the_model_metrics_and_figures(smoke_run: Path, metrics: dict[str, Any]) -> None:
    for name in ("office_detector.onnx", "metrics.json", "examples.png", "pr_curve.png"):
        assert (smoke_run / name).stat().st_size > 0, name
    assert metrics["steps"] == 1  # 16 frames, batches of 16: one step per epoch, one epoch
    assert 0.0 <= metrics["test_map50"] <= 1.0
    assert metrics["model_bytes"] == (smoke_run / "office_detector.onnx").stat().st_size < 2_000_000
    assert 0.0 < metrics["recommended_conf_threshold"] < 1.0
    assert metrics["speed_640x480_2_threads"]["threshold_0"]["frames"] == 8
    seeds = metrics["worlds"]
    assert not set(seeds["train"]) & set(seeds["test"]) and not set(seeds["val"]) & set(seeds["test"])


def test_the_export_loads_in_onnx_detector_with_the_v8_layout(
    smoke_run: Path, metrics: dict[str, Any]
) -> None:
    model = smoke_run / "office_detector.onnx"
    detector = OnnxDetector(model, DetectorSettings(intra_op_threads=2))
    assert detector.layout is Layout.V8  # found from the static output shape at load
    assert list(detector.input_hw) == metrics["input"]["shape"][2:]
    session = ort.InferenceSession(str(model), providers=["CPUExecutionProvider"])
    (image,) = session.get_inputs()
    assert image.shape == [1, 3, *detector.input_hw] and image.type == "tensor(float)"
    shape = tuple(session.get_outputs()[0].shape)
    assert shape[:2] == (1, 4 + N_COCO) and shape == tuple(metrics["output"]["shape"])
    assert detect_layout(shape, N_COCO) is Layout.V8
    # A whole 640x480 frame: boxes come back in its pixels.
    frame = np.random.default_rng(0).integers(0, 256, (480, 640, 3), dtype=np.uint8)
    for d in OnnxDetector(model, DetectorSettings(conf_threshold=0.0, max_detections=50)).detect(frame):
        assert 0 <= d.x1 < d.x2 <= 640 and 0 <= d.y1 < d.y2 <= 480
        assert 0.0 <= d.score <= 1.0


def test_onnxruntime_gives_torchs_outputs(smoke_run: Path, metrics: dict[str, Any]) -> None:
    inputs = np.load(smoke_run / "check_inputs.npy")
    expected = np.load(smoke_run / "check_torch_outputs.npy")
    assert inputs.dtype == np.float32 and inputs.shape[1:] == (3, *metrics["input"]["shape"][2:])
    assert expected.shape == (inputs.shape[0], 4 + N_COCO, metrics["output"]["shape"][2])
    session = ort.InferenceSession(
        str(smoke_run / "office_detector.onnx"), providers=["CPUExecutionProvider"]
    )
    got = np.concatenate([session.run(["output0"], {"images": x[None]})[0] for x in inputs])
    # Scores to 1e-4 absolutely, boxes (input pixels) to 1e-4 relatively.
    np.testing.assert_allclose(got[:, 4:], expected[:, 4:], rtol=0, atol=1e-4)
    np.testing.assert_allclose(got[:, :4], expected[:, :4], rtol=1e-4, atol=1e-4)
    assert metrics["onnx_max_diff"] < 1e-4
    # Scores are probabilities, and the COCO classes the office never shows are exactly zero.
    scores = got[:, 4:]
    assert (scores >= 0).all() and (scores <= 1).all()
    office = [c["class_id"] for c in metrics["classes"]]
    others = np.setdiff1d(np.arange(N_COCO), office)
    assert len(office) >= 20 and (scores[:, others] == 0).all()
    assert (got[:, 2:4] >= 0).all()  # widths and heights
