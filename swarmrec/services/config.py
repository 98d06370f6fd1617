"""Service settings: one frozen object, layered defaults < file < environment < flags.

Every service reads the same :class:`ServiceSettings` (a field a service does
not use is ignored), so one TOML file or one set of ``SWARMREC_*`` variables
configures a whole robot::

    # robot3.toml
    swarm = "lab"
    robot = 3
    n_robots = 10
    connect = ["tcp/10.0.0.1:7447", "tcp/10.0.0.2:7447"]
    data_dir = "/var/lib/swarmrec"

    SWARMREC_ROBOT=3 swarmrec serve index-shard --config robot3.toml --n-robots 10

Lists are comma-separated in the environment. Flags reuse zenoh's own names
(``--mode --connect --listen``).
"""

from __future__ import annotations

import argparse
import itertools
import math
import os
import tomllib
import types
import typing
from collections.abc import Mapping, Sequence
from dataclasses import MISSING, dataclass, fields, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from swarmrec.core.presets import get_preset
from swarmrec.datasets.tum import DEFAULT_MAX_DT, TUM_DEPTH_SCALE
from swarmrec.errors import ConfigError
from swarmrec.services.keys import validate_swarm_name

if TYPE_CHECKING:
    from swarmrec.detection.points import CameraIntrinsics

__all__ = [
    "DETECTOR_MODES",
    "ENV_PREFIX",
    "ServiceSettings",
    "add_arguments",
    "load_settings",
    "settings_to_flags",
]

ENV_PREFIX = "SWARMREC_"

ZenohMode = Literal["client", "peer", "router"]
FusionLaw = Literal["paper", "agreement"]
DetectorMode = Literal["replay", "rgbd", "classifier"]
DETECTOR_MODES: tuple[str, ...] = ("replay", "rgbd", "classifier")


@dataclass(frozen=True)
class ServiceSettings:
    """Everything a service needs; validated on construction."""

    #: Name of the swarm: a key segment, so swarms sharing a router never mix.
    swarm: str = "default"
    #: This robot's id (0 .. n_robots - 1); the index shard of robot k owns label range k.
    robot: int = 0
    #: Robots in the swarm (= number of label ranges).
    n_robots: int = 1
    #: Zenoh mode of the session.
    mode: ZenohMode = "client"
    #: Router endpoints to connect to (several give failover).
    connect: tuple[str, ...] = ("tcp/127.0.0.1:7447",)
    #: Endpoints to listen on (routers).
    listen: tuple[str, ...] = ()
    #: Place-recognition preset (see swarmrec.core.presets).
    preset: str = "paper"
    #: Size of the swarm's label list.
    n_labels: int = 80
    #: Label range boundaries (n_robots + 1 values); empty: even ranges.
    label_bounds: tuple[int, ...] = ()
    #: Where stateful services keep their data; empty: memory only (lost on restart).
    data_dir: Path | None = None
    #: Flush every stored record with fsync (survives power loss, costs ~1 ms a record).
    fsync: bool = False
    #: Prometheus endpoint: port (0 picks a free one, -1 serves none) and address.
    metrics_port: int = 0
    metrics_host: str = "127.0.0.1"
    #: Worker threads per endpoint (callbacks only enqueue; workers do the work).
    workers: int = 2
    #: How long a service waits for a peer's reply, seconds.
    request_timeout_s: float = 2.0
    #: Shards answer from the frames stored before the query's step (lock-step replay).
    lockstep: bool = False
    #: Largest request payload accepted, bytes.
    max_message_bytes: int = 1 << 20
    #: A verified match at least this good is published as a loop closure.
    loop_closure_min_score: float = 0.3
    #: Detector: "replay" sends recorded constellations; "rgbd" detects objects in RGB-D
    #: frames with an ONNX model (docs/detector.md); "classifier" runs the landmark classifier.
    detector_mode: DetectorMode = "replay"
    #: Detector: what to replay: a folder or zip of constellation files (replay), a TUM
    #: RGB-D folder with rgb.txt and depth.txt (rgbd).
    dataset: str = ""
    #: Detector: label names file for the dataset, or the model's classes (default: COCO).
    labels_file: Path | None = None
    #: Detector: frames replayed by each robot; 0 splits the dataset evenly over n_robots.
    frames_per_robot: int = 0
    #: Detector (rgbd): YOLO-style ONNX model (v5 or v8 output, n_labels classes); empty: the
    #: project's own (models/detector/office_detector.onnx, or under $SWARMREC_MODELS).
    detector_model: str = ""
    #: Detector (rgbd): keep boxes at least this confident; unset: the recommended threshold in
    #: the model's metrics.json when it has one, else 0.25.
    conf_threshold: float | None = None
    #: Detector (rgbd): boxes of one class overlapping a better one more than this are dropped (NMS).
    iou_threshold: float = 0.45
    #: Detector (rgbd): onnxruntime threads for one frame (0: onnxruntime decides).
    detector_threads: int = 1
    #: Detector (rgbd): depth camera intrinsics in pixels (defaults: TUM freiburg3, 640x480).
    camera_fx: float = 535.4
    camera_fy: float = 539.2
    camera_cx: float = 320.1
    camera_cy: float = 247.6
    #: Detector (rgbd): depth units per metre of the depth PNGs (TUM: 5000).
    depth_scale: float = TUM_DEPTH_SCALE
    #: Detector (rgbd): RGB and depth images further apart than this (seconds) are not paired.
    rgbd_max_dt: float = DEFAULT_MAX_DT
    #: Detector (classifier): the landmark classifier's ONNX model; empty: the project's own.
    classifier_model: str = ""
    #: Fusion: classes of the shared class list (the paper's street has 19 landmarks).
    n_classes: int = 19
    #: Fusion: weight law P(R) of a received message (swarmrec.fusion.wnbc): "paper" (Eq. 16)
    #: or "agreement" (the paper's weight as a prior, updated with the message).
    fusion_law: FusionLaw = "paper"
    #: Fusion: lambda of Eq. 14; unset: the law's own default (paper 2, agreement 1).
    fusion_lambda: float | None = None
    #: Fusion: r_max of Sec. 3.4, the most hops a message travels; 0: no limit.
    fusion_r_max: int = 0
    #: Fusion: messages kept per round that arrive before this robot starts that round.
    fusion_early_messages: int = 1024
    #: Logging level.
    log_level: str = "INFO"

    def __post_init__(self) -> None:
        problems: list[str] = []
        try:
            validate_swarm_name(self.swarm)
        except ConfigError as e:
            problems.append(str(e))
        if self.n_robots < 1:
            problems.append(f"n_robots must be >= 1, got {self.n_robots}")
        if not 0 <= self.robot < max(self.n_robots, 1):
            problems.append(f"robot must be in [0, n_robots={self.n_robots}), got {self.robot}")
        if self.mode not in ("client", "peer", "router"):
            problems.append(f"mode must be client, peer or router, got {self.mode!r}")
        if self.mode == "router" and not self.listen:
            problems.append("a router needs at least one --listen endpoint")
        if self.mode == "client" and not self.connect:
            problems.append("a client needs at least one --connect endpoint")
        if self.n_labels < 1:
            problems.append(f"n_labels must be >= 1, got {self.n_labels}")
        if self.label_bounds:
            b = self.label_bounds
            if (
                len(b) != self.n_robots + 1
                or b[0] != 0
                or b[-1] != self.n_labels
                or any(x >= y for x, y in itertools.pairwise(b))
            ):
                problems.append(
                    f"label_bounds must be {self.n_robots + 1} increasing values from 0 to "
                    f"{self.n_labels}, got {list(b)}"
                )
        elif self.n_labels < self.n_robots:
            problems.append(f"{self.n_labels} labels cannot be split over {self.n_robots} robots")
        if not -1 <= self.metrics_port <= 65535:
            problems.append(f"metrics_port must be -1 .. 65535, got {self.metrics_port}")
        if self.workers < 1:
            problems.append(f"workers must be >= 1, got {self.workers}")
        if not (math.isfinite(self.request_timeout_s) and self.request_timeout_s > 0):
            problems.append(f"request_timeout_s must be > 0, got {self.request_timeout_s}")
        if not 1024 <= self.max_message_bytes <= 1 << 24:
            # Above 16 MiB a stored record would not fit the record log (services/storage.py).
            problems.append(f"max_message_bytes must be 1024 .. {1 << 24}, got {self.max_message_bytes}")
        if self.frames_per_robot < 0:
            problems.append(f"frames_per_robot must be >= 0, got {self.frames_per_robot}")
        if self.detector_mode not in DETECTOR_MODES:
            problems.append(f"detector_mode must be {', '.join(DETECTOR_MODES)}; got {self.detector_mode!r}")
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
        if self.n_classes < 2:
            problems.append(f"n_classes must be >= 2, got {self.n_classes}")
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
        try:
            get_preset(self.preset)
        except ConfigError as e:
            problems.append(str(e))
        if problems:
            raise ConfigError("invalid settings: " + "; ".join(problems))

    def camera(self) -> CameraIntrinsics:
        """The rgbd detector's depth camera."""
        from swarmrec.detection.points import CameraIntrinsics

        return CameraIntrinsics(
            self.camera_fx, self.camera_fy, self.camera_cx, self.camera_cy, self.depth_scale
        )

    def with_(self, **changes: Any) -> ServiceSettings:
        """A copy with some settings changed (validated again)."""
        return replace(self, **changes)


# --- layering ---------------------------------------------------------------

_HINTS = typing.get_type_hints(ServiceSettings)


def _base_type(name: str) -> Any:
    hint = _HINTS[name]
    if isinstance(hint, types.UnionType):  # X | None
        return next(a for a in typing.get_args(hint) if a is not type(None))
    return hint


def _convert(name: str, value: Any) -> Any:
    """``value`` (from TOML, the environment or a flag) as field ``name``'s type."""
    base = _base_type(name)
    origin = typing.get_origin(base)
    try:
        if origin is tuple:
            item = typing.get_args(base)[0]
            items = [v.strip() for v in value.split(",") if v.strip()] if isinstance(value, str) else value
            return tuple(item(v) for v in items)
        if base is bool:
            if isinstance(value, bool):
                return value
            text = str(value).strip().lower()
            if text in ("1", "true", "yes", "on"):
                return True
            if text in ("0", "false", "no", "off"):
                return False
            raise ValueError(f"not a boolean: {value!r}")
        if base is Path:
            return Path(value) if str(value) else None
        if origin is Literal:
            return str(value)
        if base is int and (isinstance(value, bool) or (isinstance(value, float) and not value.is_integer())):
            # TOML gives typed values: int(2.9) or int(True) would silently become 2 or 1.
            raise ValueError(f"not an integer: {value!r}")
        return base(value)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"setting {name}: cannot read {value!r} ({e})") from None


def _from_file(path: Path) -> dict[str, Any]:
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as e:
        raise ConfigError(f"cannot read config file {path}: {e.strerror}") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"config file {path} is not valid TOML: {e}") from None
    known = {f.name for f in fields(ServiceSettings)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise ConfigError(f"config file {path}: unknown settings {', '.join(unknown)}")
    return {k: _convert(k, v) for k, v in data.items()}


def _from_env(env: Mapping[str, str]) -> dict[str, Any]:
    out = {}
    for f in fields(ServiceSettings):
        key = ENV_PREFIX + f.name.upper()
        if key in env:
            out[f.name] = _convert(f.name, env[key])
    return out


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """One flag per setting (default None, so unset flags do not override lower layers)."""
    parser.add_argument("--config", type=Path, help="TOML file of settings (below env and flags)")
    for f in fields(ServiceSettings):
        default = f.default if f.default is not MISSING else None
        shown = ",".join(map(str, default)) if isinstance(default, tuple) else default
        parser.add_argument(
            _flag(f.name),
            dest=f.name,
            default=None,
            metavar=f.name.upper(),
            help=f"(default: {shown!r}; env {ENV_PREFIX}{f.name.upper()})",
        )


def load_settings(
    args: argparse.Namespace | None = None,
    *,
    env: Mapping[str, str] | None = None,
    config: Path | None = None,
    defaults: Mapping[str, Any] | None = None,
) -> ServiceSettings:
    """Settings from the layers, lowest first: ``defaults`` (a service's own),
    the TOML file, ``SWARMREC_*`` environment variables, then flags."""
    layered: dict[str, Any] = dict(defaults or {})
    path = config if config is not None else getattr(args, "config", None)
    if path is None and (os.environ if env is None else env).get(ENV_PREFIX + "CONFIG"):
        path = Path((env or os.environ)[ENV_PREFIX + "CONFIG"])
    if path is not None:
        layered.update(_from_file(Path(path)))
    layered.update(_from_env(os.environ if env is None else env))
    if args is not None:
        for f in fields(ServiceSettings):
            value = getattr(args, f.name, None)
            if value is not None:
                layered[f.name] = _convert(f.name, value)
    return ServiceSettings(**layered)


def settings_to_flags(settings: ServiceSettings, names: Sequence[str]) -> list[str]:
    """Command-line flags that reproduce ``names`` of ``settings`` (for launching processes)."""
    out: list[str] = []
    for name in names:
        value = getattr(settings, name)
        if value is None:
            continue
        text = ",".join(map(str, value)) if isinstance(value, tuple) else str(value)
        out += [_flag(name), text]
    return out
