"""Exceptions raised by swarmrec.

Every error the project raises on purpose derives from :class:`SwarmrecError`,
so a caller can catch the whole family in one place::

    SwarmrecError
    ├── ConfigError            a setting is missing, out of range or inconsistent
    ├── DatasetError           input data cannot be read (names the file and line)
    │   ├── MalformedLineError a line of a text file does not parse
    │   └── UnknownLabelError  a label is not in the label list
    ├── WireError              a message on the bus does not decode or validate
    ├── detection.DetectionError   an image, a model or its output cannot be used
    │   ├── ModelError             the ONNX model cannot be loaded or has unusable inputs/outputs
    │   └── OutputLayoutError      a model output is neither YOLO layout (or both)
    ├── fusion.LikelihoodError     a classifier output is not a usable probability vector
    └── swarm.compose.ComposeError the compose tool failed or containers did not become healthy

The last three families live beside the code that raises them
(``swarmrec.detection.errors``, ``swarmrec.fusion.wnbc``, ``swarmrec.swarm.compose``).
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
