"""Where the project's shipped ONNX models are found.

The models are trained apart (``models/<name>/train.py``, with torch) and committed
under the repository's ``models/``, which is not part of the Python package: a wheel
stays free of binary blobs a user may want to replace. So a model is looked up

1. in ``$SWARMREC_MODELS`` when it is set (the container image copies the models to
   ``/opt/swarmrec/models`` and sets it), then
2. in the ``models/`` of the source checkout this package runs from (a clone, or an
   editable install).

A missing model is a :class:`ModelNotFound` naming every place looked at and how to
make one, never a bare ``FileNotFoundError`` from deep inside onnxruntime.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from swarmrec.errors import SwarmrecError

__all__ = [
    "DESCRIPTOR_CENTRES",
    "DESCRIPTOR_MODEL",
    "DETECTOR_MODEL",
    "LANDMARK_MODEL",
    "MODELS_ENV",
    "ModelNotFound",
    "model_search_path",
    "shipped_model",
]

#: Environment variable naming a folder laid out like the repository's ``models/``.
MODELS_ENV = "SWARMREC_MODELS"
#: The landmark classifier of the WNBC paper (19 facades), relative to ``models/``.
LANDMARK_MODEL = Path("landmarks") / "landmark_cnn.onnx"
#: The small office-world object detector (COCO class ids), relative to ``models/``.
DETECTOR_MODEL = Path("detector") / "office_detector.onnx"
#: The full-image place descriptor (128-d, unit rows), relative to ``models/``.
DESCRIPTOR_MODEL = Path("descriptor") / "descriptor.onnx"
#: k-means centres of that descriptor, trained on other worlds than a swarm's (one array per k).
DESCRIPTOR_CENTRES = Path("descriptor") / "centres.npz"

#: swarmrec/models.py -> the repository root of a source checkout or an editable install.
_REPO_MODELS = Path(__file__).resolve().parents[1] / "models"


@dataclass(eq=False)
class ModelNotFound(SwarmrecError, FileNotFoundError):
    """A shipped model is in none of the places models are looked up."""

    model: Path
    searched: tuple[Path, ...]

    def __str__(self) -> str:
        places = ", ".join(str(p) for p in self.searched)
        return (
            f"model {self.model} not found (looked in {places}); set {MODELS_ENV} to a folder holding it, "
            f"pass a model path, or train one with models/{self.model.parts[0]}/train.py"
        )


def model_search_path() -> tuple[Path, ...]:
    """The folders searched for shipped models, first match wins."""
    env = os.environ.get(MODELS_ENV, "").strip()
    return (Path(env), _REPO_MODELS) if env else (_REPO_MODELS,)


def shipped_model(relative: Path | str) -> Path:
    """The path of a shipped model (e.g. :data:`DETECTOR_MODEL`), or :class:`ModelNotFound`."""
    relative = Path(relative)
    searched = model_search_path()
    for folder in searched:
        path = folder / relative
        if path.is_file():
            return path
    raise ModelNotFound(relative, searched)
