"""The detector service, classifier mode: a camera view -> landmark probabilities -> the robot's fusion round.

The WNBC paper's robot (its Fig. 1) passes each image through its own shallow CNN and
hands the probability vector, with its yaw, to the communication module. Here the
CNN is :class:`~swarmrec.fusion.classifier.LandmarkClassifier` on onnxruntime and the
communication module is the robot's fusion service::

    classify(ClassifyRequest: round, encoded view, yaw, neighbours)
        --> decode (OpenCV) --> resize to the model's input --> CNN --> probabilities
        --> fusion/<robot>/start_round --> ClassifyReply (probabilities, own decision, fusion's answer)

A view that does not decode (not an image, truncated, empty) is answered
INVALID_ARGUMENT and counted in ``swarmrec_rejected_requests_total``; the fusion
service's own refusals (a round id that does not increase, a neighbour outside the
swarm) come back with its error code and message. Nothing a client sends stops the
service.
"""

from __future__ import annotations

import cv2
import numpy as np

from swarmrec.errors import CallError, Internal, InvalidArgument, RemoteError, RequestError, Unavailable
from swarmrec.fusion.classifier import ClassifierError, LandmarkClassifier
from swarmrec.runtime import ServiceContext, keys
from swarmrec.services.settings import ClassifierSettings, LandmarkSettings
from swarmrec.wire import messages as pb

__all__ = ["ClassifierMode", "decode_view"]

#: Largest encoded view accepted; a 64 x 64 PNG is ~10 kB, a 640 x 480 JPEG ~100 kB.
MAX_VIEW_BYTES = 8 * 1024 * 1024


def decode_view(data: bytes) -> np.ndarray:
    """An encoded image (PNG, JPEG, ... anything OpenCV reads) as RGB ``uint8 [H, W, 3]``;
    ValueError with the reason when it is not one."""
    if not data:
        raise ValueError("the view is empty")
    if len(data) > MAX_VIEW_BYTES:
        raise ValueError(f"the view has {len(data)} bytes, more than {MAX_VIEW_BYTES}")
    bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ValueError("the view is not an image OpenCV can decode (PNG, JPEG, ...)")
    return np.ascontiguousarray(bgr[:, :, ::-1])


class ClassifierMode:
    """The ``classify`` endpoint of a detector with ``--detector-mode classifier``."""

    def __init__(self, ctx: ServiceContext) -> None:
        self.ctx = ctx
        model = ctx.settings(ClassifierSettings).classifier_model
        # The model is loaded (and probed) here, so a wrong file stops the start, not a query.
        self.classifier = LandmarkClassifier(
            model or None, n_classes=ctx.settings(LandmarkSettings).n_classes
        )
        self.fusion_key = keys.endpoint(ctx.bus.swarm, "fusion", ctx.bus.robot, "start_round")
        fields = {"model": self.classifier.model, "input": list(self.classifier.image_size)}
        ctx.log.info("classifier loaded", extra={"fields": fields})

    def classify(self, req: pb.ClassifyRequest) -> pb.ClassifyReply:
        try:
            view = decode_view(req.image)
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
