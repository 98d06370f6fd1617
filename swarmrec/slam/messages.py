"""What distributed Gauss-Seidel agents tell each other, and what each step reports.

One :class:`DgsMessage` goes from one robot to one neighbour after each of
the sender's solves: the sender's current estimate of each of its keys that
appears in a separator with that neighbour, and nothing else. In the rotation
stage an estimate is 9 floats (the relaxed rotation, row by row); in a pose
stage 6 floats (the update ``(theta, dt)`` from the linearisation point). A
message is self-describing (sender, receiver, stage, linearisation, iteration)
so a transport can route it and a receiver can reject one that does not fit.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Literal

from swarmrec.slam.errors import MessageError
from swarmrec.slam.keys import describe_key

__all__ = [
    "FLOATS_PER_ESTIMATE",
    "DgsMessage",
    "Stage",
    "StepReport",
]

Stage = Literal["rotation", "pose"]
FLOATS_PER_ESTIMATE: Mapping[Stage, int] = MappingProxyType({"rotation": 9, "pose": 6})


@dataclass(frozen=True)
class DgsMessage:
    """One robot's separator estimates for one neighbour, after one of its solves.

    ``linearisation`` is 0 in the rotation stage and ``1, 2, ...`` for the
    successive pose stages (each linearised at the previous one's result);
    ``iteration`` counts the sender's Gauss-Seidel iterations from 1 within
    that stage. ``estimates`` maps each key to 9 floats (rotation stage) or 6
    (pose stage).
    """

    sender: int
    receiver: int
    stage: Stage
    linearisation: int
    iteration: int
    estimates: Mapping[int, tuple[float, ...]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.stage not in FLOATS_PER_ESTIMATE:
            raise MessageError(f"unknown stage {self.stage!r} (rotation or pose)")
        if self.sender == self.receiver:
            raise MessageError(f"robot {self.sender} sends a message to itself")
        if self.iteration < 1:
            raise MessageError(f"iterations count from 1, got {self.iteration}")
        if (self.stage == "rotation") != (self.linearisation == 0):
            raise MessageError(
                f"linearisation {self.linearisation} does not fit the {self.stage} stage "
                "(0 for rotations, 1, 2, ... for poses)"
            )
        size = FLOATS_PER_ESTIMATE[self.stage]
        frozen: dict[int, tuple[float, ...]] = {}
        for key, values in self.estimates.items():
            vector = tuple(float(v) for v in values)
            if len(vector) != size:
                raise MessageError(
                    f"{self.stage} estimate of {describe_key(key)} has {len(vector)} floats, expected {size}"
                )
            if not all(math.isfinite(v) for v in vector):
                raise MessageError(f"{self.stage} estimate of {describe_key(key)} is not finite")
            frozen[key] = vector
        object.__setattr__(self, "estimates", MappingProxyType(frozen))

    @property
    def floats(self) -> int:
        """Floats carried (9 per rotation, 6 per pose update): the communication model's unit."""
        return FLOATS_PER_ESTIMATE[self.stage] * len(self.estimates)


@dataclass(frozen=True)
class StepReport:
    """What one agent did in one iteration.

    ``solved`` is False when the agent had nothing to solve against yet (no
    anchor and no estimated neighbour, flagged initialisation): it then sends
    nothing and its ``change`` is infinite. ``change`` is the Euclidean norm of
    the difference between the new solution and the previous estimate over all
    the robot's free variables (9 or 6 per key), the quantity the stopping rule
    compares with eta.
    """

    robot: int
    stage: Stage
    linearisation: int
    iteration: int
    solved: bool
    change: float
    messages: tuple[DgsMessage, ...]
