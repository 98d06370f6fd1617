"""The main job: a local swarm of N robots replays a dataset and reports.

``main(settings)`` writes the dataset (the built-in synthetic world by
default), starts a zenoh router and every robot's detector, descriptor,
index-shard and verifier as separate processes, replays the dataset split
into N sub-trajectories, scrapes every service's Prometheus endpoint, stops
everything and writes the report under ``settings.out`` (docs/swarm-report.md):
summary.json, the pair scores, the loop closures and PNG figures.

In lock-step mode (the default) step t of every robot finishes before step
t + 1 starts, exactly as the offline decentralized evaluation simulates, and
the report checks that the swarm's pair scores equal the offline ones.

From pixels (``from_pixels`` renders the synthetic world, ``rgbd`` names a
TUM-format folder) the detectors detect objects in RGB-D frames instead of
replaying constellations, and the report scores the constellations they made
(:mod:`swarmrec.swarm.pixels`, docs/detector.md).
"""

from __future__ import annotations

import math
import shutil
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from tqdm import tqdm

from swarmrec.core.association import warm_up
from swarmrec.core.presets import get_preset
from swarmrec.core.split import split_frames
from swarmrec.core.types import ConstellationSequence, Trajectory
from swarmrec.datasets.tum import DEFAULT_MAX_DT
from swarmrec.errors import ConfigError
from swarmrec.services.config import ServiceSettings
from swarmrec.swarm.processes import LocalSwarm
from swarmrec.swarm.scrape import scrape
from swarmrec.wire import messages as pb
from swarmrec.wire.codec import constellation_from_proto, constellation_to_proto

__all__ = [
    "Replay",
    "SwarmSettings",
    "as_on_the_wire",
    "collect_loop_closures",
    "main",
    "prepare_dataset",
    "replay_free",
    "replay_lockstep",
    "swarm_label_bounds",
]

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class SwarmSettings:
    """One local swarm run; validated on construction."""

    dataset: str = "synthetic"
    seed: int = 0
    frames: int | None = None
    labels: Path | None = None
    groundtruth: Path | None = None
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
    #: Start from pixels: render the synthetic world as RGB-D frames and detect objects in them.
    from_pixels: bool = False
    #: Start from pixels: a TUM-format RGB-D folder (rgb.txt, depth.txt, images) to detect objects in.
    rgbd: Path | None = None
    #: From pixels: the detectors' ONNX model; empty: the project's own.
    model: str = ""
    #: From pixels: the detectors' confidence threshold; None: the model's recommended one.
    conf_threshold: float | None = None
    #: From pixels: onnxruntime threads of each detector.
    detector_threads: int = 1
    #: From pixels: depth camera fx, fy, cx, cy; None: a render's own (boxes.json) or TUM fr3's.
    camera: tuple[float, float, float, float] | None = None
    #: From pixels: depth units per metre; None: a render's own or TUM's 5000.
    depth_scale: float | None = None
    #: From pixels: RGB and depth images further apart (seconds) are not paired.
    rgbd_max_dt: float = DEFAULT_MAX_DT

    def __post_init__(self) -> None:
        if self.robots < 1:
            raise ConfigError(f"robots must be >= 1, got {self.robots}")
        if self.frames is not None and self.frames < 1:
            raise ConfigError(f"frames must be >= 1, got {self.frames}")
        if self.pace not in ("lockstep", "fast"):
            try:
                rate = float(self.pace)
            except ValueError:
                rate = -1.0
            if not (math.isfinite(rate) and rate > 0):
                raise ConfigError(f"pace must be lockstep, fast or a rate > 0 (frames/s), got {self.pace!r}")
        get_preset(self.preset)
        if self.from_pixels and self.rgbd is not None:
            raise ConfigError("--from-pixels renders the synthetic world; --rgbd names a recording: pick one")
        if self.from_pixels and self.dataset != "synthetic":
            raise ConfigError(
                "--from-pixels renders the synthetic world (--dataset synthetic); "
                "for a recording use --rgbd DIR"
            )
        if self.rgbd is not None and self.dataset != "synthetic":
            raise ConfigError("--rgbd DIR replaces --dataset: give one of them")
        if self.conf_threshold is not None and not 0.0 <= self.conf_threshold <= 1.0:
            raise ConfigError(f"conf_threshold must be in [0, 1], got {self.conf_threshold}")
        if self.detector_threads < 0:
            raise ConfigError(f"detector_threads must be >= 0, got {self.detector_threads}")
        if self.camera is not None and len(self.camera) != 4:
            raise ConfigError(f"camera must be fx, fy, cx, cy, got {self.camera}")

    @property
    def lockstep(self) -> bool:
        return self.pace == "lockstep"

    @property
    def pixels(self) -> bool:
        """Whether the detectors start from RGB-D frames."""
        return self.from_pixels or self.rgbd is not None


def as_on_the_wire(seq: ConstellationSequence) -> ConstellationSequence:
    """``seq`` as the services see it: positions rounded to the wire's millimetres."""
    out = [
        constellation_from_proto(constellation_to_proto(c, 0, 0), seq.n_labels) for c in seq.constellations
    ]
    return ConstellationSequence(
        seq.frame_ids, seq.timestamps, tuple(out), seq.label_names, seq.name, dict(seq.skipped)
    )


def prepare_dataset(
    settings: SwarmSettings,
) -> tuple[str, Path | None, ConstellationSequence, Trajectory | None]:
    """The dataset folder the detectors replay, and the sequence and poses it holds."""
    from swarmrec.datasets.constellations import read_constellations
    from swarmrec.datasets.labels import COCO_NAMES, read_label_names
    from swarmrec.datasets.tum import read_trajectory

    if settings.dataset == "synthetic":
        from swarmrec.synthetic import OfficeConfig, generate_office, write_dataset

        config = OfficeConfig(seed=settings.seed)
        if settings.frames is not None:
            config = OfficeConfig(seed=settings.seed, n_frames=settings.frames)
        folder = settings.out / "dataset"
        write_dataset(generate_office(config), folder, overwrite=True)
        source, labels_file = str(folder), None
    else:
        source, labels_file = settings.dataset, settings.labels
    names = read_label_names(labels_file) if labels_file else COCO_NAMES
    seq = read_constellations(Path(source), names)
    if settings.frames is not None and settings.dataset != "synthetic" and settings.frames < len(seq):
        # The detectors replay the folder; a subset is written for them.
        from swarmrec.datasets.constellations import write_constellations

        seq = seq.subset(range(settings.frames))
        folder = settings.out / "dataset"
        write_constellations(seq, folder)
        source = str(folder)
    gt_path = settings.groundtruth
    if gt_path is None and Path(source).is_dir() and (Path(source) / "groundtruth.txt").is_file():
        gt_path = Path(source) / "groundtruth.txt"
    return source, labels_file, seq, read_trajectory(gt_path) if gt_path else None


def swarm_label_bounds(
    settings: SwarmSettings, seq: ConstellationSequence | None, n_labels: int | None = None
) -> npt.NDArray[np.int64]:
    """The shards' label ranges for the preset (``balanced`` weighs labels by their frequency in ``seq``).

    ``seq`` may be None (frames not detected yet) for even ranges of ``n_labels``.
    """
    from swarmrec.core.association import build_table
    from swarmrec.evaluation.scoring import label_bounds, label_frequency_prior

    preset = get_preset(settings.preset)
    load = None
    if preset.ranges == "balanced":
        if seq is None:
            raise ConfigError(
                "the balanced preset balances label ranges on the dataset's label frequencies, which "
                "RGB-D frames do not have before detection (a synthetic render has them in its "
                "constellations/); use --preset paper"
            )
        load = label_frequency_prior(build_table(seq.constellations, seq.n_labels))
    labels = seq.n_labels if seq is not None else n_labels
    if labels is None:
        raise ValueError("swarm_label_bounds needs seq or n_labels")
    return label_bounds(preset, labels, settings.robots, load)


@dataclass
class Replay:
    """What a replay got back: the query reports, the slots with no answer, errors, timings."""

    reports: list[pb.QueryReport]
    missing: list[tuple[int, int]]  # (robot, step) slots with no answer
    errors: list[str]
    step_seconds: list[float]
    wall_s: float


def replay_lockstep(
    client: Any, blocks: list[range], settings: SwarmSettings, on_step: Callable[[int], None] | None
) -> Replay:
    per = max((len(b) for b in blocks), default=0)
    reports: list[pb.QueryReport] = []
    missing: list[tuple[int, int]] = []
    errors: list[str] = []
    step_s: list[float] = []
    t0 = time.perf_counter()
    step_timeout = 6 * settings.request_timeout_s
    with tqdm(
        total=per,
        desc=f"swarm x{settings.robots} lock-step",
        unit="step",
        disable=not settings.progress,
        leave=False,
    ) as bar:
        for t in range(per):
            ts = time.perf_counter()
            answered: set[int] = set()
            for item in client.step(t, step_timeout):
                if isinstance(item, Exception):
                    errors.append(f"step {t}: {item}")
                    continue
                answered.add(item.robot_id)
                if not item.finished:
                    reports.append(item.report)
            missing += [(r, t) for r, b in enumerate(blocks) if t < len(b) and r not in answered]
            step_s.append(time.perf_counter() - ts)
            bar.update(1)
            if on_step is not None:
                on_step(t)
    return Replay(reports, missing, errors, step_s, time.perf_counter() - t0)


def replay_free(client: Any, blocks: list[range], settings: SwarmSettings) -> Replay:
    import zenoh

    from swarmrec.services import keys

    rate = 0.0 if settings.pace == "fast" else float(settings.pace)
    expected = sum(len(b) for b in blocks)
    reports: list[pb.QueryReport] = []
    errors: list[str] = []
    key = keys.event(settings.swarm, "query", "*")
    t0 = time.perf_counter()
    with (
        client.session.declare_subscriber(key) as sub,
        tqdm(
            total=expected,
            desc=f"swarm x{settings.robots} at {settings.pace}",
            unit="frame",
            disable=not settings.progress,
            leave=False,
        ) as bar,
    ):
        for item in client.replay(rate):
            if isinstance(item, Exception):
                errors.append(f"replay: {item}")
        idle_limit = 6 * settings.request_timeout_s
        last = time.perf_counter()
        while len(reports) < expected:
            sample = sub.try_recv()
            if sample is None:
                if time.perf_counter() - last > idle_limit:
                    errors.append(f"no report for {idle_limit:g} s; {expected - len(reports)} frames missing")
                    break
                time.sleep(0.002)
                continue
            assert isinstance(sample, zenoh.Sample)
            reports.append(pb.QueryReport.FromString(sample.payload.to_bytes()))
            last = time.perf_counter()
            bar.update(1)
    seen = {(r.robot_id, r.frame_index) for r in reports}
    missing = [(r, t) for r, b in enumerate(blocks) for t in range(len(b)) if (r, t) not in seen]
    return Replay(reports, missing, errors, [], time.perf_counter() - t0)


def collect_loop_closures(client: Any, robots: int, replay: Replay) -> list[pb.LoopClosure]:
    """Every robot's loop closures after a replay; a robot that does not answer adds an
    error to ``replay`` rather than losing the others'."""
    closures: list[pb.LoopClosure] = []
    for r in range(robots):
        try:
            closures += client.loop_closures(r)
        except Exception as e:
            replay.errors.append(f"loop closures of robot {r}: {e}")
    return closures


def main(
    settings: SwarmSettings,
    *,
    on_step: Callable[[int], None] | None = None,
    swarm_hook: Callable[[LocalSwarm], None] | None = None,
) -> dict[str, Any]:
    """Run the swarm, write the report, return the summary.

    ``on_step`` is called after each lock-step step and ``swarm_hook`` once
    the swarm is up (tests use them to inject faults).
    """
    from swarmrec.client import SwarmClient

    t_start = time.perf_counter()
    out = settings.out
    out.mkdir(parents=True, exist_ok=True)
    pixels = None
    detector: dict[str, Any] = {}
    if settings.pixels:
        from swarmrec.swarm.pixels import detector_flags_settings, prepare_pixels

        pixels = prepare_pixels(settings)
        source, labels_file, trajectory = str(pixels.folder), pixels.labels_file, pixels.trajectory
        n_frames, n_labels = len(pixels), len(pixels.label_names)
        bounds = swarm_label_bounds(settings, pixels.exact, n_labels)
        detector = detector_flags_settings(pixels, settings)
    else:
        source, labels_file, seq, trajectory = prepare_dataset(settings)
        n_frames, n_labels = len(seq), seq.n_labels
        bounds = swarm_label_bounds(settings, seq)
    preset = get_preset(settings.preset)
    blocks = split_frames(n_frames, settings.robots)
    # Compiled once here, ten verifier processes load the kernels from numba's cache.
    warm_up()
    base = ServiceSettings(
        swarm=settings.swarm,
        n_robots=settings.robots,
        preset=settings.preset,
        n_labels=n_labels,
        label_bounds=tuple(int(b) for b in bounds),
        lockstep=settings.lockstep,
        request_timeout_s=settings.request_timeout_s,
        connect=("tcp/127.0.0.1:7447",),
        **detector,
    )
    timings: dict[str, float] = {"prepare_s": time.perf_counter() - t_start}
    for old in (out / "data").glob("robot*/*/*.log"):
        old.unlink()  # a fresh run starts from empty stores
    for old in (out / "data").glob("robot*/detector/constellations/*.txt"):
        old.unlink()  # and no constellation of an earlier run is read back as this one's
    swarm = LocalSwarm(
        base, data_dir=out / "data", log_dir=out / "logs", dataset=source, labels_file=labels_file
    )
    exit_codes: dict[str, int] = {}
    try:
        t0 = time.perf_counter()
        swarm.start(progress=settings.progress)
        timings["start_s"] = time.perf_counter() - t0
        with SwarmClient([swarm.endpoint], settings.swarm, timeout_s=settings.request_timeout_s) as client:
            expected = {(k, r) for r in range(settings.robots) for k in swarm.services}
            client.wait_for(expected)
            if swarm_hook is not None:
                swarm_hook(swarm)
            replay = (
                replay_lockstep(client, blocks, settings, on_step)
                if settings.lockstep
                else replay_free(client, blocks, settings)
            )
            timings["replay_s"] = replay.wall_s
            metrics = scrape(swarm.metrics_targets())
            closures = collect_loop_closures(client, settings.robots, replay)
    finally:
        t0 = time.perf_counter()
        exit_codes = swarm.stop()
        timings["stop_s"] = time.perf_counter() - t0
    detector_info: dict[str, Any] | None = None
    if pixels is not None:
        from swarmrec.datasets.constellations import write_constellations
        from swarmrec.swarm.pixels import detected_sequence

        seq, not_made = detected_sequence(pixels, out / "data", blocks)
        shutil.rmtree(out / "detections", ignore_errors=True)
        write_constellations(seq, out / "detections")
        detector_info = {
            "mode": "rgbd",
            "folder": str(pixels.folder),
            "model": str(pixels.model),
            "conf_threshold": pixels.conf_threshold,
            "camera": asdict(pixels.camera),
            "frames_without_constellation": len(not_made),
            "render": pixels.render,
        }
        if pixels.render is not None:
            timings["render_s"] = pixels.render["total_s"]
    wire_seq = as_on_the_wire(seq)
    timings["total_s"] = time.perf_counter() - t_start
    from swarmrec.swarm.report import write_report

    return write_report(
        settings,
        seq=seq,
        wire_seq=wire_seq,
        trajectory=trajectory,
        preset=preset,
        bounds=bounds,
        blocks=blocks,
        replay=replay,
        metrics=metrics,
        closures=closures,
        exit_codes=exit_codes,
        timings=timings,
        detector=detector_info,
    )
