"""The detector service, classifier mode: a camera view -> landmark probabilities -> the robot's fusion round.

The WNBC paper's robot (its Fig. 1) passes each image through its own shallow CNN and
hands the probability vector, with its yaw, to the communication module. Here the
CNN is :class:`~swarmrec.fusion.classifier.LandmarkClassifier` on onnxruntime and the
communication module is the robot's fusion service::

    classify(ClassifyRequest: round, encoded view, yaw, neighbours)
        --> decode (OpenCV) --> resize to the model's input --> CNN --> probabilities
        --> fusion/<robot>/start_round --> ClassifyReply (probabilities, own decision, fusion's answer)

A view that does not decode (not an image, truncated, empty) is answered
INVALID_ARGUMENT and counted in ``swarmrec_rejected_requests_total``. A view is a
PNG or a JPEG whose header claims at most ``max_view_pixels`` pixels, checked
before decoding: a few hundred compressed bytes can claim 30000 x 30000
pixels, which OpenCV would allocate (2.7 GB) and fill (TOO_LARGE); the fusion
service's own refusals (a round id that does not increase, a neighbour outside the
swarm) come back with its error code and message. Nothing a client sends stops the
service.
"""

from __future__ import annotations

import cv2
import numpy as np

from swarmrec.errors import (
    CallError,
    Internal,
    InvalidArgument,
    LimitExceededError,
    RemoteError,
    RequestError,
    Unavailable,
)
from swarmrec.fusion.classifier import ClassifierError, LandmarkClassifier
from swarmrec.runtime import ServiceContext, keys
from swarmrec.services.settings import ClassifierSettings, LandmarkSettings
from swarmrec.wire import messages as pb

__all__ = ["ClassifierMode", "decode_view"]

#: Largest encoded view accepted; a 64 x 64 PNG is ~10 kB, a 640 x 480 JPEG ~100 kB.
MAX_VIEW_BYTES = 8 * 1024 * 1024

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# JPEG start-of-frame markers (they carry the size): C0-CF but DHT (C4), JPG (C8) and DAC (CC).
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def view_size(data: bytes) -> tuple[int, int]:
    """(width, height) a PNG or JPEG claims in its header, read without decoding;
    ValueError when ``data`` is neither (or its header is cut short)."""
    if data.startswith(_PNG_SIGNATURE):
        # The IHDR chunk comes first: length, "IHDR", width, height (big-endian).
        if len(data) < 24 or data[12:16] != b"IHDR":
            raise ValueError("the view does not decode: a PNG without its IHDR header")
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    if data.startswith(b"\xff\xd8"):
        i = 2
        while i + 4 <= len(data):
            if data[i] != 0xFF:
                break
            marker = data[i + 1]
            if marker == 0xFF:  # fill byte
                i += 1
                continue
            if marker == 0x01 or 0xD0 <= marker <= 0xD7:  # markers without a length
                i += 2
                continue
            length = int.from_bytes(data[i + 2 : i + 4], "big")
            if marker in _JPEG_SOF:
                if length < 7 or i + 9 > len(data):
                    break
                # length (2), precision (1), height (2), width (2)
                return int.from_bytes(data[i + 7 : i + 9], "big"), int.from_bytes(data[i + 5 : i + 7], "big")
            i += 2 + length
        raise ValueError("the view does not decode: a JPEG without a readable frame header")
    raise ValueError("the view does not decode as a PNG or a JPEG")


def decode_view(data: bytes, max_pixels: int | None = None) -> np.ndarray:
    """An encoded PNG or JPEG as RGB ``uint8 [H, W, 3]``; ValueError with the reason when
    it is not one, LimitExceededError (before decoding) when its header claims more
    than ``max_pixels`` pixels."""
    if not data:
        raise ValueError("the view is empty")
    if len(data) > MAX_VIEW_BYTES:
        raise ValueError(f"the view has {len(data)} bytes, more than {MAX_VIEW_BYTES}")
    width, height = view_size(data)
    if max_pixels is not None and width * height > max_pixels:
        raise LimitExceededError(f"pixels in the view ({width} x {height})", width * height, max_pixels,
                                 "max_view_pixels")  # fmt: skip
    bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ValueError("the view does not decode (a truncated or corrupt PNG or JPEG)")
    if bgr.shape[:2] != (height, width):
        raise ValueError(
            f"the view decodes to {bgr.shape[1]} x {bgr.shape[0]}, its header says {width} x {height}"
        )
    return np.ascontiguousarray(bgr[:, :, ::-1])


class ClassifierMode:
    """The ``classify`` endpoint of a detector with ``--detector-mode classifier``."""

    def __init__(self, ctx: ServiceContext) -> None:
        self.ctx = ctx
        settings = ctx.settings(ClassifierSettings)
        model = settings.classifier_model
        self.max_pixels = settings.max_view_pixels
        # The model is loaded (and probed) here, so a wrong file stops the start, not a query.
        self.classifier = LandmarkClassifier(
            model or None, n_classes=ctx.settings(LandmarkSettings).n_classes
        )
        self.fusion_key = keys.endpoint(ctx.bus.swarm, "fusion", ctx.bus.robot, "start_round")
        fields = {"model": self.classifier.model, "input": list(self.classifier.image_size)}
        ctx.log.info("classifier loaded", extra={"fields": fields})

    def classify(self, req: pb.ClassifyRequest) -> pb.ClassifyReply:
        try:
            view = decode_view(req.image, self.max_pixels)
        except LimitExceededError:
            raise  # TOO_LARGE, its own code
        except ValueError as e:
            raise InvalidArgument(f"round {req.round_id}: {e}") from None
        h, w = self.classifier.image_size
        if view.shape[:2] != (h, w):
            # INTER_AREA averages when shrinking, as a camera's larger frame would be.
            view = cv2.resize(view, (w, h), interpolation=cv2.INTER_AREA)
        try:
            probabilities = self.classifier.classify(view)[0]
        except ClassifierError as e:  # the model misbehaving at run time: the robot's fault, not the view's
            raise Internal(f"classifier: {e}") from None
        start = pb.FusionRoundStart(
            round_id=req.round_id,
            probabilities=probabilities.tolist(),
            yaw_rad=req.yaw_rad,
            neighbour_robot_ids=list(req.neighbour_robot_ids),
        )
        if req.HasField("weight_law"):
            start.weight_law.CopyFrom(req.weight_law)
        robot = self.ctx.bus.robot
        try:
            started = self.ctx.caller.call(
                self.fusion_key, start, pb.FusionRoundStarted, target_robot=robot, endpoint="start_round"
            )
        except RemoteError as e:
            # The fusion service's refusal keeps its code (INVALID_ARGUMENT for a bad round).
            raise RequestError(f"fusion: {e}", code=e.code or None) from None
        except CallError as e:  # no reply, timeout: the robot's fusion service is not there
            raise Unavailable(f"fusion: {e}") from None
        return pb.ClassifyReply(
            robot_id=robot,
            round_id=req.round_id,
            probabilities=probabilities.tolist(),
            decision=int(np.argmax(probabilities)),
            fusion=started,
        )
