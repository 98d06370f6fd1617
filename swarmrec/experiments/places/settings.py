"""What one place-recognition run is (the dataset, the swarm's size and preset, the pace),
and what each of its stages receives of it (:class:`ReplaySettings`, :class:`ReportSettings`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from swarmrec.core.presets import get_preset
from swarmrec.datasets.tum import DEFAULT_MAX_DT
from swarmrec.errors import ConfigError
from swarmrec.evaluation.source import SYNTHETIC, DatasetSource
from swarmrec.runtime.settings import BusSettings, DataPlane
from swarmrec.services.settings import IndexSettings, PlaceSettings, WirePositions

__all__ = ["PixelSettings", "PlacesSettings", "ReplaySettings", "ReportSettings"]


@dataclass(frozen=True)
class PixelSettings:
    """Starting from pixels: the detectors find objects in RGB-D frames."""

    #: Render the synthetic world as RGB-D frames and detect objects in them.
    from_pixels: bool = False
    #: A TUM-format RGB-D folder (rgb.txt, depth.txt, images) to detect objects in.
    rgbd: Path | None = None
    #: The detectors' ONNX model; empty: the project's own.
    model: str = ""
    #: The detectors' confidence threshold; None: the model's recommended one.
    conf_threshold: float | None = None
    #: onnxruntime threads of each detector.
    detector_threads: int = 1
    #: Depth camera fx, fy, cx, cy; None: a render's own (boxes.json) or TUM fr3's.
    camera: tuple[float, float, float, float] | None = None
    #: Depth units per metre; None: a render's own or TUM's 5000.
    depth_scale: float | None = None
    #: RGB and depth images further apart (seconds) are not paired.
    rgbd_max_dt: float = DEFAULT_MAX_DT

    def __post_init__(self) -> None:
        if self.from_pixels and self.rgbd is not None:
            raise ConfigError("--from-pixels renders the synthetic world; --rgbd names a recording: pick one")
        if self.conf_threshold is not None and not 0.0 <= self.conf_threshold <= 1.0:
            raise ConfigError(f"conf_threshold must be in [0, 1], got {self.conf_threshold}")
        if self.detector_threads < 0:
            raise ConfigError(f"detector_threads must be >= 0, got {self.detector_threads}")
        if self.camera is not None and len(self.camera) != 4:
            raise ConfigError(f"camera must be fx, fy, cx, cy, got {self.camera}")

    @property
    def enabled(self) -> bool:
        """Whether the detectors start from RGB-D frames."""
        return self.from_pixels or self.rgbd is not None


@dataclass(frozen=True)
class ReplaySettings:
    """What the replay stage needs of a run (``PlacesSettings.replay()``)."""

    robots: int
    #: The swarm's name (its key expressions' swarm segment).
    swarm: str
    #: "lockstep", "fast" or a rate in frames per second.
    pace: str
    #: Seconds a request waits; a step or an idle spell waits six times that.
    request_timeout_s: float
    progress: bool = True

    @property
    def lockstep(self) -> bool:
        return self.pace == "lockstep"


@dataclass(frozen=True)
class ReportSettings:
    """What the report stage needs of a run (``PlacesSettings.report()``): where it goes, what
    it draws and checks, and the run's own settings it records."""

    out: Path
    robots: int
    #: "lockstep", "fast" or a rate in frames per second.
    pace: str
    #: The dataset as the run named it (``synthetic``, a folder or a zip).
    dataset: str
    #: Index shards that hold each label group.
    replicas: int
    plots: bool = True
    #: Compare the pair scores with the offline decentralized evaluation (lock-step only).
    check_offline: bool = True

    @property
    def lockstep(self) -> bool:
        return self.pace == "lockstep"


@dataclass(frozen=True)
class PlacesSettings:
    """One place-recognition run through a swarm; validated on construction."""

    source: DatasetSource = field(default_factory=DatasetSource)
    robots: int = 10
    preset: str = "paper"
    #: "lockstep", "fast" (free replay, as fast as answered) or a rate in frames per second.
    pace: str = "lockstep"
    out: Path = Path("runs/swarm")
    swarm: str = "local"
    request_timeout_s: float = 5.0
    plots: bool = True
    progress: bool = True
    #: Compare the pair scores with the offline decentralized evaluation (lock-step only).
    check_offline: bool = True
    pixels: PixelSettings = field(default_factory=PixelSettings)
    #: How the swarm carries object positions: "mm" (compact) or "exact" (the published scores).
    wire_positions: WirePositions = "mm"
    #: Which implementation serves the kinds that have a compiled one (python or compiled;
    #: docs/dataplane.md).
    data_plane: DataPlane = "compiled"
    #: The elastic index: replicas per label group, rebalancing (docs/elastic-index.md).
    index: IndexSettings = field(default_factory=IndexSettings)

    def __post_init__(self) -> None:
        if self.robots < 1:
            raise ConfigError(f"robots must be >= 1, got {self.robots}")
        if self.pace not in ("lockstep", "fast"):
            try:
                rate = float(self.pace)
            except ValueError:
                rate = -1.0
            if not (math.isfinite(rate) and rate > 0):
                raise ConfigError(f"pace must be lockstep, fast or a rate > 0 (frames/s), got {self.pace!r}")
        get_preset(self.preset)
        if self.pixels.from_pixels and not self.source.synthetic:
            raise ConfigError(
                "--from-pixels renders the synthetic world (--dataset synthetic); "
                "for a recording use --rgbd DIR"
            )
        if self.pixels.rgbd is not None and not self.source.synthetic:
            raise ConfigError("--rgbd DIR replaces --dataset: give one of them")
        # The bus checks the swarm name and timeout; the services' settings the preset and positions.
        self.bus()
        self.places(80, ())

    @property
    def lockstep(self) -> bool:
        return self.pace == "lockstep"

    def bus(self) -> BusSettings:
        """The swarm's bus settings."""
        return BusSettings(
            swarm=self.swarm,
            n_robots=self.robots,
            request_timeout_s=self.request_timeout_s,
            data_plane=self.data_plane,
        )

    def places(self, n_labels: int, bounds: tuple[int, ...]) -> PlaceSettings:
        """The services' place-recognition settings for this run's label list and ranges."""
        return PlaceSettings(
            preset=self.preset,
            n_labels=n_labels,
            label_bounds=bounds,
            lockstep=self.lockstep,
            wire_positions=self.wire_positions,
        )

    def replay(self) -> ReplaySettings:
        """The replay stage's settings."""
        return ReplaySettings(
            robots=self.robots,
            swarm=self.swarm,
            pace=self.pace,
            request_timeout_s=self.request_timeout_s,
            progress=self.progress,
        )

    def report(self) -> ReportSettings:
        """The report stage's settings."""
        return ReportSettings(
            out=self.out,
            robots=self.robots,
            pace=self.pace,
            dataset=self.source.dataset,
            replicas=self.index.replicas,
            plots=self.plots,
            check_offline=self.check_offline,
        )

    def with_(self, **changes: Any) -> PlacesSettings:
        return replace(self, **changes)

    # --- swarm.json: what a compose swarm records of the run it was composed for ------

    def record(self) -> dict[str, Any]:
        """What ``swarmrec run --attach`` needs to run this again against the same swarm."""
        s = self.source
        return {
            "dataset": s.dataset,
            "seed": s.seed,
            "frames": s.frames,
            "labels": str(s.labels) if s.labels else None,
            "groundtruth": str(s.groundtruth) if s.groundtruth else None,
            "robots": self.robots,
            "preset": self.preset,
            "lockstep": self.lockstep,
            "swarm": self.swarm,
            "request_timeout_s": self.request_timeout_s,
            "wire_positions": self.wire_positions,
            "replicas": self.index.replicas,
            "rebalance_target": self.index.rebalance_target,
            "data_plane": self.data_plane,
        }

    @classmethod
    def from_record(cls, record: dict[str, Any], **changes: Any) -> PlacesSettings:
        """The run a compose swarm was composed for (``changes``: pace, out, plots ...)."""
        try:
            source = DatasetSource(
                dataset=str(record.get("dataset", SYNTHETIC)),
                seed=int(record.get("seed", 0)),
                frames=record.get("frames"),
                labels=Path(record["labels"]) if record.get("labels") else None,
                groundtruth=Path(record["groundtruth"]) if record.get("groundtruth") else None,
            )
            base = cls(
                source=source,
                robots=int(record["robots"]),
                preset=str(record["preset"]),
                swarm=str(record["swarm"]),
                request_timeout_s=float(record["request_timeout_s"]),
                pace="lockstep" if record.get("lockstep", True) else "fast",
                wire_positions=record.get("wire_positions", "mm"),
                data_plane=record.get("data_plane", "compiled"),
                index=IndexSettings(
                    replicas=int(record.get("replicas", IndexSettings.replicas)),
                    rebalance_target=float(record.get("rebalance_target", IndexSettings.rebalance_target)),
                ),
            )
        except (KeyError, TypeError, ValueError) as e:
            raise ConfigError(f"the swarm file's experiment record is not a places run: {e}") from None
        composed_lockstep = base.lockstep
        run = base.with_(**changes)
        if run.lockstep != composed_lockstep:
            raise ConfigError(
                f"the swarm was started for {'lock-step' if composed_lockstep else 'free'} replay; "
                + (
                    f"--pace {run.pace} needs one started with --free (swarmrec up --free, compose up --free)"
                    if composed_lockstep
                    else "a lock-step replay needs one started without --free"
                )
            )
        return run
