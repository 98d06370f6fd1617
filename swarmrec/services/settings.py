"""The services' settings components, beyond the bus and storage (:mod:`swarmrec.runtime.settings`).

Each component is one concern; the registry lists which components each
service kind reads, so ``swarmrec serve index-shard --help`` shows the bus,
storage and place-recognition settings and nothing of cameras or fusion.
Every field becomes a flag (``--name``), an environment variable
(``SWARMREC_NAME``) and a key of the TOML file.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar, Literal

import numpy as np
import numpy.typing as npt

from swarmrec.core.presets import get_preset
from swarmrec.core.ranges import label_bounds, validate_bounds
from swarmrec.datasets.tum import DEFAULT_MAX_DT, TUM_DEPTH_SCALE
from swarmrec.errors import ConfigError
from swarmrec.fusion.robot import DEFAULT_MAX_ROUND_JUMP
from swarmrec.runtime.settings import BusSettings, Component, Config, setting
from swarmrec.wire.codec import FrameLimits

if TYPE_CHECKING:
    from swarmrec.detection.points import CameraIntrinsics

__all__ = [
    "DETECTOR_MODES",
    "ClassifierSettings",
    "DetectorSettings",
    "ExplainSettings",
    "FusionSettings",
    "GatewaySettings",
    "IndexSettings",
    "LandmarkSettings",
    "PlaceSettings",
    "RgbdSettings",
    "SlamServiceSettings",
    "VprSettings",
]

DetectorMode = Literal["replay", "rgbd", "classifier"]
WirePositions = Literal["mm", "exact"]
WIRE_POSITIONS: tuple[str, ...] = ("mm", "exact")
DETECTOR_MODES: tuple[str, ...] = ("replay", "rgbd", "classifier")
FusionLaw = Literal["paper", "agreement"]
PlaceMethod = Literal["constellations", "dvpr"]
PLACE_METHODS: tuple[str, ...] = ("constellations", "dvpr")
VprCode = Literal["int8", "float32"]
VPR_CODES: tuple[str, ...] = ("int8", "float32")
RebalanceRule = Literal["pack", "greedy"]
REBALANCE_RULES: tuple[str, ...] = ("pack", "greedy")


@dataclass(frozen=True)
class PlaceSettings(Component):
    """Place recognition with constellations: the preset, the label list and its ranges."""

    title: ClassVar[str] = "place recognition"

    preset: str = setting("paper", "place-recognition preset (swarmrec.core.presets: paper, balanced)")
    n_labels: int = setting(80, "size of the swarm's label list")
    label_bounds: tuple[int, ...] = setting(
        (), "label range boundaries, n_robots + 1 values; empty: even ranges (the paper's)"
    )
    lockstep: bool = setting(False, "shards answer from the frames stored before the query's step")
    loop_closure_min_score: float = setting(
        0.3, "a verified match at least this good is published as a loop closure"
    )
    wire_positions: WirePositions = setting(
        "mm",
        "object positions on the wire: mm (integers, about 2 bytes a coordinate) or exact (8-byte doubles, "
        "every score bit for bit the published scripts')",
    )
    # Bounds on the work one request can cause (docs/swarm.md, "Bad input"): a frame's
    # association costs about objects^2 x labels, so one huge frame must not cost seconds
    # of CPU and gigabytes, on arrival or in every later verify.
    max_objects_per_frame: int = setting(
        300, "a frame with more objects is refused (TOO_LARGE); the detector keeps at most 300 boxes"
    )
    max_objects_per_label: int = setting(100, "a frame with more objects of one label is refused (TOO_LARGE)")
    verify_max_frames: int = setting(
        1024, "a verify request that would check more stored frames is refused (TOO_LARGE)"
    )
    verify_max_object_pairs: int = setting(
        1_000_000,
        "a verify request that would compare more object pairs (query objects x frame objects, "
        "summed over the frames checked) is refused (TOO_LARGE)",
    )

    def problems(self) -> list[str]:
        problems = []
        if self.n_labels < 1:
            problems.append(f"n_labels must be >= 1, got {self.n_labels}")
        for name in ("max_objects_per_frame", "max_objects_per_label", "verify_max_frames",
                     "verify_max_object_pairs"):  # fmt: skip
            if getattr(self, name) < 1:
                problems.append(f"{name} must be >= 1, got {getattr(self, name)}")
        if not math.isfinite(self.loop_closure_min_score):
            problems.append(f"loop_closure_min_score must be a number, got {self.loop_closure_min_score}")
        try:
            get_preset(self.preset)
        except ConfigError as e:
            problems.append(str(e))
        if self.wire_positions not in WIRE_POSITIONS:
            problems.append(f"wire_positions must be mm or exact, got {self.wire_positions!r}")
        return problems

    def frame_limits(self) -> FrameLimits:
        """The bounds on one frame's objects, as the wire codec checks them."""
        return FrameLimits(self.max_objects_per_frame, self.max_objects_per_label)

    @property
    def exact_positions(self) -> bool:
        """Whether constellations carry positions as exact doubles."""
        return self.wire_positions == "exact"

    def problems_with(self, config: Config) -> list[str]:
        n = config.bus.n_robots
        b = self.label_bounds
        if b:
            # The check of a split given offline (core.ranges), and one range a robot.
            try:
                validate_bounds(b, self.n_labels)
                fits = len(b) == n + 1
            except ConfigError:
                fits = False
            if not fits:
                return [
                    f"label_bounds must be {n + 1} non-decreasing values from 0 to {self.n_labels}, "
                    f"got {list(b)}"
                ]
            return []
        # More robots than labels is allowed: the paper's split (integer linspace) then
        # leaves some robots an empty range, as the offline evaluation does; their shards
        # hold other groups' replicas and queries never ask them for a range of their own.
        if get_preset(self.preset).ranges == "balanced":
            return ["the balanced preset needs explicit label_bounds (computed from label loads)"]
        return []

    def bounds(self, bus: BusSettings) -> npt.NDArray[np.int64]:
        """The swarm's label range boundaries: explicit, or the preset's (even) ranges."""
        if self.label_bounds:
            return np.asarray(self.label_bounds, np.int64)
        return label_bounds("even", self.n_labels, bus.n_robots)


#: The most query reports a descriptor may be told to keep for ``explain`` (each ~300 B).
MAX_EXPLAIN_REPORTS = 1_000_000


@dataclass(frozen=True)
class ExplainSettings(Component):
    """What a descriptor keeps to explain its queries (swarmrec explain --connect)."""

    title: ClassVar[str] = "explain"

    explain_reports: int = setting(
        4096,
        "query reports a descriptor keeps in memory for its explain endpoint, the last N frames "
        f"(0: none; at most {MAX_EXPLAIN_REPORTS:,}; about 300 bytes each)",
    )

    def problems(self) -> list[str]:
        if not 0 <= self.explain_reports <= MAX_EXPLAIN_REPORTS:
            return [f"explain_reports must be 0 .. {MAX_EXPLAIN_REPORTS}, got {self.explain_reports}"]
        return []


@dataclass(frozen=True)
class IndexSettings(Component):
    """The elastic index: replicas of each label group, handoffs and rebalancing
    (docs/elastic-index.md), and how descriptors ride out shards that do not answer."""

    title: ClassVar[str] = "elastic index"

    replicas: int = setting(2, "index shards that hold each label group (1: the paper's one range a shard)")
    placement_tick_s: float = setting(
        0.25,
        "how often the coordinator (the lowest live shard) checks members, handoffs and load (it asks "
        "every shard only when something calls for it: state_interval_s)",
    )
    state_interval_s: float = setting(
        10.0,
        "while the placement is settled and no shard came, went or began draining, the coordinator "
        "asks every shard for its state (versions, load) this often instead of every tick",
    )
    member_grace_s: float = setting(
        5.0,
        "a shard gone this long loses its groups to the others' new replicas; "
        "queries go to a group's other owners at once",
    )
    member_start_grace_s: float = setting(
        60.0,
        "a member never seen alive since the coordinator started counts as starting this long "
        "before it loses its groups (a large swarm takes a while to start; moving the groups of "
        "shards still starting and back is churn)",
    )
    rebalance_target: float = setting(
        1.25,
        "the coordinator moves and adds replicas while the busiest shard's load is above this x the mean",
    )
    rebalance_rule: RebalanceRule = setting(
        "pack",
        "pack: owners per group planned and packed onto the shards (swarmrec.core.rebalance); "
        "greedy: the rule before it, one move at a time off the busiest shard (a benchmark's baseline)",
    )
    rebalance_min_queries: int = setting(
        200, "partial queries to observe (since the last rebalancing) before rebalancing on them"
    )
    transfer_page: int = setting(2000, "descriptors in one page of a handoff copy")
    drain_timeout_s: float = setting(
        30.0,
        "a shard told to stop first hands its groups to the others (a scale-down), for at most this "
        "long; it stops at once when every other shard is stopping too",
    )
    max_shards: int = setting(
        0,
        "index shards may have ids up to max(n_robots, max_shards) - 1: shards beyond the robots "
        "(a StatefulSet scaled up); 0: as many as robots",
    )
    pending_capacity: int = setting(
        100_000,
        "stores a descriptor keeps to retry (on disk) while shards do not acknowledge them; "
        "past it, new frames are refused (UNAVAILABLE) rather than stores dropped",
    )
    retry_interval_s: float = setting(0.5, "how often a descriptor retries its pending stores")
    hold_when_away: bool = setting(
        False,
        "a mesh (a router per robot, docs/mesh.md): a member out of sight is away (in another "
        "part of a split team, or its robot's router died), not gone, and while one is the "
        "coordinator changes no placement (set by the deployment for --topology mesh)",
    )
    suspect_s: float = setting(
        5.0, "a shard that timed out is asked last for this long (another owner answers first)"
    )

    def max_robot_id(self, bus: BusSettings) -> int:
        return max(bus.n_robots, self.max_shards) - 1

    def problems(self) -> list[str]:
        problems = []
        if not 1 <= self.replicas <= 16:
            problems.append(f"replicas must be 1 to 16, got {self.replicas}")
        for name in ("placement_tick_s", "retry_interval_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0.01 <= value <= 3600):
                problems.append(f"{name} must be 0.01 to 3600 s, got {value}")
        if self.max_shards < 0:
            problems.append(f"max_shards must be >= 0, got {self.max_shards}")
        for name in (
            "suspect_s",
            "member_grace_s",
            "member_start_grace_s",
            "drain_timeout_s",
            "state_interval_s",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0 <= value <= 3600):
                problems.append(f"{name} must be 0 to 3600 s, got {value}")
        if not (math.isfinite(self.rebalance_target) and self.rebalance_target >= 1.0):
            problems.append(
                f"rebalance_target must be >= 1 (1 is perfect balance), got {self.rebalance_target}"
            )
        if self.rebalance_rule not in REBALANCE_RULES:
            problems.append(
                f"rebalance_rule must be {', '.join(REBALANCE_RULES)}; got {self.rebalance_rule!r}"
            )
        if self.rebalance_min_queries < 1:
            problems.append(f"rebalance_min_queries must be >= 1, got {self.rebalance_min_queries}")
        if not 1 <= self.transfer_page <= 100_000:
            problems.append(f"transfer_page must be 1 to 100000, got {self.transfer_page}")
        if self.pending_capacity < 1:
            problems.append(f"pending_capacity must be >= 1, got {self.pending_capacity}")
        return problems


@dataclass(frozen=True)
class DetectorSettings(Component):
    """The detector: where its robot's frames come from."""

    title: ClassVar[str] = "detector"

    detector_mode: DetectorMode = setting(
        "replay",
        "replay: recorded constellations; rgbd: objects detected in RGB-D frames (docs/detector.md); "
        "classifier: camera views to landmark probabilities",
    )
    dataset: str = setting(
        "", "replay: a folder or zip of constellation files; rgbd: a TUM RGB-D folder (rgb.txt, depth.txt)"
    )
    labels_file: Path | None = setting(
        None, "label names of the dataset or the model's classes (default COCO)"
    )
    frames_per_robot: int = setting(
        0, "frames played by each robot; 0 splits the dataset evenly over n_robots"
    )
    outbox_capacity: int = setting(
        100_000,
        "frames the detector keeps (on disk) while its descriptor cannot take them; past it, "
        "steps are refused (UNAVAILABLE) rather than frames dropped",
    )
    outbox_retry_s: float = setting(0.5, "how often queued frames are sent again")

    def problems(self) -> list[str]:
        problems = []
        if self.outbox_capacity < 1:
            problems.append(f"outbox_capacity must be >= 1, got {self.outbox_capacity}")
        if not (math.isfinite(self.outbox_retry_s) and 0.01 <= self.outbox_retry_s <= 3600):
            problems.append(f"outbox_retry_s must be 0.01 to 3600 s, got {self.outbox_retry_s}")
        if self.detector_mode not in DETECTOR_MODES:
            problems.append(f"detector_mode must be {', '.join(DETECTOR_MODES)}; got {self.detector_mode!r}")
        if self.frames_per_robot < 0:
            problems.append(f"frames_per_robot must be >= 0, got {self.frames_per_robot}")
        return problems


@dataclass(frozen=True)
class RgbdSettings(Component):
    """The detector's rgbd mode: the ONNX model and the depth camera."""

    title: ClassVar[str] = "detector, rgbd mode"

    detector_model: str = setting(
        "", "YOLO-style ONNX model (v5 or v8 output, n_labels classes); empty: the project's own"
    )
    conf_threshold: float | None = setting(
        None, "keep boxes at least this confident; unset: the model's recommended one, else 0.25"
    )
    iou_threshold: float = setting(
        0.45, "boxes of one class overlapping a better one more than this are dropped"
    )
    detector_threads: int = setting(1, "onnxruntime threads for one frame (0: onnxruntime decides)")
    camera_fx: float = setting(535.4, "depth camera focal length x, pixels (default: TUM freiburg3)")
    camera_fy: float = setting(539.2, "depth camera focal length y, pixels")
    camera_cx: float = setting(320.1, "depth camera principal point x, pixels")
    camera_cy: float = setting(247.6, "depth camera principal point y, pixels")
    depth_scale: float = setting(TUM_DEPTH_SCALE, "depth units per metre of the depth PNGs (TUM: 5000)")
    rgbd_max_dt: float = setting(
        DEFAULT_MAX_DT, "RGB and depth images further apart (seconds) are not paired"
    )

    def problems(self) -> list[str]:
        problems = []
        if self.conf_threshold is not None and not 0.0 <= self.conf_threshold <= 1.0:
            problems.append(f"conf_threshold must be in [0, 1], got {self.conf_threshold}")
        if not 0.0 < self.iou_threshold <= 1.0:
            problems.append(f"iou_threshold must be in (0, 1], got {self.iou_threshold}")
        if self.detector_threads < 0:
            problems.append(f"detector_threads must be >= 0 (0: automatic), got {self.detector_threads}")
        # The same rules as CameraIntrinsics, checked here without loading the detection stack.
        for name in ("camera_fx", "camera_fy", "depth_scale"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                problems.append(f"{name} must be a positive number, got {value}")
        if not (math.isfinite(self.camera_cx) and math.isfinite(self.camera_cy)):
            problems.append(f"camera_cx, camera_cy must be finite, got ({self.camera_cx}, {self.camera_cy})")
        if not (math.isfinite(self.rgbd_max_dt) and self.rgbd_max_dt > 0):
            problems.append(f"rgbd_max_dt must be > 0 (seconds), got {self.rgbd_max_dt}")
        return problems

    def camera(self) -> CameraIntrinsics:
        """The depth camera these settings describe."""
        from swarmrec.detection.points import CameraIntrinsics  # onnxruntime and OpenCV: rgbd mode only

        return CameraIntrinsics(
            self.camera_fx, self.camera_fy, self.camera_cx, self.camera_cy, self.depth_scale
        )


@dataclass(frozen=True)
class VprSettings(Component):
    """Full-image place recognition (docs/vpr.md): the descriptor model, the centres and
    their owners, how queries carry descriptors."""

    title: ClassVar[str] = "full-image place recognition"

    place_method: PlaceMethod = setting(
        "constellations",
        "what the detector sends each frame to: constellations (the descriptor service's two-step "
        "query) or dvpr (a full-image descriptor to its robot's place-owner; rgbd mode only)",
    )
    descriptor_model: str = setting("", "the full-image descriptor's ONNX model; empty: the project's own")
    descriptor_threads: int = setting(1, "onnxruntime threads describing one frame (0: onnxruntime decides)")
    vpr_centres: str = setting(
        "",
        "k-means centres (.npz, one array per k; swarmrec vpr centres makes them); empty: the shipped "
        "models/descriptor/centres.npz. k = n_robots x vpr_clusters_per_robot",
    )
    vpr_clusters_per_robot: int = setting(1, "clusters each robot owns (the paper's c)")
    vpr_assignment_seed: int = setting(0, "seed of the paper's random assignment of clusters to robots")
    vpr_assignment: Path | None = setting(
        None, "an assignment table (JSON, swarmrec.vpr.assignment/1) instead of the seeded random one"
    )
    vpr_wire_code: VprCode = setting(
        "int8",
        "how a query carries its descriptor to the owner: int8 (4 + d bytes, recall within 0.1 point) "
        "or float32 (4 d bytes, the paper's)",
    )
    vpr_snapshot_every: int = setting(
        1000, "an owner saves its faiss index after this many new descriptors (and when it stops)"
    )
    vpr_rebalance_every_s: float = setting(
        0.0,
        "the coordinator (lowest live place-owner) re-balances the cluster owners this often, seconds, "
        "when at least vpr_rebalance_min_queries arrived since the last table (0: only when asked, "
        "the rebalance endpoint; docs/vpr.md)",
    )
    vpr_rebalance_min_queries: int = setting(
        100, "queries since the last table a timed re-balancing needs (fewer: the table stays)"
    )
    vpr_rebalance_slack: float = setting(
        0.25, "re-balancing capacity: (1 + slack) x an even share of the queries; busier clusters split"
    )
    vpr_copy_share: float = setting(
        1.0,
        "after a re-balancing, this share of descriptors nearest a cell boundary is also stored at the "
        "next cells' owners (1: every descriptor, 0: none)",
    )
    vpr_copy_neighbours: int = setting(
        2, "after a re-balancing, copies go to at most this many other robots (docs/vpr.md: 2 generalises)"
    )

    def problems(self) -> list[str]:
        problems = []
        if self.place_method not in PLACE_METHODS:
            problems.append(f"place_method must be {' or '.join(PLACE_METHODS)}, got {self.place_method!r}")
        if self.vpr_wire_code not in VPR_CODES:
            problems.append(f"vpr_wire_code must be {' or '.join(VPR_CODES)}, got {self.vpr_wire_code!r}")
        if self.descriptor_threads < 0:
            problems.append(f"descriptor_threads must be >= 0 (0: automatic), got {self.descriptor_threads}")
        if self.vpr_clusters_per_robot < 1:
            problems.append(f"vpr_clusters_per_robot must be >= 1, got {self.vpr_clusters_per_robot}")
        if self.vpr_snapshot_every < 1:
            problems.append(f"vpr_snapshot_every must be >= 1, got {self.vpr_snapshot_every}")
        if not (math.isfinite(self.vpr_rebalance_every_s) and self.vpr_rebalance_every_s >= 0):
            problems.append(
                f"vpr_rebalance_every_s must be >= 0 (0: only when asked), got {self.vpr_rebalance_every_s}"
            )
        if self.vpr_rebalance_min_queries < 1:
            problems.append(f"vpr_rebalance_min_queries must be >= 1, got {self.vpr_rebalance_min_queries}")
        if not (math.isfinite(self.vpr_rebalance_slack) and self.vpr_rebalance_slack >= 0):
            problems.append(f"vpr_rebalance_slack must be >= 0, got {self.vpr_rebalance_slack}")
        if not 0.0 <= self.vpr_copy_share <= 1.0:
            problems.append(f"vpr_copy_share must be in [0, 1], got {self.vpr_copy_share}")
        if self.vpr_copy_neighbours < 1:
            problems.append(f"vpr_copy_neighbours must be >= 1, got {self.vpr_copy_neighbours}")
        return problems


@dataclass(frozen=True)
class LandmarkSettings(Component):
    """The landmarks the classifier and fusion share."""

    title: ClassVar[str] = "landmarks"

    n_classes: int = setting(19, "classes of the shared class list (the paper's street has 19 landmarks)")

    def problems(self) -> list[str]:
        return [] if self.n_classes >= 2 else [f"n_classes must be >= 2, got {self.n_classes}"]


@dataclass(frozen=True)
class ClassifierSettings(Component):
    """The detector's classifier mode: the landmark CNN."""

    title: ClassVar[str] = "detector, classifier mode"

    classifier_model: str = setting("", "the landmark classifier's ONNX model; empty: the project's own")
    max_view_pixels: int = setting(
        1 << 22, "a view (PNG or JPEG) whose header claims more pixels is refused before decoding (TOO_LARGE)"
    )

    def problems(self) -> list[str]:
        return (
            [] if self.max_view_pixels >= 1 else [f"max_view_pixels must be >= 1, got {self.max_view_pixels}"]
        )


@dataclass(frozen=True)
class FusionSettings(Component):
    """Cooperative landmark recognition: the weight law and the flooding's limits."""

    title: ClassVar[str] = "fusion"

    fusion_law: FusionLaw = setting(
        "paper", "weight law of a received message: paper (Eq. 16) or agreement (docs/fusion.md)"
    )
    fusion_lambda: float | None = setting(
        None, "lambda of Eq. 14; unset: the law's own (paper 2, agreement 1)"
    )
    fusion_r_max: int = setting(0, "r_max of Sec. 3.4, the most hops a message travels; 0: no limit")
    fusion_early_messages: int = setting(
        1024, "messages kept per round that arrive before this robot starts that round"
    )
    fusion_max_round_jump: int = setting(
        DEFAULT_MAX_ROUND_JUMP,
        "a new round id is at most this far ahead of the current one (ids count modulo 2^32)",
    )

    def problems(self) -> list[str]:
        problems = []
        if self.fusion_law not in ("paper", "agreement"):
            problems.append(f"fusion_law must be paper or agreement, got {self.fusion_law!r}")
        if self.fusion_lambda is not None and not (
            math.isfinite(self.fusion_lambda) and self.fusion_lambda >= 0
        ):
            problems.append(f"fusion_lambda must be finite and >= 0, got {self.fusion_lambda}")
        if self.fusion_r_max < 0:
            problems.append(f"fusion_r_max must be >= 0 (0: no limit), got {self.fusion_r_max}")
        if self.fusion_early_messages < 0:
            problems.append(f"fusion_early_messages must be >= 0, got {self.fusion_early_messages}")
        if not 1 <= self.fusion_max_round_jump < 2**31:
            problems.append(f"fusion_max_round_jump must be in [1, 2^31), got {self.fusion_max_round_jump}")
        return problems


@dataclass(frozen=True)
class GatewaySettings(Component):
    """The gRPC gateway: where clients in any language reach the swarm (docs/gateway.md)."""

    title: ClassVar[str] = "gateway"

    grpc_host: str = setting("127.0.0.1", "address the gRPC port listens on (0.0.0.0 in a container)")
    grpc_port: int = setting(50051, "the gRPC port (0: a free one, printed in the ready line)")
    grpc_cert: Path | None = setting(
        None, "server certificate of the gRPC port (PEM); unset: this process's own from pki_dir"
    )
    grpc_key: Path | None = setting(None, "its private key; unset: this process's own from pki_dir")
    grpc_client_auth: bool = setting(
        True, "require a client certificate signed by the swarm CA on the gRPC port (mtls)"
    )
    grpc_workers: int = setting(16, "threads serving gRPC calls (each open stream holds one)")
    grpc_max_streams: int = setting(8, "event streams open at once; more are refused RESOURCE_EXHAUSTED")
    grpc_max_streams_per_caller: int = setting(
        4,
        "event streams one caller (its certificate's name; without TLS, its address) may hold open "
        "at once, so one cannot take every stream; more are refused RESOURCE_EXHAUSTED",
    )
    grpc_stream_buffer: int = setting(
        4096, "events queued for a slow stream reader; past it the stream ends RESOURCE_EXHAUSTED"
    )
    web_host: str = setting("127.0.0.1", "address the live view (a web page of the swarm) listens on")
    web_port: int = setting(
        0, "the live view's port (0: a free one; its address, with its token, in the ready line; -1: off)"
    )
    web_max_streams: int = setting(4, "live-view event streams open at once; more are answered 503")

    def problems(self) -> list[str]:
        problems = []
        if not 0 <= self.grpc_port <= 65535:
            problems.append(f"grpc_port must be 0 .. 65535, got {self.grpc_port}")
        if (self.grpc_cert is None) != (self.grpc_key is None):
            problems.append("grpc_cert and grpc_key go together")
        if self.grpc_workers < 2:
            problems.append(f"grpc_workers must be >= 2, got {self.grpc_workers}")
        if not 1 <= self.grpc_max_streams < self.grpc_workers:
            problems.append(
                f"grpc_max_streams must be 1 .. grpc_workers - 1 ({self.grpc_workers - 1}), "
                f"got {self.grpc_max_streams}"
            )
        if not 1 <= self.grpc_max_streams_per_caller <= self.grpc_max_streams:
            problems.append(
                f"grpc_max_streams_per_caller must be 1 .. grpc_max_streams ({self.grpc_max_streams}), "
                f"got {self.grpc_max_streams_per_caller}"
            )
        if self.grpc_stream_buffer < 1:
            problems.append(f"grpc_stream_buffer must be >= 1, got {self.grpc_stream_buffer}")
        if not -1 <= self.web_port <= 65535:
            problems.append(f"web_port must be -1 (off) or 0 .. 65535, got {self.web_port}")
        if not 1 <= self.web_max_streams <= 64:
            problems.append(f"web_max_streams must be 1 .. 64, got {self.web_max_streams}")
        return problems


@dataclass(frozen=True)
class SlamServiceSettings(Component):
    """The live distributed Gauss-Seidel: where a robot's pose graph is, how long it waits (docs/slam.md)."""

    title: ClassVar[str] = "distributed SLAM"

    slam_folder: Path | None = setting(
        None, "folder of the robots' g2o files; this robot reads <folder>/<robot>.g2o (its own only)"
    )
    slam_peer_timeout_s: float = setting(
        10.0,
        "a team member silent this long while this robot waits for it is declared gone and the solve "
        "ends at the last consistent estimate",
    )
    slam_max_iterations: int = setting(
        10000, "a solve whose max_iterations is larger is refused (INVALID_ARGUMENT)"
    )

    def problems(self) -> list[str]:
        problems = []
        if not (math.isfinite(self.slam_peer_timeout_s) and self.slam_peer_timeout_s > 0):
            problems.append(f"slam_peer_timeout_s must be > 0, got {self.slam_peer_timeout_s}")
        if self.slam_max_iterations < 1:
            problems.append(f"slam_max_iterations must be >= 1, got {self.slam_max_iterations}")
        return problems
