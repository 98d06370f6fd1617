"""Exceptions of the detector, in the project's hierarchy (:mod:`swarmrec.errors`)::

    SwarmrecError
    └── DetectionError         the detector cannot run on this model, output or image
        ├── ModelError         the .onnx file does not load or is not a YOLO-style model
        └── OutputLayoutError  a model output is neither YOLOv5 nor YOLOv8 layout for the classes

All are also :class:`ValueError`, so a service that answers bad input with an
error reply catches them with the rest of its bad-input errors.
"""

from __future__ import annotations

from dataclasses import dataclass

from swarmrec.errors import SwarmrecError

__all__ = ["DetectionError", "ModelError", "OutputLayoutError"]


class DetectionError(SwarmrecError, ValueError):
    """The detector cannot run on this model, model output or image."""


@dataclass(eq=False)
class ModelError(DetectionError):
    """The model file does not load, or its inputs or outputs are not a YOLO-style detector's."""

    model: str
    reason: str

    def __str__(self) -> str:
        return f"{self.model}: {self.reason}"


@dataclass(eq=False)
class OutputLayoutError(DetectionError):
    """A model output whose shape fits neither layout (or both) for ``n_classes`` classes.

    The shape and class count are fields so that the message, and a caller,
    can say which of the two is wrong.
    """

    shape: tuple[int, ...]
    n_classes: int
    reason: str

    def __str__(self) -> str:
        return f"model output of shape {list(self.shape)} with {self.n_classes} classes: {self.reason}"
