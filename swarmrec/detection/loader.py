"""The one way a detector model is loaded: the services' rgbd mode, the pixels
pipeline and the benchmarks all call :func:`load_detector`.

An empty model names the project's shipped detector (``models/detector/``,
looked up by :func:`swarmrec.models.shipped_model`). A confidence threshold
left unset is the shipped model's recommended one (``recommended_conf_threshold``
in its ``metrics.json``, written by models/detector/train.py), and
:data:`DEFAULT_CONF_THRESHOLD` for a user's model.
"""

from __future__ import annotations

import json
from pathlib import Path

from swarmrec.detection.yolo import DetectorSettings, OnnxDetector
from swarmrec.models import DETECTOR_MODEL, shipped_model

__all__ = ["DEFAULT_CONF_THRESHOLD", "conf_threshold_for", "load_detector", "model_path"]

#: Confidence threshold of a user's model when none is set: Ultralytics' own default.
#: (The paper's zero threshold keeps hundreds of boxes a frame with today's exports.)
DEFAULT_CONF_THRESHOLD = 0.25


def model_path(model: str | Path = "") -> Path:
    """``model``, or the project's shipped detector when it is empty."""
    return Path(model) if str(model) else shipped_model(DETECTOR_MODEL)


def conf_threshold_for(model: str | Path = "", conf_threshold: float | None = None) -> float:
    """``conf_threshold``; unset: the shipped model's recommended one for the project's
    model, :data:`DEFAULT_CONF_THRESHOLD` for a user's."""
    if conf_threshold is not None:
        return conf_threshold
    if not str(model):
        recommended = _recommended_threshold(model_path(model).parent / "metrics.json")
        if recommended is not None:
            return recommended
    return DEFAULT_CONF_THRESHOLD


def _recommended_threshold(path: Path) -> float | None:
    """``recommended_conf_threshold`` of a model card's metrics."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict):
        return None
    value = data.get("recommended_conf_threshold")
    if isinstance(value, int | float) and not isinstance(value, bool) and 0.0 <= value <= 1.0:
        return float(value)
    return None


def load_detector(
    model: str | Path = "",
    *,
    n_classes: int,
    conf_threshold: float | None = None,
    iou_threshold: float = 0.45,
    threads: int = 1,
) -> OnnxDetector:
    """The ONNX detector ``model`` (empty: the shipped one) for ``n_classes`` labels;
    ModelError / ModelNotFound name the file."""
    return OnnxDetector(
        model_path(model),
        DetectorSettings(
            n_classes=n_classes,
            conf_threshold=conf_threshold_for(model, conf_threshold),
            iou_threshold=iou_threshold,
            intra_op_threads=threads,
        ),
    )
