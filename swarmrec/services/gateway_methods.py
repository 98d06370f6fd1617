"""The gateway's calls to the other methods' services: full-image place recognition, SLAM,
landmark rounds (the RPCs of proto/swarmrec/v1/gateway.proto after ``WatchMembership``).

Each unary call is one function of :mod:`swarmrec.services.methods` (the same the Python
client runs over zenoh), run with the call's deadline by :meth:`Gateway.unary
<swarmrec.services.gateway.Gateway.unary>`, which maps a refusal to its gRPC status. Two
things only the gateway does:

* a ``PlaceQuery`` by image: the gateway decodes the image (a PNG or JPEG of at most
  :data:`MAX_IMAGE_PIXELS` pixels, checked in its header before decoding) and describes it
  with the swarm's descriptor model (``descriptor_model``, loaded on the first such query);
  a gateway that cannot load the model answers FAILED_PRECONDITION with the reason, and a
  client sends the descriptor instead;
* ``WatchSlamEstimate``: a slam service publishes no events, so the stream asks the robot
  every ``interval_ms`` and sends its estimate each time it has moved on (solve, state,
  linearisation, iteration), ending OK after the estimate of a solve that has ended. It
  takes one of the gateway's stream slots, as the event streams do.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from typing import NoReturn, Protocol

import grpc
import numpy as np
import numpy.typing as npt

# protobuf ships no type stubs (see swarmrec/runtime/rpc.py for the two codes).
from google.protobuf.message import Message  # type: ignore[import-untyped, unused-ignore]

from swarmrec.errors import ErrorCode, FailedPrecondition, InvalidArgument, LimitExceededError, RequestError
from swarmrec.runtime.rpc import Caller
from swarmrec.runtime.settings import BusSettings
from swarmrec.services import methods
from swarmrec.services.metrics import GatewayMetrics
from swarmrec.services.settings import VprSettings
from swarmrec.wire import messages as pb
from swarmrec.wire.gen.swarmrec.v1 import gateway_pb2

__all__ = ["MAX_IMAGE_PIXELS", "SUBSCRIBED_METADATA", "GatewayMethods", "ImageDescriber"]

#: Initial metadata of a stream, sent once it is open: for an event stream once its zenoh
#: subscriber is declared (events published after the client reads it are delivered), for a
#: robot's estimate once the first estimate is read.
SUBSCRIBED_METADATA = "swarmrec-subscribed"

#: The most pixels an image of a PlaceQuery may claim (2048 x 2048; 12 MB decoded): a few
#: hundred compressed bytes can claim far more, which decoding would allocate.
MAX_IMAGE_PIXELS = 1 << 22


class ImageDescriber:
    """The swarm's descriptor model, loaded on first use; if it cannot be, why (kept, so a
    broken model costs one attempt, not one a query)."""

    def __init__(self, vpr: VprSettings) -> None:
        self.vpr = vpr
        self.lock = threading.Lock()
        self.model: methods.Describer | None = None
        self.failure = ""

    def _load(self) -> methods.Describer:
        with self.lock:
            if self.model is None and not self.failure:
                try:
                    # onnxruntime and the model only in a gateway asked to describe an image.
                    from swarmrec.vpr.model import DescriptorModel

                    self.model = DescriptorModel(
                        self.vpr.descriptor_model or None, intra_op_threads=self.vpr.descriptor_threads
                    )
                except Exception as e:  # a missing runtime, file or a wrong model: all say why
                    self.failure = f"{type(e).__name__}: {e}"
            if self.model is None:
                raise FailedPrecondition(
                    f"this gateway cannot run the descriptor model ({self.failure}); "
                    "send the image's descriptor instead"
                )
            return self.model

    def describe(self, image: bytes) -> npt.NDArray[np.float32]:
        """The unit descriptor of an encoded image, as the robots' detectors compute it."""
        from swarmrec.services.detector.classifier import decode_view  # OpenCV, on first use

        model = self._load()
        try:
            rgb = decode_view(image, MAX_IMAGE_PIXELS)
        except LimitExceededError:
            raise  # TOO_LARGE: it claims more pixels than a query may cost
        except ValueError as e:
            raise InvalidArgument(f"image: {e}") from None
        # The model takes camera frames as OpenCV gives them (BGR) and resizes them itself.
        described = model.describe_frames(np.ascontiguousarray(rgb[:, :, ::-1]))
        return np.asarray(described[0], np.float32)


class Host(Protocol):
    """What these calls need of the gateway (:class:`swarmrec.services.gateway.Gateway`,
    which imports this module)."""

    bus: BusSettings
    metrics: GatewayMetrics
    stopping: threading.Event

    def caller_for(self, context: grpc.ServicerContext) -> Caller: ...

    def take_stream_slot(
        self, context: grpc.ServicerContext, on_release: Callable[[], None]
    ) -> Callable[[], None]: ...

    def abort_for(self, context: grpc.ServicerContext, e: Exception) -> NoReturn: ...


class GatewayMethods:
    """The gateway's RPCs of the full-image, SLAM and landmark methods."""

    def __init__(self, gateway: Host, vpr: VprSettings) -> None:
        self.g = gateway
        self.swarm = gateway.bus.swarm
        self.vpr = vpr
        self.describer = ImageDescriber(vpr)

    # --- full-image place recognition -------------------------------------------------

    def place_query(self, req: gateway_pb2.PlaceQueryRequest, caller: Caller) -> gateway_pb2.PlaceQueryReply:
        if bool(req.descriptor) == bool(req.image):
            raise InvalidArgument("a PlaceQuery takes exactly one of a descriptor or an image")
        t0 = time.perf_counter()
        computed: npt.NDArray[np.float32] | None = None
        if req.image:
            computed = self.describer.describe(req.image)
        x = computed if computed is not None else list(req.descriptor)
        exclude = req.exclude_robot_id if req.HasField("exclude_robot_id") else None
        reply = methods.place_query(
            caller, self.swarm, x, exclude_robot=exclude, centres=self.vpr.vpr_centres or None
        )
        if computed is not None:
            reply.descriptor.extend(computed.tolist())
        reply.duration_us = min(int((time.perf_counter() - t0) * 1e6), 2**32 - 1)
        return reply

    def cluster_table(self, caller: Caller) -> gateway_pb2.ClusterTableReply:
        return methods.cluster_table(caller, self.swarm)

    def place_loop_closures(
        self, req: gateway_pb2.RobotLoopClosuresRequest, caller: Caller
    ) -> pb.LoopClosureList:
        return methods.place_loop_closures(caller, self.swarm, req.robot_id, req.min_score)

    # --- SLAM ---------------------------------------------------------------------------

    def slam_team(self, caller: Caller) -> gateway_pb2.SlamTeamReply:
        return methods.slam_team(caller, self.swarm)

    def slam_estimate(self, req: gateway_pb2.SlamRobotRequest, caller: Caller) -> pb.SlamEstimate:
        return methods.slam_estimate(caller, self.swarm, req.robot_id)

    def slam_map(self, caller: Caller) -> gateway_pb2.SlamMapReply:
        return methods.slam_map(caller, self.swarm)

    def watch_estimate(
        self, req: gateway_pb2.WatchSlamEstimateRequest, context: grpc.ServicerContext
    ) -> Iterator[Message]:
        """Robot ``req.robot_id``'s estimate each time it moves on, until its solve ends."""
        lo, hi = methods.WATCH_INTERVAL_MS
        interval_ms = req.interval_ms or methods.DEFAULT_WATCH_INTERVAL_MS
        if not lo <= interval_ms <= hi:
            self.g.abort_for(
                context, InvalidArgument(f"interval_ms must be in [{lo}, {hi}], got {interval_ms}")
            )
        release = self.g.take_stream_slot(context, lambda: None)
        if not context.add_callback(release):
            release()  # the call has ended already
        sent = self.g.metrics.events_sent.labels("slam_estimate")
        last: tuple[int, int, int, int] | None = None
        try:
            while context.is_active():
                if self.g.stopping.is_set():
                    self.g.abort_for(
                        context, RequestError("the gateway is stopping", code=ErrorCode.UNAVAILABLE)
                    )
                try:
                    estimate = methods.slam_estimate(self.g.caller_for(context), self.swarm, req.robot_id)
                except Exception as e:
                    self.g.abort_for(context, e)
                if last is None:
                    context.send_initial_metadata(((SUBSCRIBED_METADATA, "1"),))
                position = methods.estimate_position(estimate)
                if position != last:
                    last = position
                    sent.inc()
                    yield estimate
                if methods.terminal(estimate.state):
                    return  # the solve has ended: its final estimate was the last one
                self.g.stopping.wait(interval_ms / 1000)
        finally:
            release()

    # --- landmark rounds ----------------------------------------------------------------

    def landmark_round(
        self, req: gateway_pb2.LandmarkRoundRequest, caller: Caller
    ) -> gateway_pb2.LandmarkRoundReply:
        round_id = req.round_id if req.HasField("round_id") else None
        return methods.landmark_round(caller, self.swarm, round_id)
