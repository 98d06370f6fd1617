"""The detector service: turns its robot's camera into what the swarm shares.

One service kind with three modes (``--detector-mode``), each a strategy inside
one class with one set of endpoints:

* ``replay`` (:mod:`.replay`): recorded constellations, a folder or zip of
  constellation files;
* ``rgbd`` (:mod:`.rgbd`): RGB-D frames of a TUM-format folder through a
  YOLO-style ONNX model and the depth image, as the constellation paper made
  them (docs/detector.md);
* ``classifier`` (:mod:`.classifier`): camera views to landmark probabilities
  for the robot's fusion round.

The replay and rgbd modes answer ``step`` and ``replay`` (:mod:`.frames`); the
classifier mode answers ``classify``. Asking a detector for an endpoint of
another mode is answered FAILED_PRECONDITION, naming the mode it runs in. A
request without its required field (``step``, ``rate_hz``, ``round_id``: an
empty payload would read as step 0, a replay as fast as possible, round 0) or
with fields its schema does not have is refused before anything runs.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from swarmrec.errors import FailedPrecondition
from swarmrec.runtime import Endpoint, RequestContext, ServiceBase, ServiceContext
from swarmrec.services.detector.frames import FramePlayer, FrameSource
from swarmrec.services.detector.replay import ReplaySource
from swarmrec.services.settings import DetectorSettings, PlaceSettings
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import check_fields

if TYPE_CHECKING:
    from swarmrec.services.detector.classifier import ClassifierMode

__all__ = ["Detector"]


class Detector(ServiceBase):
    """The ``detector`` kind: its mode's source of frames, or its classifier."""

    def __init__(self, ctx: ServiceContext) -> None:
        self.mode = ctx.settings(DetectorSettings).detector_mode
        self.n_labels = ctx.settings(PlaceSettings).n_labels
        self.player: FramePlayer | None = None
        self.classifier: ClassifierMode | None = None
        # The rgbd and classifier modes are imported when chosen: a replaying detector (and a
        # robot process hosting one) need not load onnxruntime and OpenCV, a second of start-up.
        if self.mode == "classifier":
            from swarmrec.services.detector.classifier import ClassifierMode

            self.classifier = ClassifierMode(ctx)
        elif self.mode == "rgbd":
            from swarmrec.services.detector.rgbd import RgbdSource

            self.player = FramePlayer(ctx, RgbdSource(ctx))
        else:
            source: FrameSource = ReplaySource(ctx)
            self.player = FramePlayer(ctx, source)

    def member_info(self) -> pb.MemberInfo:
        # A classifier's classes are the landmarks', not the place-recognition label list.
        return pb.MemberInfo(
            n_labels=0 if self.classifier is not None else self.n_labels,
            pending_items=self.player.pending() if self.player is not None else 0,
        )

    def _player(self, endpoint: str) -> FramePlayer:
        if self.player is None:
            raise FailedPrecondition(
                f"{endpoint}: this detector runs in {self.mode} mode (it classifies views)"
            )
        return self.player

    def step(self, req: pb.StepRequest, _ctx: RequestContext) -> pb.StepReply:
        check_fields(req, "step")
        return self._player("step").step(req)

    def replay(self, req: pb.ReplayRequest, _ctx: RequestContext) -> pb.ReplayReply:
        check_fields(req, "rate_hz")
        return self._player("replay").replay(req)

    def classify(self, req: pb.ClassifyRequest, _ctx: RequestContext) -> pb.ClassifyReply:
        check_fields(req, "round_id")
        if self.classifier is None:
            raise FailedPrecondition(f"classify: this detector runs in {self.mode} mode (it plays frames)")
        return self.classifier.classify(req)

    def close(self) -> None:
        if self.player is not None:
            self.player.close()

    ENDPOINTS = (
        Endpoint(
            "step", pb.StepRequest, pb.StepReply, step, "lock-step replay: play frame `step` (replay, rgbd)"
        ),
        Endpoint(
            "replay",
            pb.ReplayRequest,
            pb.ReplayReply,
            replay,
            "free replay of the whole block (replay, rgbd)",
        ),
        Endpoint(
            "classify",
            pb.ClassifyRequest,
            pb.ClassifyReply,
            classify,
            "a view to a fusion round (classifier)",
        ),
    )
