"""Exceptions of place recognition, in the project's hierarchy (:mod:`swarmrec.errors`)::

    SwarmrecError
    └── VprError                  place recognition cannot use this input
        ├── DescriptorError       a descriptor of the wrong shape or dtype, or with NaN/inf
        ├── DescriptorModelError  the ONNX model is missing, does not load or is not a descriptor model
        └── StateFileError        a saved index, assignment or centres file that cannot be read back

All are also :class:`ValueError`, so a service answering bad input with an
error reply catches them with the rest of its bad-input errors.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from swarmrec.errors import SwarmrecError

__all__ = ["DescriptorError", "DescriptorModelError", "StateFileError", "VprError"]


class VprError(SwarmrecError, ValueError):
    """Place recognition cannot use this input."""


class DescriptorError(VprError):
    """A descriptor (or batch of them) of the wrong shape or dtype, or holding NaN or inf."""


@dataclass(eq=False)
class DescriptorModelError(VprError):
    """The model file is missing, does not load, or is not a full-image descriptor model."""

    model: str
    reason: str

    def __str__(self) -> str:
        return f"{self.model}: {self.reason}"


@dataclass(eq=False)
class StateFileError(VprError):
    """A saved file (index, assignment, centres) that is missing a part, corrupt or inconsistent."""

    path: str | Path
    reason: str

    def __str__(self) -> str:
        return f"{self.path}: {self.reason}"
