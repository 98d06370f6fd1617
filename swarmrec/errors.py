"""Exceptions raised by swarmrec.

Every error the project raises on purpose derives from :class:`SwarmrecError`,
so a caller can catch the whole family in one place::

    SwarmrecError
    ├── ConfigError            a setting is missing, out of range or inconsistent
    ├── DatasetError           input data cannot be read (names the file and line)
    │   ├── MalformedLineError a line of a text file does not parse
    │   ├── UnknownLabelError  a label is not in the label list
    │   └── datasets.tum_rgbd.RgbdImageError  a frame's RGB or depth image is missing, corrupt or mismatched
    ├── WireError              a message on the bus does not decode or validate
    ├── detection.DetectionError   an image, a model or its output cannot be used
    │   ├── ModelError             the ONNX model cannot be loaded or has unusable inputs/outputs
    │   └── OutputLayoutError      a model output is neither YOLO layout (or both)
    ├── fusion.LikelihoodError     a classifier output is not a usable probability vector
    ├── fusion.classifier.ClassifierError   views the landmark classifier cannot take
    │   └── ClassifierModelError            its ONNX file is missing, does not load or is not a 19-way softmax
    ├── services.fusion.RoundError a fusion round that cannot start (answered INVALID_ARGUMENT)
    ├── models.ModelNotFound       a shipped model is in none of the places models are looked up
    ├── vpr.errors.VprError        place recognition cannot use this input
    │   ├── DescriptorError        a descriptor of the wrong shape or dtype, or with NaN/inf
    │   ├── DescriptorModelError   the descriptor ONNX file is missing, does not load or is not one
    │   └── StateFileError         a saved index, assignment or centres file cannot be read back
    └── swarm.compose.ComposeError the compose tool failed or containers did not become healthy

The families below the first four live beside the code that raises them
(``swarmrec.detection.errors``, ``swarmrec.fusion``, ``swarmrec.services.fusion``,
``swarmrec.models``, ``swarmrec.vpr.errors``, ``swarmrec.swarm.compose``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

__all__ = [
    "ConfigError",
    "DatasetError",
    "MalformedLineError",
    "SwarmrecError",
    "UnknownLabelError",
    "WireError",
]


class SwarmrecError(Exception):
    """Base class of every error swarmrec raises on purpose."""


class ConfigError(SwarmrecError, ValueError):
    """A setting is missing, out of range or inconsistent with another one."""


@dataclass
class DatasetError(SwarmrecError):
    """Input data cannot be read.

    ``source`` is the file (or ``archive.zip:member``) and ``line`` the 1-based
    line number when the problem is on one line, so the message always points
    the user at the exact place to fix.
    """

    source: str | Path
    reason: str
    line: int | None = None

    def __str__(self) -> str:
        where = f"{self.source}:{self.line}" if self.line is not None else str(self.source)
        return f"{where}: {self.reason}"


@dataclass
class MalformedLineError(DatasetError):
    """A line of a text file does not parse (wrong column count, not a number, NaN...)."""


@dataclass
class UnknownLabelError(DatasetError):
    """A label that is not in the label list."""


class WireError(SwarmrecError, ValueError):
    """A message on the bus does not decode or does not validate."""
