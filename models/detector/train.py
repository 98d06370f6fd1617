"""Train the office object detector: a tiny anchor-free YOLO-style CNN on rendered office frames.

The detector stage (:class:`swarmrec.detection.OnnxDetector`) runs any YOLO-style ONNX
model; this script makes a small one for the synthetic office, from the frames that
:mod:`swarmrec.synthetic.render` draws (exact boxes and COCO class ids come with every
frame, so no labelling is needed). Training, validation and test frames come from
different worlds (each its own ``OfficeConfig`` seed: object placement, colours and
patterns, camera path, sensor noise), so the test set is a disjoint draw; the test and
validation worlds use the default office settings (the world the swarm replays), the
training worlds vary the desk count, orbit, camera height, wobble and glances.

The network: depthwise-separable convolutions down to stride 32, a top-down and
bottom-up feature pyramid, and an anchor-free head at strides 8, 16 and 32 that predicts,
for every cell, the distances from the cell's centre to the four sides of a box and one
score per office class (YOLOv8's recipe: task-aligned assignment, binary cross-entropy
on IoU-scaled class targets, CIoU box loss). Box decoding and the sigmoid are inside the
exported graph, so the model's output is YOLOv8's layout, ``[1, 84, N]`` (``cx cy w h``
in input pixels, then 80 COCO class scores in 0..1; the classes the office never shows
are exact zeros).

The model ships as ONNX (input ``images``: float32 ``[1, 3, H, W]`` RGB 0..1, the
letterboxed frame; output ``output0``), run by onnxruntime: torch is only needed here,
in the separate training environment::

    .venv-train/bin/python models/detector/train.py                   # writes models/detector/
    .venv-train/bin/python models/detector/train.py --frames 16 --epochs 1 --max-steps 3 --out /tmp/smoke

Test metrics (mAP@0.5 per class, the speed at 640x480) are computed on the exported file
through :class:`~swarmrec.detection.OnnxDetector`, so they describe the artefact that ships.
"""

from __future__ import annotations

import argparse
import copy
import math
import multiprocessing
import sys
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
import torch
import torch.nn.functional as F
from torch import nn

from swarmrec.detection import (
    DetectorSettings,
    Letterbox,
    OnnxDetector,
    decode_output,
    detect_layout,
    letterbox,
)
from swarmrec.detection.metrics import DetectionEvaluation, GroundTruth, Predictions, evaluate_detections
from swarmrec.detection.nms import non_max_suppression
from swarmrec.errors import ConfigError
from swarmrec.synthetic import OfficeConfig, coco_names, generate_office
from swarmrec.synthetic.config import DESK_DEPTH_M, DESK_WIDTH_M, MIN_CLEARANCE_M
from swarmrec.synthetic.render import RenderedFrame, SequenceRenderer
from swarmrec.synthetic.world import build_world

# What the three training scripts share lives beside them (models/ is no package).
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from training_common import (
    OPSET,
    check_export,
    export_onnx,
    log,
    onnx_session,
    run_script,
    run_torch,
    to_input,
    versions,
    write_json,
)

ImageArray = npt.NDArray[np.uint8]
FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

HERE = Path(__file__).resolve().parent
MODEL_FILE = "office_detector.onnx"
METRICS_FILE = "metrics.json"
EXAMPLES_FILE = "examples.png"
PR_FILE = "pr_curve.png"
#: Written with ``--check-arrays``: model inputs and torch's outputs on them.
CHECK_INPUTS_FILE = "check_inputs.npy"
CHECK_TORCH_FILE = "check_torch_outputs.npy"
INPUT_NAME = "images"
OUTPUT_NAME = "output0"
#: The output's class channels: COCO's 80, the label list of the synthetic world.
N_COCO = 80
#: Largest allowed |torch - onnxruntime| / (1 + |torch|) of the outputs: absolute for the scores
#: (0..1), relative for the boxes (input pixels).
EXPORT_TOLERANCE = 1e-4
#: The renderer's frame size (TUM's camera).
FRAME_HW = (480, 640)
#: A visible object is a true object to find when its box is at least this many pixels on both
#: sides (at 640x480) and at least this share of it is not hidden; smaller or more hidden ones
#: are "ignored" (VOC's difficult): neither missed when not found nor wrong when found.
MIN_SIDE_PX = 8
MIN_VISIBLE_FRACTION = 0.25
#: The box confidence threshold for mAP (standard practice: keep almost every box).
EVAL_CONF_THRESHOLD = 0.001
STRIDES = (8, 16, 32)
#: Confidence thresholds whose precision, recall and detections per frame metrics.json lists.
OPERATING_POINTS = (0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.4, 0.5, 0.6, 0.7)
_CHECK_IMAGES = 4


@dataclass(frozen=True)
class TrainSettings:
    """Everything a training run depends on. ``val_frames`` and ``test_frames`` default to
    a tenth and an eighth of ``frames`` (at least 8), so a smoke run with a tiny ``frames``
    renders tiny held-out sets too."""

    out: Path = HERE
    #: Training frames, ``frames_per_world`` from each training world.
    frames: int = 4000
    val_frames: int | None = None
    test_frames: int | None = None
    frames_per_world: int = 100
    #: Bases of the world seeds of the training, validation and test splits: world ``j``
    #: of a split has ``OfficeConfig.seed = 1000 * base + j`` (distinct, so the splits are disjoint).
    data_seeds: tuple[int, int, int] = (1, 2, 3)
    #: Seed of weight initialisation, shuffling and augmentation.
    seed: int = 0
    #: Model input (height, width), multiples of 32; 640x480 frames are letterboxed into it.
    input_hw: tuple[int, int] = (384, 512)
    #: Train on random crops of this (height, width) of the model input (None: whole inputs); the
    #: network is fully convolutional, so a crop costs its share of the pixels and keeps the scale.
    crop_hw: tuple[int, int] | None = (256, 320)
    #: Channels of the five stages (strides 2, 4, 8, 16, 32).
    widths: tuple[int, int, int, int, int] = (24, 48, 96, 128, 160)
    epochs: int = 9
    #: Stop after this many optimiser steps in all (smoke runs); None: no limit.
    max_steps: int | None = None
    batch_size: int = 16
    #: Peak learning rate (AdamW), reached after a linear warm-up, then cosine decay.
    lr: float = 3e-3
    weight_decay: float = 5e-4
    #: Decay of the exponential moving average of the weights (the model that is kept).
    ema_decay: float = 0.999
    threads: int = 2
    #: Processes rendering the worlds (1: render in this process).
    workers: int = 2
    #: Test frames timed through OnnxDetector for the speed figure.
    fps_frames: int = 300
    #: Also write model inputs and torch's outputs on them, for a test to compare with onnxruntime.
    check_arrays: bool = False

    def __post_init__(self) -> None:
        for name in (
            "frames",
            "frames_per_world",
            "epochs",
            "batch_size",
            "threads",
            "workers",
            "fps_frames",
        ):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("val_frames", "test_frames", "max_steps"):
            value = getattr(self, name)
            if value is not None and value < 1:
                raise ConfigError(f"{name} must be >= 1 or unset, got {value}")
        if len(set(self.data_seeds)) != 3 or min(self.data_seeds) < 0:
            raise ConfigError(
                f"the three data seeds must differ and be >= 0 (disjoint splits), got {self.data_seeds}"
            )
        if max(self.frames, self.val_size, self.test_size) > 1000 * self.frames_per_world:
            raise ConfigError("a split may have at most 1000 worlds (its seeds would reach the next split's)")
        height, width = self.input_hw
        if height % 32 or width % 32 or not 64 <= min(height, width) <= max(height, width) <= 1024:
            raise ConfigError(f"input_hw must be multiples of 32 in [64, 1024], got {self.input_hw}")
        if self.crop_hw is not None and not (
            self.crop_hw[0] % 32 == 0
            and self.crop_hw[1] % 32 == 0
            and 64 <= self.crop_hw[0] <= height
            and 64 <= self.crop_hw[1] <= width
        ):
            raise ConfigError(
                f"crop_hw must be multiples of 32, at least 64 and within input_hw, got {self.crop_hw}"
            )
        if min(self.widths) < 8:
            raise ConfigError(f"widths must be >= 8, got {self.widths}")
        if not (math.isfinite(self.lr) and self.lr > 0):
            raise ConfigError(f"lr must be > 0, got {self.lr}")
        if not (math.isfinite(self.weight_decay) and self.weight_decay >= 0):
            raise ConfigError(f"weight_decay must be >= 0, got {self.weight_decay}")
        if not 0.0 <= self.ema_decay < 1.0:
            raise ConfigError(f"ema_decay must be in [0, 1), got {self.ema_decay}")

    @property
    def val_size(self) -> int:
        return self.val_frames or max(8, self.frames // 10)

    @property
    def test_size(self) -> int:
        return self.test_frames or max(8, self.frames // 8)


@dataclass(frozen=True)
class TrainResult:
    """Where the run wrote its files, and the numbers a caller checks first."""

    model: Path
    metrics_file: Path
    test_map50: float
    onnx_max_diff: float
    metrics: dict[str, Any] = field(repr=False)


def office_classes() -> tuple[int, ...]:
    """The COCO class ids the office world can hold (every desk layout and the room), ascending."""
    world = build_world(OfficeConfig(n_desks=8), np.random.default_rng(0))
    return tuple(sorted({int(c) for c in world.labels}))


# --- data ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class WorldJob:
    """Render ``frames`` frames of the world ``seed``; ``vary``: draw the world's settings too."""

    seed: int
    frames: int
    vary: bool
    input_hw: tuple[int, int]
    keep_originals: bool


@dataclass(eq=False)
class Split:
    """Frames of one split: letterboxed RGB model inputs, (optionally) the original BGR frames,
    the ground truth in original pixels, and where each frame comes from."""

    images: ImageArray
    originals: ImageArray | None
    truths: list[GroundTruth]
    sources: list[tuple[int, int]]

    def __len__(self) -> int:
        return int(self.images.shape[0])


def world_config(seed: int, vary: bool) -> OfficeConfig:
    """The default office of ``seed``; with ``vary``, desks, orbit, camera height, wobble and
    glances drawn from ``seed`` too (training worlds: more looks at the room, more distances)."""
    if not vary:
        return OfficeConfig(seed=seed)
    rng = np.random.default_rng([seed, 0x5EED])
    n_desks = int(rng.choice([4, 6, 6, 8]))
    half_x, half_y = DESK_WIDTH_M * n_desks / 4, DESK_DEPTH_M
    closest = MIN_CLEARANCE_M + (half_x + half_y) / 2
    return OfficeConfig(
        seed=seed,
        n_desks=n_desks,
        orbit_radius_m=round(closest + float(rng.uniform(0.3, 1.2)), 3),
        camera_height_m=(round(float(rng.uniform(0.9, 1.2)), 3), round(float(rng.uniform(1.5, 1.8)), 3)),
        wobble_deg=round(float(rng.uniform(8.0, 22.0)), 2),
        glances_per_minute=round(float(rng.uniform(3.0, 10.0)), 2),
    )


def ground_truth(frame: RenderedFrame) -> GroundTruth:
    """Every visible object of a frame, the small or mostly hidden ones marked ignored."""
    boxes = frame.boxes.astype(np.float64)
    sides = np.minimum(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1])
    kept = (sides >= MIN_SIDE_PX) & (frame.visible_fraction >= MIN_VISIBLE_FRACTION)
    return GroundTruth(boxes, frame.labels.astype(np.int64), ~kept)


def to_model_image(bgr: ImageArray, input_hw: tuple[int, int]) -> tuple[ImageArray, Letterbox]:
    """A BGR frame as the model sees it, as uint8 RGB: letterboxed exactly as OnnxDetector does."""
    padded, placement = letterbox(bgr, input_hw)
    return np.ascontiguousarray(padded[:, :, ::-1]), placement


def render_world(job: WorldJob) -> Split:
    """``job.frames`` frames of one world, at frame indices drawn from the world's seed."""
    ds = generate_office(world_config(job.seed, job.vary))
    renderer = SequenceRenderer(ds)
    rng = np.random.default_rng([job.seed, 0xF4A3])
    indices = np.sort(rng.choice(len(renderer), size=min(job.frames, len(renderer)), replace=False))
    images, originals, truths = [], [], []
    for i in indices.tolist():
        frame = renderer.render(i)
        images.append(to_model_image(frame.rgb, job.input_hw)[0])
        if job.keep_originals:
            originals.append(frame.rgb)
        truths.append(ground_truth(frame))
    return Split(
        np.stack(images),
        np.stack(originals) if job.keep_originals else None,
        truths,
        [(job.seed, i) for i in indices.tolist()],
    )


def render_split(
    base: int,
    frames: int,
    per_world: int,
    *,
    vary: bool,
    input_hw: tuple[int, int],
    originals: bool,
    workers: int,
) -> Split:
    """``frames`` frames from worlds ``1000 * base + j``, ``per_world`` each (the last takes the rest)."""
    jobs = [
        WorldJob(1000 * base + j, min(per_world, frames - j * per_world), vary, input_hw, originals)
        for j in range(math.ceil(frames / per_world))
    ]
    if workers == 1 or len(jobs) == 1:
        parts = [render_world(job) for job in jobs]
    else:
        # spawn: forking a process that has started torch's thread pools can deadlock.
        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
            parts = list(pool.map(render_world, jobs))
    kept = [p.originals for p in parts if p.originals is not None]
    return Split(
        np.concatenate([p.images for p in parts]),
        np.concatenate(kept) if originals else None,
        [t for p in parts for t in p.truths],
        [s for p in parts for s in p.sources],
    )


@dataclass(frozen=True)
class Targets:
    """Objects of a batch of frames, padded to the most in one frame: boxes in model input
    pixels ``[N, M, 4]``, indices into the model's classes ``[N, M]`` and which entries are
    real ``[N, M]``. One set for the objects to find, one for the ignored ones."""

    boxes: torch.Tensor
    labels: torch.Tensor
    mask: torch.Tensor

    def __getitem__(self, index: torch.Tensor) -> Targets:
        """The frames ``index``, padded to the most objects among them."""
        most = max(1, int(self.mask[index].sum(1).max()))
        return Targets(self.boxes[index, :most], self.labels[index, :most], self.mask[index, :most])


def training_targets(
    split: Split, placement: Letterbox, class_index: dict[int, int], *, ignored: bool
) -> Targets:
    """The objects to find (or with ``ignored``, the ignored objects) of every frame of ``split``."""
    chosen = [t.ignore if ignored else t.kept for t in split.truths]
    most = max([int(c.sum()) for c in chosen] + [1])
    boxes = torch.zeros(len(split), most, 4)
    labels = torch.zeros(len(split), most, dtype=torch.long)
    mask = torch.zeros(len(split), most, dtype=torch.bool)
    scale = np.array([placement.scale_x, placement.scale_y] * 2)
    pad = np.array([placement.pad_x, placement.pad_y] * 2, np.float64)
    for i, (truth, rows) in enumerate(zip(split.truths, chosen, strict=True)):
        n = int(rows.sum())
        boxes[i, :n] = torch.from_numpy(truth.boxes[rows] * scale + pad).float()
        labels[i, :n] = torch.tensor([class_index[int(c)] for c in truth.class_ids[rows]], dtype=torch.long)
        mask[i, :n] = True
    return Targets(boxes, labels, mask)


def _crop(
    x: torch.Tensor,
    targets: Sequence[Targets],
    crop_hw: tuple[int, int],
    min_side: float,
    generator: torch.Generator,
) -> tuple[torch.Tensor, list[Targets]]:
    """A random ``crop_hw`` window of each image. Boxes are clipped to it, which is what the
    renderer's boxes are at the frame's border (the extent of the visible pixels); objects left
    thinner than ``min_side`` are dropped."""
    n, _, height, width = x.shape
    ch, cw = crop_hw
    top = torch.randint(0, height - ch + 1, (n,), generator=generator)
    left = torch.randint(0, width - cw + 1, (n,), generator=generator)
    corners = zip(top.tolist(), left.tolist(), strict=True)
    x = torch.stack([x[i, :, y : y + ch, z : z + cw] for i, (y, z) in enumerate(corners)])
    shift = torch.stack([left, top, left, top], -1)[:, None, :].float()
    limit = torch.tensor([cw, ch, cw, ch], dtype=torch.float32)
    cropped = []
    for t in targets:
        clipped = torch.minimum((t.boxes - shift).clamp(min=0.0), limit)
        sides = torch.minimum(clipped[..., 2] - clipped[..., 0], clipped[..., 3] - clipped[..., 1])
        cropped.append(Targets(clipped, t.labels, t.mask & (sides >= min_side)))
    return x, cropped


def _augment(
    x: torch.Tensor, targets: Sequence[Targets], generator: torch.Generator
) -> tuple[torch.Tensor, list[Targets]]:
    """Mirror half of the images left-right (an office mirrored is still an office) and vary
    brightness, contrast and colour balance a little more than the renderer's lighting does."""
    n, width = x.shape[0], x.shape[-1]
    flip = torch.rand(n, generator=generator) < 0.5
    x = torch.where(flip[:, None, None, None], x.flip(-1), x)
    flipped = []
    for t in targets:
        b = t.boxes
        mirrored = torch.stack([width - b[..., 2], b[..., 1], width - b[..., 0], b[..., 3]], -1)
        flipped.append(Targets(torch.where(flip[:, None, None], mirrored, b), t.labels, t.mask))
    gain = torch.empty(n, 1, 1, 1).uniform_(0.75, 1.25, generator=generator)
    tint = torch.empty(n, 3, 1, 1).uniform_(0.92, 1.08, generator=generator)
    mean = x.mean(dim=(1, 2, 3), keepdim=True)
    contrast = torch.empty(n, 1, 1, 1).uniform_(0.8, 1.2, generator=generator)
    x = ((x - mean) * contrast + mean) * gain * tint
    return x.clamp(0.0, 1.0), flipped


# --- model --------------------------------------------------------------------------------------


def _conv(n_in: int, n_out: int, kernel: int = 3, stride: int = 1, groups: int = 1) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(n_in, n_out, kernel, stride, kernel // 2, groups=groups, bias=False),
        nn.BatchNorm2d(n_out),
        nn.ReLU(inplace=True),
    )


class SeparableBlock(nn.Module):
    """Depthwise 3x3 (strided or not) then pointwise 1x1, each with batch norm and ReLU;
    a residual connection when the shape is kept."""

    def __init__(self, n_in: int, n_out: int, stride: int = 1) -> None:
        super().__init__()
        self.body = nn.Sequential(_conv(n_in, n_in, 3, stride, groups=n_in), _conv(n_in, n_out, 1))
        self.residual = stride == 1 and n_in == n_out

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y: torch.Tensor = self.body(x)
        return x + y if self.residual else y


def _stage(n_in: int, n_out: int, blocks: int) -> nn.Sequential:
    return nn.Sequential(
        SeparableBlock(n_in, n_out, 2), *(SeparableBlock(n_out, n_out) for _ in range(blocks))
    )


class OfficeDetector(nn.Module):
    """Backbone to stride 32, feature pyramid (top-down then bottom-up), one head per stride.

    :meth:`raw` gives the training outputs, :meth:`forward` the exported YOLOv8 layout.
    ``class_ids[k]`` is the COCO id of the model's class ``k``.
    """

    def __init__(self, class_ids: Sequence[int], input_hw: tuple[int, int], widths: Sequence[int]) -> None:
        super().__init__()
        w0, w1, w2, w3, w4 = widths
        self.n_classes = len(class_ids)
        self.input_hw = input_hw
        self.stem = nn.Sequential(_conv(3, w0, 3, 2), _stage(w0, w1, 1))
        self.stage3 = _stage(w1, w2, 2)
        self.stage4 = _stage(w2, w3, 2)
        self.stage5 = _stage(w3, w4, 2)
        self.lateral5 = _conv(w4, w3, 1)
        self.top_down4 = SeparableBlock(w3, w3)
        self.lateral4 = _conv(w3, w2, 1)
        self.top_down3 = SeparableBlock(w2, w2)
        self.down3 = SeparableBlock(w2, w3, 2)
        self.bottom_up4 = SeparableBlock(w3, w3)
        self.down4 = SeparableBlock(w3, w4, 2)
        self.bottom_up5 = SeparableBlock(w4, w4)
        outputs = 4 + self.n_classes
        self.heads = nn.ModuleList(
            nn.Sequential(SeparableBlock(c, c), nn.Conv2d(c, outputs, 1)) for c in (w2, w3, w4)
        )
        for head in self.heads:
            last = head[-1]
            assert isinstance(last, nn.Conv2d) and last.bias is not None
            nn.init.zeros_(last.bias)
            # Class scores start near 1 %, as in RetinaNet and YOLO: most cells hold nothing.
            nn.init.constant_(last.bias[4:], -math.log(99.0))
        centres, strides = self._grid(input_hw)
        self.centres: torch.Tensor
        self.strides: torch.Tensor
        self.register_buffer("centres", centres, persistent=False)
        self.register_buffer("strides", strides, persistent=False)
        # Output channel c is model class index[c], or the constant zero channel (index n_classes).
        index = torch.full((N_COCO,), self.n_classes, dtype=torch.long)
        index[torch.tensor(list(class_ids))] = torch.arange(self.n_classes)
        self.coco_index: torch.Tensor
        self.register_buffer("coco_index", index, persistent=False)

    @staticmethod
    def _grid(input_hw: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
        """Cell centres ``[A, 2]`` (x, y in input pixels) and strides ``[A]``, level by level, row-major."""
        centres, strides = [], []
        for stride in STRIDES:
            ys, xs = torch.meshgrid(
                torch.arange(input_hw[0] // stride), torch.arange(input_hw[1] // stride), indexing="ij"
            )
            centres.append((torch.stack([xs, ys], -1).reshape(-1, 2).float() + 0.5) * stride)
            strides.append(torch.full((centres[-1].shape[0],), float(stride)))
        return torch.cat(centres), torch.cat(strides)

    def grid(self, hw: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
        """Cell centres and strides of an input of ``hw`` (training crops are smaller than the input)."""
        if hw == self.input_hw:
            return self.centres, self.strides
        return self._grid(hw)

    def raw(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Box distances ``[B, A, 4]`` (left, top, right, bottom, input pixels, >= 0) and class
        logits ``[B, A, K]`` of every cell of every level."""
        c3 = self.stage3(self.stem(images))
        c4 = self.stage4(c3)
        c5 = self.stage5(c4)
        p5 = self.lateral5(c5)
        p4 = self.top_down4(c4 + F.interpolate(p5, scale_factor=2.0, mode="nearest"))
        p3 = self.top_down3(c3 + F.interpolate(self.lateral4(p4), scale_factor=2.0, mode="nearest"))
        n4 = self.bottom_up4(p4 + self.down3(p3))
        n5 = self.bottom_up5(c5 + self.down4(n4))
        out = torch.cat([head(p).flatten(2) for head, p in zip(self.heads, (p3, n4, n5), strict=True)], 2)
        out = out.transpose(1, 2)
        strides = self.grid((int(images.shape[-2]), int(images.shape[-1])))[1]
        distances = F.softplus(out[..., :4]) * strides[None, :, None]
        return distances, out[..., 4:]

    def boxes(self, distances: torch.Tensor, centres: torch.Tensor) -> torch.Tensor:
        """``x1 y1 x2 y2`` (input pixels) from the distances of :meth:`raw` and the cell centres."""
        return torch.cat([centres - distances[..., :2], centres + distances[..., 2:]], -1)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """YOLOv8's layout ``[B, 4 + 80, A]``: ``cx cy w h`` in input pixels, COCO class scores."""
        distances, logits = self.raw(images)
        centre = self.centres + (distances[..., 2:] - distances[..., :2]) / 2
        size = distances[..., :2] + distances[..., 2:]
        scores = torch.sigmoid(logits)
        scores = torch.cat([scores, torch.zeros_like(scores[..., :1])], -1).index_select(-1, self.coco_index)
        return torch.cat([centre, size, scores], -1).transpose(1, 2)


# --- loss ---------------------------------------------------------------------------------------


def _pair_iou(a: torch.Tensor, b: torch.Tensor, eps: float = 1e-9) -> torch.Tensor:
    """IoU of boxes ``a[..., 4]`` and ``b[..., 4]`` (broadcast)."""
    lo = torch.maximum(a[..., :2], b[..., :2])
    hi = torch.minimum(a[..., 2:], b[..., 2:])
    inter = (hi - lo).clamp(min=0).prod(-1)
    area_a = (a[..., 2:] - a[..., :2]).clamp(min=0).prod(-1)
    area_b = (b[..., 2:] - b[..., :2]).clamp(min=0).prod(-1)
    return inter / (area_a + area_b - inter + eps)


def _ciou(a: torch.Tensor, b: torch.Tensor, eps: float = 1e-7) -> torch.Tensor:
    """Complete IoU (Zheng et al. 2020) of matching boxes ``[n, 4]``: IoU minus centre distance
    and aspect-ratio penalties."""
    iou = _pair_iou(a, b, eps)
    outer = torch.maximum(a[:, 2:], b[:, 2:]) - torch.minimum(a[:, :2], b[:, :2])
    diagonal = outer.pow(2).sum(-1) + eps
    centre = ((a[:, :2] + a[:, 2:]) - (b[:, :2] + b[:, 2:])).pow(2).sum(-1) / 4
    wa, ha = (a[:, 2] - a[:, 0]).clamp(min=eps), (a[:, 3] - a[:, 1]).clamp(min=eps)
    wb, hb = (b[:, 2] - b[:, 0]).clamp(min=eps), (b[:, 3] - b[:, 1]).clamp(min=eps)
    v = (4 / math.pi**2) * (torch.atan(wb / hb) - torch.atan(wa / ha)).pow(2)
    with torch.no_grad():
        alpha = v / (v - iou + (1 + eps))
    return iou - centre / diagonal - alpha * v


@torch.no_grad()
def assign(
    scores: torch.Tensor,
    boxes: torch.Tensor,
    centres: torch.Tensor,
    strides: torch.Tensor,
    gt_boxes: torch.Tensor,
    gt_labels: torch.Tensor,
    gt_mask: torch.Tensor,
    *,
    topk: int = 10,
    alpha: float = 0.5,
    beta: float = 6.0,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Task-aligned assignment (TOOD, as YOLOv8 uses it): each object takes the ``topk`` cells
    with the best ``score ** alpha * IoU ** beta`` among the cells whose centre lies in its box or
    within one stride of its centre (so that objects smaller than a cell still get cells); a cell
    claimed by two objects goes to the one its box overlaps more.

    Returns the target boxes ``[B, A, 4]``, the target class scores ``[B, A, K]`` (the
    alignment, scaled so that each object's best cell gets that cell's IoU) and the foreground
    mask ``[B, A]``.
    """
    batch, cells, n_classes = scores.shape
    if gt_boxes.shape[1] == 0:
        return torch.zeros_like(boxes), torch.zeros_like(scores), torch.zeros(batch, cells, dtype=torch.bool)
    x, y = centres[:, 0], centres[:, 1]
    g = gt_boxes[:, :, None, :]  # [B, M, 1, 4]
    inside = (x > g[..., 0]) & (x < g[..., 2]) & (y > g[..., 1]) & (y < g[..., 3])
    gx, gy = (g[..., 0] + g[..., 2]) / 2, (g[..., 1] + g[..., 3]) / 2
    near = ((x - gx).abs() < strides) & ((y - gy).abs() < strides)
    candidate = (inside | near) & gt_mask[:, :, None]
    iou = _pair_iou(g, boxes[:, None, :, :]) * candidate  # [B, M, A]
    class_scores = scores.transpose(1, 2).gather(1, gt_labels[:, :, None].expand(-1, -1, cells))
    metric = class_scores.pow(alpha) * iou.pow(beta) * candidate
    best = metric.topk(min(topk, cells), dim=-1).indices
    chosen = torch.zeros_like(candidate).scatter_(-1, best, True) & candidate
    # A cell claimed twice: the object its box overlaps most keeps it.
    claimed = chosen.sum(1)
    if bool((claimed > 1).any()):
        overlap_best = F.one_hot(iou.argmax(1), gt_boxes.shape[1]).transpose(1, 2).bool()
        chosen = torch.where((claimed > 1)[:, None, :], overlap_best & candidate, chosen)
    foreground = chosen.any(1)
    owner = chosen.float().argmax(1)  # [B, A]
    target_boxes = gt_boxes.gather(1, owner[..., None].expand(-1, -1, 4))
    target_labels = gt_labels.gather(1, owner)
    metric = metric * chosen
    scale = (iou * chosen).amax(-1, keepdim=True) / (metric.amax(-1, keepdim=True) + 1e-9)
    quality = (metric * scale).amax(1)  # [B, A]
    target_scores = F.one_hot(target_labels, n_classes).float() * (quality * foreground)[..., None]
    return target_boxes, target_scores, foreground


def _ignored_cells(
    shape: tuple[int, int, int], centres: torch.Tensor, strides: torch.Tensor, ignored: Targets
) -> torch.Tensor:
    """``[B, A, K]``: True where cell ``a`` lies in (or within a stride of the centre of) an ignored
    object of class ``k``: a score for that class there is neither demanded nor punished."""
    out = torch.zeros(shape, dtype=torch.bool)
    if ignored.boxes.shape[1] == 0:
        return out
    g = ignored.boxes[:, :, None, :]
    x, y = centres[:, 0], centres[:, 1]
    inside = (x > g[..., 0]) & (x < g[..., 2]) & (y > g[..., 1]) & (y < g[..., 3])
    near = ((x - (g[..., 0] + g[..., 2]) / 2).abs() < strides) & (
        (y - (g[..., 1] + g[..., 3]) / 2).abs() < strides
    )
    b, m, a = ((inside | near) & ignored.mask[:, :, None]).nonzero(as_tuple=True)
    out[b, a, ignored.labels[b, m]] = True
    return out


def detection_loss(
    model: OfficeDetector, images: torch.Tensor, objects: Targets, ignored: Targets
) -> tuple[torch.Tensor, dict[str, float]]:
    """YOLOv8's loss without the distribution focal term: 7.5 x CIoU loss (weighted by the
    target scores) + 0.5 x binary cross-entropy of the class scores, both per target score.
    The class scores of ignored objects at their cells are left out, unless the cell is
    assigned to an object to find."""
    distances, logits = model.raw(images)
    centres, strides = model.grid((int(images.shape[-2]), int(images.shape[-1])))
    boxes = model.boxes(distances, centres)
    target_boxes, target_scores, foreground = assign(
        logits.detach().sigmoid(),
        boxes.detach(),
        centres,
        strides,
        objects.boxes,
        objects.labels,
        objects.mask,
    )
    skip = _ignored_cells(tuple(logits.shape), centres, strides, ignored) & ~foreground[..., None]
    norm = target_scores.sum().clamp(min=1.0)
    bce = F.binary_cross_entropy_with_logits(logits, target_scores, reduction="none")
    cls = bce.masked_fill(skip, 0.0).sum() / norm
    if bool(foreground.any()):
        weight = target_scores.sum(-1)[foreground]
        box = ((1.0 - _ciou(boxes[foreground], target_boxes[foreground])) * weight).sum() / norm
    else:
        box = boxes.sum() * 0.0
    loss = 7.5 * box + 0.5 * cls
    return loss, {"box": box.item(), "cls": cls.item(), "positives": float(foreground.sum())}


class WeightAverage:
    """Exponential moving average of the weights (and batch-norm statistics), with YOLOv5's
    warm-up of the decay so that the first, poor weights fade fast."""

    def __init__(self, model: nn.Module, decay: float, warmup_steps: float) -> None:
        self.model = copy.deepcopy(model).eval()
        self.decay = decay
        self.warmup_steps = warmup_steps
        self.updates = 0
        for p in self.model.parameters():
            p.requires_grad_(False)

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        self.updates += 1
        d = self.decay * (1 - math.exp(-self.updates / self.warmup_steps))
        mine = self.model.state_dict()
        for name, value in model.state_dict().items():
            if value.dtype.is_floating_point:
                mine[name].mul_(d).add_(value.detach(), alpha=1 - d)
            else:
                mine[name].copy_(value)


# --- evaluation ---------------------------------------------------------------------------------


def _predictions(
    output: npt.NDArray[np.float32], placement: Letterbox, settings: DetectorSettings
) -> Predictions:
    """One v8 output ``[1, 84, A]`` -> detections in original pixels, as OnnxDetector makes them."""
    candidates = decode_output(output, N_COCO)
    keep = non_max_suppression(
        candidates, settings.conf_threshold, settings.iou_threshold, settings.max_detections
    )
    boxes = placement.to_original(candidates.boxes[keep])
    valid = (boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1])
    return Predictions(boxes[valid], candidates.scores[keep][valid], candidates.class_ids[keep][valid])


def torch_outputs(model: OfficeDetector, images: ImageArray, batch_size: int = 32) -> npt.NDArray[np.float32]:
    """torch's v8 outputs ``[N, 84, A]`` for uint8 model images, in eval mode."""
    outputs: npt.NDArray[np.float32] = run_torch(model, images, batch_size, as_float64=False)
    return outputs


def evaluate_torch(model: OfficeDetector, split: Split, placement: Letterbox) -> DetectionEvaluation:
    """mAP@0.5 of the torch model on a split (validation during training)."""
    settings = DetectorSettings(conf_threshold=EVAL_CONF_THRESHOLD)
    outputs = torch_outputs(model, split.images)
    predictions = [_predictions(outputs[i : i + 1], placement, settings) for i in range(len(split))]
    return evaluate_detections(predictions, split.truths)


def detect_all(detector: OnnxDetector, originals: ImageArray) -> list[Predictions]:
    """OnnxDetector's detections on every BGR frame."""
    found = []
    for image in originals:
        detections = detector.detect(image)
        found.append(
            Predictions(
                np.array([d.box for d in detections]).reshape(-1, 4),
                np.array([d.score for d in detections]),
                np.array([d.class_id for d in detections], np.int64),
            )
        )
    return found


def time_detector(model_path: Path, originals: ImageArray, settings: DetectorSettings) -> dict[str, float]:
    """Milliseconds per 640x480 frame through OnnxDetector.detect (letterbox, onnxruntime, decode,
    threshold and NMS), after a warm-up; also the share of onnxruntime's run alone."""
    detector = OnnxDetector(model_path, settings)
    for image in originals[:10]:
        detector.detect(image)
    times, detections = [], 0
    for image in originals:
        started = time.perf_counter()
        detections += len(detector.detect(image))
        times.append(time.perf_counter() - started)
    blob = to_input(to_model_image(originals[0], detector.input_hw)[0][None]).numpy()
    session = detector._session  # the same session, to time the network alone
    run_times = []
    for _ in range(len(originals)):
        started = time.perf_counter()
        session.run([OUTPUT_NAME], {INPUT_NAME: blob})
        run_times.append(time.perf_counter() - started)
    ms = 1000 * np.array(times)
    return {
        "frames": len(originals),
        "ms_per_frame_mean": float(ms.mean()),
        "ms_per_frame_median": float(np.median(ms)),
        "ms_per_frame_p90": float(np.percentile(ms, 90)),
        "fps": float(1000 / ms.mean()),
        "onnxruntime_run_ms_median": float(1000 * np.median(run_times)),
        "detections_per_frame": detections / len(originals),
    }


def _class_table(evaluation: DetectionEvaluation, names: Sequence[str]) -> list[dict[str, Any]]:
    rows = []
    for class_id, result in sorted(evaluation.per_class.items()):
        if result.n_truth == 0 and result.n_ignored_truth == 0:
            continue
        rows.append(
            {
                "class_id": class_id,
                "name": names[class_id],
                "ap50": result.ap,
                "objects": result.n_truth,
                "ignored_objects": result.n_ignored_truth,
                "max_recall": result.max_recall,
            }
        )
    return rows


def _draw_examples(
    split: Split,
    found: list[Predictions],
    picks: Sequence[int],
    threshold: float,
    names: Sequence[str],
    path: Path,
) -> None:
    import matplotlib  # only for the figures; imported here so a headless backend is set first

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    assert split.originals is not None
    fig, axes = plt.subplots(2, 2, figsize=(15, 11.8), dpi=80)
    for ax, i in zip(axes.ravel(), picks, strict=False):
        ax.imshow(split.originals[i][:, :, ::-1])
        truth = split.truths[i]
        for box, kept in zip(truth.boxes, truth.kept, strict=True):
            colour, style = ("lime", "-") if kept else ("lightgrey", ":")
            ax.add_patch(
                plt.Rectangle(box[:2], *(box[2:] - box[:2]), fill=False, ec=colour, lw=1.2, ls=style)
            )
        p = found[i]
        shown = p.scores >= threshold
        for box, score, class_id in zip(p.boxes[shown], p.scores[shown], p.class_ids[shown], strict=True):
            ax.add_patch(plt.Rectangle(box[:2], *(box[2:] - box[:2]), fill=False, ec="red", lw=1.0))
            ax.text(box[0], box[1] - 2, f"{names[class_id]} {score:.2f}", color="red", fontsize=6)
        world, frame = split.sources[i]
        ax.set_title(
            f"world {world}, frame {frame}: {int(truth.kept.sum())} objects, {int(shown.sum())} detections"
        )
        ax.axis("off")
    fig.suptitle(
        f"Held-out renders: true boxes (green; dotted grey: too small or hidden, ignored), "
        f"detections at conf >= {threshold:.2f} (red)"
    )
    fig.tight_layout()
    _save_small_png(fig, path)
    plt.close(fig)


def _save_small_png(fig: Any, path: Path) -> None:
    """Save a figure of rendered frames as a 256-colour PNG: the frames' sensor noise makes a
    full-colour PNG several times larger, for no visible difference at this size."""
    import io

    from PIL import Image  # matplotlib's own dependency

    buffer = io.BytesIO()
    fig.savefig(buffer, format="png")
    buffer.seek(0)
    with Image.open(buffer) as image:
        image.convert("RGB").quantize(256).save(path, optimize=True)


def _plot_pr(evaluation: DetectionEvaluation, threshold: float, names: Sequence[str], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 6.5), dpi=100)
    classes = sorted(evaluation.evaluated_classes, key=lambda c: -evaluation.per_class[c].n_truth)
    for c in classes[:10]:
        r = evaluation.per_class[c]
        ax.plot(r.recall, r.precision, lw=1, label=f"{names[c]} (AP {r.ap:.2f}, {r.n_truth})")
    thresholds = np.linspace(0.0, 0.99, 100)
    points = [evaluation.at_threshold(float(t)) for t in thresholds]
    ax.plot([p.recall for p in points], [p.precision for p in points], "k-", lw=2, label="all classes")
    chosen = evaluation.at_threshold(threshold)
    ax.plot(chosen.recall, chosen.precision, "ko", ms=8, mfc="none")
    ax.annotate(
        f"conf {threshold:.2f}", (chosen.recall, chosen.precision), xytext=(8, 8), textcoords="offset points"
    )
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1.02)
    ax.set_xlabel("recall")
    ax.set_ylabel("precision")
    ax.set_title(f"Held-out renders, IoU 0.5: mAP@0.5 {evaluation.mean_ap:.3f} (10 most frequent classes)")
    ax.legend(fontsize=7, loc="lower left")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main(settings: TrainSettings) -> TrainResult:
    """Render the splits, train (keeping the epoch of best validation mAP@0.5), export to ONNX,
    check it against torch, choose the confidence threshold on the validation split, score and
    time it on the test split through OnnxDetector, and write ``office_detector.onnx``,
    ``metrics.json``, ``examples.png`` and ``pr_curve.png`` to ``settings.out``."""
    s = settings
    torch.set_num_threads(s.threads)
    torch.manual_seed(s.seed)
    generator = torch.Generator().manual_seed(s.seed)
    out = Path(s.out)
    out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    names = coco_names()
    classes = office_classes()
    class_index = {c: k for k, c in enumerate(classes)}

    common: dict[str, Any] = {"per_world": s.frames_per_world, "input_hw": s.input_hw, "workers": s.workers}
    train = render_split(s.data_seeds[0], s.frames, vary=True, originals=False, **common)
    val = render_split(s.data_seeds[1], s.val_size, vary=False, originals=True, **common)
    test = render_split(s.data_seeds[2], s.test_size, vary=False, originals=True, **common)
    render_s = time.perf_counter() - started
    placement = to_model_image(np.zeros((*FRAME_HW, 3), np.uint8), s.input_hw)[1]
    n_objects = sum(int(t.kept.sum()) for t in train.truths)
    log(
        f"rendered {len(train)} train ({n_objects} objects), {len(val)} val, {len(test)} test frames "
        f"in {render_s:.1f} s"
    )

    model = OfficeDetector(classes, s.input_hw, s.widths)
    n_params = sum(p.numel() for p in model.parameters())
    steps_per_epoch = math.ceil(len(train) / s.batch_size)
    total_steps = (
        s.epochs * steps_per_epoch if s.max_steps is None else min(s.max_steps, s.epochs * steps_per_epoch)
    )
    warmup = max(1, min(300, total_steps // 10))
    ema = WeightAverage(model, s.ema_decay, warmup_steps=max(1.0, total_steps / 10))
    # Weight decay on the convolution weights only, not on biases and batch-norm scales.
    decay = [p for p in model.parameters() if p.ndim > 1]
    no_decay = [p for p in model.parameters() if p.ndim <= 1]
    optimiser = torch.optim.AdamW(
        [{"params": decay, "weight_decay": s.weight_decay}, {"params": no_decay, "weight_decay": 0.0}],
        lr=s.lr,
    )
    scheduler = torch.optim.lr_scheduler.LambdaLR(
        optimiser,
        lambda step: (
            (step + 1) / warmup
            if step < warmup
            else 0.02
            + 0.98 * 0.5 * (1 + math.cos(math.pi * min(1.0, (step - warmup) / max(1, total_steps - warmup))))
        ),
    )
    log(f"model: {n_params} parameters, input {s.input_hw[1]}x{s.input_hw[0]}, {len(classes)} classes")
    objects = training_targets(train, placement, class_index, ignored=False)
    ignored = training_targets(train, placement, class_index, ignored=True)

    history: list[dict[str, float]] = []
    best_map, best_epoch, best_state = -1.0, 0, copy.deepcopy(ema.model.state_dict())
    steps, train_started = 0, time.perf_counter()
    for epoch in range(1, s.epochs + 1):
        epoch_started = time.perf_counter()
        model.train()
        order = torch.randperm(len(train), generator=generator)
        sums = {"loss": 0.0, "box": 0.0, "cls": 0.0, "positives": 0.0}
        batches = 0
        for i in range(0, len(order), s.batch_size):
            idx = order[i : i + s.batch_size]
            x, batch = to_input(train.images[idx.numpy()]), [objects[idx], ignored[idx]]
            if s.crop_hw is not None:
                x, batch = _crop(x, batch, s.crop_hw, MIN_SIDE_PX * placement.scale_x, generator)
            x, batch = _augment(x, batch, generator)
            loss, parts = detection_loss(model, x, batch[0], batch[1])
            optimiser.zero_grad()
            loss.backward()  # type: ignore[no-untyped-call]  # untyped in torch's stubs
            nn.utils.clip_grad_norm_(model.parameters(), 10.0)
            optimiser.step()
            scheduler.step()
            ema.update(model)
            sums["loss"] += loss.item()
            for k, v in parts.items():
                sums[k] += v
            batches += 1
            steps += 1
            if steps % 50 == 0:
                log(
                    f"  step {steps}/{total_steps}  loss {sums['loss'] / batches:.3f}  "
                    f"({(time.perf_counter() - epoch_started) / batches:.2f} s/step)"
                )
            if steps >= total_steps:
                break
        val_eval = evaluate_torch(ema.model, val, placement)
        history.append(
            {
                "epoch": epoch,
                **{k: v / max(batches, 1) for k, v in sums.items()},
                "val_map50": val_eval.mean_ap,
                "lr": optimiser.param_groups[0]["lr"],
                "seconds": time.perf_counter() - epoch_started,
            }
        )
        log(
            f"epoch {epoch:2d}/{s.epochs}  loss {history[-1]['loss']:.3f} (box {history[-1]['box']:.3f}, "
            f"cls {history[-1]['cls']:.3f})  val mAP@0.5 {val_eval.mean_ap:.3f}  "
            f"({history[-1]['seconds']:.1f} s)"
        )
        if val_eval.mean_ap > best_map:
            best_map, best_epoch, best_state = val_eval.mean_ap, epoch, copy.deepcopy(ema.model.state_dict())
        if steps >= total_steps:
            log(f"stopping: reached {steps} steps")
            break
    train_s = time.perf_counter() - train_started
    model.load_state_dict(best_state)
    model.eval()

    model_path = out / MODEL_FILE
    # A static [1, 3, H, W] input: the detector runs one frame at a time.
    example = torch.rand(1, 3, *model.input_hw)
    export_onnx(model, model_path, example, input_name=INPUT_NAME, output_name=OUTPUT_NAME)
    session = onnx_session(model_path, s.threads)
    check = val.images[: max(_CHECK_IMAGES, min(32, len(val)))]
    torch_out = torch_outputs(model, check)
    onnx_out = np.concatenate(
        [session.run([OUTPUT_NAME], {INPUT_NAME: to_input(im[None]).numpy()})[0] for im in check]
    )
    diff = np.abs(torch_out.astype(np.float64) - onnx_out)
    # Scores (0..1) are compared absolutely, boxes (input pixels, up to the input's width)
    # relatively: the numpy.allclose(rtol=tolerance, atol=tolerance) test.
    max_diff = float((diff / (1.0 + np.abs(torch_out))).max())
    max_score_diff, max_box_diff = float(diff[:, 4:].max()), float(diff[:, :4].max())
    if s.check_arrays:
        np.save(out / CHECK_INPUTS_FILE, to_input(check[:_CHECK_IMAGES]).numpy())
        np.save(out / CHECK_TORCH_FILE, torch_out[:_CHECK_IMAGES])
    output_shape = tuple(int(d) for d in onnx_out[:1].shape)
    layout = detect_layout(output_shape, N_COCO)

    # The threshold: best F1 over all classes on the validation split, through the exported model.
    assert val.originals is not None and test.originals is not None
    eval_settings = DetectorSettings(conf_threshold=EVAL_CONF_THRESHOLD, intra_op_threads=s.threads)
    detector = OnnxDetector(model_path, eval_settings)
    val_eval = evaluate_detections(detect_all(detector, val.originals), val.truths)
    chosen = val_eval.best_f1()
    threshold = chosen.threshold
    test_found = detect_all(detector, test.originals)
    test_eval = evaluate_detections(test_found, test.truths)
    at_threshold = test_eval.at_threshold(threshold)
    timed = test.originals[: s.fps_frames]
    speed = {
        "recommended_threshold": time_detector(
            model_path, timed, DetectorSettings(conf_threshold=threshold, intra_op_threads=2)
        ),
        "threshold_0": time_detector(
            model_path, timed, DetectorSettings(conf_threshold=0.0, intra_op_threads=2)
        ),
    }
    per_frame_truth = [int(t.kept.sum()) for t in test.truths]
    metrics: dict[str, Any] = {
        "model": MODEL_FILE,
        "test_map50": test_eval.mean_ap,
        "test_per_class": _class_table(test_eval, names),
        "val_map50": val_eval.mean_ap,
        "torch_val_map50_best_epoch": best_map,
        "recommended_conf_threshold": threshold,
        "threshold_choice": "best F1 over all classes on the validation split (candidates 0.01 ... 0.99)",
        "val_at_threshold": asdict(chosen),
        "test_at_threshold": asdict(at_threshold),
        "test_operating_points": [asdict(test_eval.at_threshold(t)) for t in OPERATING_POINTS],
        "test_objects_per_frame": float(np.mean(per_frame_truth)),
        "test_visible_objects_per_frame": float(np.mean([len(t) for t in test.truths])),
        "speed_640x480_2_threads": speed,
        "onnx_max_diff": max_diff,
        "onnx_max_abs_diff_scores": max_score_diff,
        "onnx_max_abs_diff_boxes_px": max_box_diff,
        "onnx_tolerance": EXPORT_TOLERANCE,
        "parameters": n_params,
        "model_bytes": model_path.stat().st_size,
        "classes": [{"class_id": c, "name": names[c]} for c in classes],
        "best_epoch": best_epoch,
        "epochs_run": len(history),
        "steps": steps,
        "history": history,
        "sizes": {
            "train": len(train),
            "val": len(val),
            "test": len(test),
            "train_objects": n_objects,
            "test_objects": int(sum(per_frame_truth)),
        },
        "worlds": {
            "train": sorted({w for w, _ in train.sources}),
            "val": sorted({w for w, _ in val.sources}),
            "test": sorted({w for w, _ in test.sources}),
        },
        "ground_truth": {
            "min_side_px": MIN_SIDE_PX,
            "min_visible_fraction": MIN_VISIBLE_FRACTION,
            "others": "ignored (VOC difficult)",
        },
        "evaluation": {
            "iou_threshold": 0.5,
            "conf_threshold": EVAL_CONF_THRESHOLD,
            "nms_iou_threshold": eval_settings.iou_threshold,
            "max_detections": eval_settings.max_detections,
            "through": "OnnxDetector on the exported file, 640x480 BGR frames",
        },
        "seconds": {"render": render_s, "train": train_s, "total": time.perf_counter() - started},
        "settings": {**asdict(s), "out": str(s.out), "val_frames": s.val_size, "test_frames": s.test_size},
        "input": {"name": INPUT_NAME, "shape": [1, 3, *s.input_hw], "dtype": "float32", "range": "RGB 0..1"},
        "output": {
            "name": OUTPUT_NAME,
            "shape": list(output_shape),
            "layout": layout.value,
            "meaning": "cx cy w h (input pixels), 80 COCO class scores (0..1)",
        },
        "opset": OPSET,
        "versions": versions(opencv=cv2.__version__),
        "threads": s.threads,
    }
    metrics_path = write_json(out / METRICS_FILE, metrics)
    picks = np.linspace(0, len(test) - 1, 4).round().astype(int).tolist()
    _draw_examples(test, test_found, picks, threshold, names, out / EXAMPLES_FILE)
    _plot_pr(test_eval, threshold, names, out / PR_FILE)
    fast = speed["recommended_threshold"]
    log(
        f"test mAP@0.5 {test_eval.mean_ap:.3f} over {len(test_eval.evaluated_classes)} classes; "
        f"conf {threshold:.2f}: precision {at_threshold.precision:.3f}, recall {at_threshold.recall:.3f}, "
        f"{at_threshold.detections_per_frame:.1f} detections per frame "
        f"({np.mean(per_frame_truth):.1f} objects); "
        f"{fast['ms_per_frame_mean']:.1f} ms per 640x480 frame ({fast['fps']:.0f} fps, 2 threads); "
        f"{n_params} parameters, {metrics['model_bytes']} bytes, torch vs onnxruntime max diff {max_diff:.2e}"
    )
    check_export(max_diff, EXPORT_TOLERANCE)
    return TrainResult(model_path, metrics_path, test_eval.mean_ap, max_diff, metrics)


def parse_args(argv: Sequence[str] | None = None) -> TrainSettings:
    d = TrainSettings()
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, default=d.out, help="output folder (default: beside this script)")
    p.add_argument("--frames", type=int, default=d.frames, help="training frames")
    p.add_argument("--val-frames", type=int, help="validation frames (default frames/10, at least 8)")
    p.add_argument("--test-frames", type=int, help="test frames (default frames/8, at least 8)")
    p.add_argument("--frames-per-world", type=int, default=d.frames_per_world)
    p.add_argument("--data-seeds", type=int, nargs=3, default=d.data_seeds, metavar=("TRAIN", "VAL", "TEST"))
    p.add_argument("--seed", type=int, default=d.seed, help="seed of initialisation, shuffling, augmentation")
    p.add_argument("--input-size", type=int, nargs=2, default=d.input_hw, metavar=("HEIGHT", "WIDTH"))
    p.add_argument(
        "--crop-size",
        type=int,
        nargs=2,
        default=d.crop_hw,
        metavar=("HEIGHT", "WIDTH"),
        help="training crops",
    )
    p.add_argument("--full-frames", action="store_true", help="train on whole inputs, no crops")
    p.add_argument("--widths", type=int, nargs=5, default=d.widths, help="channels at strides 2 ... 32")
    p.add_argument("--epochs", type=int, default=d.epochs, help="epochs")
    p.add_argument("--max-steps", type=int, help="stop after this many optimiser steps (smoke runs)")
    p.add_argument("--batch-size", type=int, default=d.batch_size)
    p.add_argument("--lr", type=float, default=d.lr)
    p.add_argument("--weight-decay", type=float, default=d.weight_decay)
    p.add_argument("--ema-decay", type=float, default=d.ema_decay)
    p.add_argument("--threads", type=int, default=d.threads, help="torch and onnxruntime threads")
    p.add_argument("--workers", type=int, default=d.workers, help="rendering processes")
    p.add_argument("--fps-frames", type=int, default=d.fps_frames, help="test frames timed for the speed")
    p.add_argument(
        "--check-arrays", action="store_true", help=f"also write {CHECK_INPUTS_FILE}, {CHECK_TORCH_FILE}"
    )
    a = p.parse_args(argv)
    return TrainSettings(
        out=a.out,
        frames=a.frames,
        val_frames=a.val_frames,
        test_frames=a.test_frames,
        frames_per_world=a.frames_per_world,
        data_seeds=(a.data_seeds[0], a.data_seeds[1], a.data_seeds[2]),
        seed=a.seed,
        input_hw=(a.input_size[0], a.input_size[1]),
        crop_hw=None if a.full_frames else (a.crop_size[0], a.crop_size[1]),
        widths=(a.widths[0], a.widths[1], a.widths[2], a.widths[3], a.widths[4]),
        epochs=a.epochs,
        max_steps=a.max_steps,
        batch_size=a.batch_size,
        lr=a.lr,
        weight_decay=a.weight_decay,
        ema_decay=a.ema_decay,
        threads=a.threads,
        workers=a.workers,
        fps_frames=a.fps_frames,
        check_arrays=a.check_arrays,
    )


if __name__ == "__main__":
    run_script(main, parse_args)
