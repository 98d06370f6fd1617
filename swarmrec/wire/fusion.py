"""Conversion between the fusion core's types and the v1 fusion messages.

A flooded :class:`~swarmrec.fusion.flooding.FloodMessage` travels as a
``ClassifierOutput`` whose probabilities are float32: a vector received and
forwarded goes out bit-identical to what its origin sent, so every robot fuses
the same numbers. Received messages are converted as they are; the
:class:`~swarmrec.fusion.flooding.FloodingNode` validates them (length, NaN,
hops) and says why it refuses one.
"""

from __future__ import annotations

import struct

import numpy as np

from swarmrec.fusion.flooding import FloodMessage
from swarmrec.fusion.robot import Step
from swarmrec.fusion.wnbc import WeightLaw, make_weight_law
from swarmrec.wire import messages as pb

__all__ = [
    "ORIGIN_STATEMENT_TAG",
    "classifier_output_to_flood",
    "flood_to_classifier_output",
    "origin_statement",
    "step_to_proto",
    "weight_law_from_proto",
    "weight_law_to_proto",
]


def classifier_output_to_flood(msg: pb.ClassifierOutput) -> FloodMessage:
    """The core's view of a received ClassifierOutput (validated by the node, not here)."""
    return FloodMessage(
        round_id=msg.round_id,
        origin=msg.origin_robot_id,
        sender=msg.sender_robot_id,
        hops=msg.hop_count,
        yaw=msg.yaw_rad,
        likelihood=list(msg.probabilities),
    )


def flood_to_classifier_output(message: FloodMessage) -> pb.ClassifierOutput:
    """The wire form of a message to send (float32 probabilities and yaw)."""
    return pb.ClassifierOutput(
        origin_robot_id=message.origin,
        round_id=message.round_id,
        probabilities=np.asarray(message.likelihood, dtype=np.float64).tolist(),
        yaw_rad=message.yaw,
        hop_count=message.hops,
        sender_robot_id=message.sender,
    )


#: What a fusion origin statement starts with (so it can be mistaken for no other signed bytes).
ORIGIN_STATEMENT_TAG = b"swarmrec.v1.ClassifierOutput.origin\x00"


def origin_statement(swarm: str, msg: pb.ClassifierOutput) -> bytes:
    """The bytes an origin signs for ``msg`` (``origin_signature``): the tag, the swarm's
    name (UTF-8, then a zero byte), then little-endian uint32 origin, round and count of
    probabilities, the probabilities as float32 and the yaw as float32: what the origin
    said, as the wire carries it. Not the hops nor the sender: every relay changes them."""
    probabilities = np.asarray(msg.probabilities, dtype="<f4")
    return b"".join(
        (
            ORIGIN_STATEMENT_TAG,
            swarm.encode("utf-8"),
            b"\x00",
            struct.pack("<III", msg.origin_robot_id, msg.round_id, len(probabilities)),
            probabilities.tobytes(),
            struct.pack("<f", msg.yaw_rad),
        )
    )


def step_to_proto(step: Step) -> pb.FusionStep:
    """One incorporated message as the ``posterior`` endpoint and the events report it."""
    return pb.FusionStep(
        origin_robot_id=step.origin,
        sender_robot_id=step.sender,
        hops=step.hops,
        yaw_rad=step.yaw,
        weight=step.weight,
        decision_after=step.decision_after,
    )


def weight_law_from_proto(spec: pb.WeightLaw) -> WeightLaw:
    """The weight law a ``FusionRoundStart.weight_law`` names; ConfigError for an unknown
    name or a lambda that is negative or not a number."""
    lam = float(getattr(spec, "lambda")) if spec.HasField("lambda") else None  # a Python keyword
    return make_weight_law(spec.name, lam=lam)


def weight_law_to_proto(name: str, lam: float | None) -> pb.WeightLaw:
    """The wire form of a law choice (``lam`` None: the law's own default)."""
    msg = pb.WeightLaw(name=name)
    if lam is not None:
        setattr(msg, "lambda", lam)  # a Python keyword
    return msg
