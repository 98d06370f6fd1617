"""Train the place descriptor: a small CNN with a NetVLAD head, reduced to 128 dimensions.

Cieslewski and Scaramuzza route each frame by one full-image descriptor (NetVLAD, d = 128
through a final PCA layer). This script makes the project's own from the synthetic office
renders (:mod:`swarmrec.synthetic.render`), so nothing is downloaded: many worlds, each its
own ``OfficeConfig`` seed (object placement, colours, path, sensor noise); training worlds
also vary the desk count, orbit, camera height, wobble, glances and loops, the validation
and test worlds are the default office (the world a swarm replays).

Places and labels come from the known poses (:mod:`swarmrec.vpr.places`): two views are a
positive pair when their cameras are at most 0.5 m apart and look at most 30 deg apart, a
negative pair when more than 1 m or 60 deg apart or in different worlds; pairs in between
are ignored. Each batch holds anchors from a few worlds, each with one positive from
another pass of the camera (more than 100 frames away), and the loss is a multi-positive
contrastive loss (InfoNCE over cosine similarities, every other view of the batch a
candidate), so the other views of the same world are the negatives the model must push away,
the twin desks included.

The network: seven 3x3 convolutions, four of them strided (96 x 128 RGB -> 6 x 8 x 128 local
features), NetVLAD pooling (16 clusters, intra-normalised, then L2), a linear layer
2048 -> 128 (the paper's PCA layer, learnt end to end) and L2 normalisation: the output
is a unit vector, so squared L2 distance = 2 - 2 cos.

The model ships as ONNX (input ``image``: float32 ``[N, 3, 96, 128]`` RGB in 0..1, the
normalisation is inside the graph; output ``descriptor``: float32 ``[N, 128]``, unit
rows), run by onnxruntime in :mod:`swarmrec.vpr.model`; torch is only needed here::

    .venv-train/bin/python models/descriptor/train.py                  # writes models/descriptor/
    .venv-train/bin/python models/descriptor/train.py --steps 3 --train-worlds 1 --val-worlds 1 \\
        --test-worlds 1 --world-frames 400 --frame-stride 8 --workers 1 --out /tmp/smoke

Frames are rendered at 256 x 192 and area-averaged to 128 x 96, as a 640 x 480 camera
frame resized with ``cv2.INTER_AREA`` would be. Test metrics (recall@1, recall@5, AUC on
held-out worlds, and the same for a tiny-image baseline) are computed on the exported file.
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
import onnxruntime as ort  # type: ignore[import-untyped]  # onnxruntime ships no type hints
import torch
import torch.nn.functional as F
from torch import nn

from swarmrec.errors import ConfigError
from swarmrec.vpr.data import INPUT_HW, RenderedWorld, render_world
from swarmrec.vpr.places import (
    TRAIN_NEGATIVE,
    TRAIN_POSITIVE,
    PlaceThresholds,
    RetrievalMetrics,
    eligible_pairs,
    pair_distances,
    retrieval_metrics,
    same_place,
)

# What the three training scripts share lives beside them (models/ is no package).
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from training_common import (
    OPSET,
    check_export,
    export_onnx,
    log,
    onnx_session,
    run_onnx,
    run_script,
    run_torch,
    to_input,
    versions,
    write_json,
)

ImageArray = npt.NDArray[np.uint8]
FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

HERE = Path(__file__).resolve().parent
MODEL_FILE = "descriptor.onnx"
METRICS_FILE = "metrics.json"
CHECK_INPUTS_FILE = "check_inputs.npy"
CHECK_TORCH_FILE = "check_torch_descriptors.npy"
INPUT_NAME = "image"
OUTPUT_NAME = "descriptor"
DIMENSION = 128
#: Largest allowed |torch - onnxruntime| over the test descriptors (unit vectors).
EXPORT_TOLERANCE = 1e-4
#: Revisit positives are at least this many frames apart (another pass of the camera).
REVISIT_FRAMES = 100
#: The tiny-image baseline: grey images of this (height, width), zero mean, unit norm.
BASELINE_HW = (12, 16)
_CHECK_BATCH = 16


@dataclass(frozen=True)
class TrainSettings:
    """Everything a training run depends on."""

    out: Path = HERE
    train_worlds: int = 40
    val_worlds: int = 2
    test_worlds: int = 4
    #: Frames of each generated world, and every how many of them are rendered.
    world_frames: int = 2500
    frame_stride: int = 4
    #: World ``j`` of a split has ``OfficeConfig.seed = 1000 * base + j`` (disjoint splits).
    data_seeds: tuple[int, int, int] = (11, 12, 13)
    #: Seed of initialisation, batch sampling and augmentation.
    seed: int = 0
    #: Optimiser steps in all; training also stops after ``max_minutes``.
    steps: int = 3000
    max_minutes: float = 22.0
    #: Steps the learning-rate schedule spans (default: ``steps``); with ``steps`` below it, a
    #: run stopped early by ``max_minutes`` is repeated exactly: ``--steps 838 --schedule-steps 3000``.
    schedule_steps: int | None = None
    #: A batch: ``worlds_per_batch`` worlds x ``anchors_per_world`` anchors x (anchor, positive).
    worlds_per_batch: int = 4
    anchors_per_world: int = 8
    lr: float = 2e-3
    weight_decay: float = 1e-4
    #: Temperature of the contrastive loss on cosine similarities.
    temperature: float = 0.07
    #: Validate (recall@1 on the validation worlds) every this many steps; the best is kept.
    val_every: int = 250
    vlad_clusters: int = 16
    threads: int = 2
    workers: int = 2
    check_arrays: bool = False
    #: Keep rendered worlds here and reuse them (same seeds and sampling) on the next run.
    cache: Path | None = None

    def __post_init__(self) -> None:
        for name in (
            "train_worlds", "val_worlds", "test_worlds", "frame_stride", "steps",
            "worlds_per_batch", "anchors_per_world", "val_every", "vlad_clusters", "threads", "workers",
        ):  # fmt: skip
            if getattr(self, name) < 1:
                raise ConfigError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not 300 <= self.world_frames <= 10000:
            raise ConfigError(f"world_frames must be in [300, 10000], got {self.world_frames}")
        if len(set(self.data_seeds)) != 3 or min(self.data_seeds) < 0:
            raise ConfigError(f"the three data seeds must differ and be >= 0, got {self.data_seeds}")
        if max(self.train_worlds, self.val_worlds, self.test_worlds) > 999:
            raise ConfigError("a split may have at most 999 worlds (its seeds would reach the next split's)")
        if self.schedule_steps is not None and self.schedule_steps < self.steps:
            raise ConfigError(f"schedule_steps must be >= steps, got {self.schedule_steps} < {self.steps}")
        for name in ("lr", "temperature", "max_minutes"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"{name} must be > 0, got {value}")
        if not (math.isfinite(self.weight_decay) and self.weight_decay >= 0):
            raise ConfigError(f"weight_decay must be >= 0, got {self.weight_decay}")


@dataclass(frozen=True)
class TrainResult:
    model: Path
    metrics_file: Path
    test_recall_at_1: float
    onnx_max_abs_diff: float
    metrics: dict[str, Any] = field(repr=False)


# --- data ---------------------------------------------------------------------------------------


def _render_job(job: tuple[int, int, int, bool, str]) -> RenderedWorld:
    """One world, from the cache folder when it was rendered before (same seed and sampling)."""
    seed, frames, stride, vary, cache = job
    path = Path(cache) / f"world_{seed}_{frames}_{stride}_{int(vary)}.npz" if cache else None
    if path is not None and path.is_file():
        with np.load(path) as d:
            return RenderedWorld(seed, d["images"], d["frames"], d["positions"], d["directions"])
    world = render_world(seed, frames, stride, vary)
    if path is not None:
        np.savez(path, images=world.images, frames=world.frames, positions=world.positions,
                 directions=world.directions)  # fmt: skip
    return world


def render_split(base: int, count: int, s: TrainSettings, vary: bool, stride: int) -> list[RenderedWorld]:
    cache = str(s.cache) if s.cache else ""
    if s.cache:
        s.cache.mkdir(parents=True, exist_ok=True)
    jobs = [(1000 * base + j, s.world_frames, stride, vary, cache) for j in range(count)]
    if s.workers == 1 or len(jobs) == 1:
        return [_render_job(job) for job in jobs]
    # spawn: forking a process that has started torch's thread pools can deadlock.
    with ProcessPoolExecutor(s.workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        return list(pool.map(_render_job, jobs))


def revisit_positives(world: RenderedWorld) -> list[IntArray]:
    """For each frame, the frames of another pass (> REVISIT_FRAMES apart) showing the same place."""
    distance, angle = pair_distances(world.positions, world.directions)
    far = np.abs(world.frames[:, None] - world.frames[None, :]) > REVISIT_FRAMES
    positive = (distance <= TRAIN_POSITIVE.max_distance_m) & (angle <= TRAIN_POSITIVE.max_angle_deg) & far
    return [np.flatnonzero(row).astype(np.int64) for row in positive]


# --- model --------------------------------------------------------------------------------------


def _conv(n_in: int, n_out: int, stride: int = 1) -> list[nn.Module]:
    """A 3x3 convolution with batch norm and ReLU."""
    return [nn.Conv2d(n_in, n_out, 3, stride=stride, padding=1, bias=False), nn.BatchNorm2d(n_out), nn.ReLU()]


class NetVLAD(nn.Module):
    """Soft-assign each local feature to ``clusters`` learnt centres and sum the residuals."""

    def __init__(self, clusters: int, dim: int) -> None:
        super().__init__()
        self.assign = nn.Conv2d(dim, clusters, 1)
        self.centres = nn.Parameter(torch.randn(clusters, dim) * 0.1)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        unit = F.normalize(features, dim=1)  # per-location unit features
        x = unit.flatten(2)  # (N, D, HW)
        a = torch.softmax(self.assign(unit).flatten(2), dim=1)  # (N, K, HW)
        # sum_hw a_k (x - c_k) = (a @ x^T) - c_k * sum_hw a_k
        vlad = torch.matmul(a, x.transpose(1, 2)) - self.centres[None] * a.sum(2, keepdim=True)
        vlad = F.normalize(vlad, dim=2)  # intra-normalisation: no cluster dominates by burstiness
        return F.normalize(vlad.flatten(1), dim=1)


class PlaceDescriptor(nn.Module):
    """RGB 0..1 ``(N, 3, 96, 128)`` -> unit descriptor ``(N, 128)``. ``mean``/``std`` are the
    training images' per-channel statistics, kept in the graph so callers feed plain 0..1 RGB."""

    def __init__(self, mean: Sequence[float], std: Sequence[float], clusters: int = 16) -> None:
        super().__init__()
        self.mean: torch.Tensor
        self.std: torch.Tensor
        self.register_buffer("mean", torch.tensor(mean, dtype=torch.float32).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor(std, dtype=torch.float32).view(1, 3, 1, 1))
        # Down to stride 16 fast (two strided convolutions first), then two convolutions at each of
        # strides 4, 8 and 16: ~30 M multiply-adds per 96 x 128 frame, a third of a plain VGG-like
        # stack of the same widths, which on 2 shared CPU cores is the difference between a few
        # hundred and a few thousand training steps; 6 x 8 = 48 local features for NetVLAD.
        self.backbone = nn.Sequential(
            *_conv(3, 16, 2), *_conv(16, 32, 2), *_conv(32, 32),
            *_conv(32, 64, 2), *_conv(64, 64),
            *_conv(64, 128, 2), *_conv(128, 128),
        )  # fmt: skip
        self.pool = NetVLAD(clusters, 128)
        self.reduce = nn.Linear(clusters * 128, DIMENSION)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        features = self.backbone((image - self.mean) / self.std)
        return F.normalize(self.reduce(self.pool(features)), dim=1)


def augment(batch: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """Lighting (gain, contrast, a colour cast) and shifts of up to 6 px: what changes between two
    visits of a place in a real room. No flips: a mirrored room is another place."""
    n = batch.shape[0]
    gain = 0.75 + 0.5 * torch.rand(n, 1, 1, 1, generator=generator)
    cast = 1.0 + 0.08 * (torch.rand(n, 3, 1, 1, generator=generator) - 0.5)
    contrast = 0.8 + 0.4 * torch.rand(n, 1, 1, 1, generator=generator)
    mean = batch.mean(dim=(1, 2, 3), keepdim=True)
    out = ((batch - mean) * contrast + mean) * gain * cast
    shift = 6
    padded = F.pad(out, (shift, shift, shift, shift), mode="replicate")
    offsets = torch.randint(0, 2 * shift + 1, (n, 2), generator=generator).tolist()
    h, w = batch.shape[-2:]
    return torch.stack([padded[i, :, y : y + h, x : x + w] for i, (y, x) in enumerate(offsets)]).clamp(0, 1)


def pair_masks(
    worlds: torch.Tensor, positions: torch.Tensor, directions: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Positive and negative pairs of a batch from its poses (see the module docstring)."""
    same_world = worlds[:, None] == worlds[None, :]
    distance = torch.cdist(positions, positions)
    angle = torch.rad2deg(torch.acos((directions @ directions.T).clamp(-1.0, 1.0)))
    eye = torch.eye(len(worlds), dtype=torch.bool)
    positive = (
        same_world
        & (distance <= TRAIN_POSITIVE.max_distance_m)
        & (angle <= TRAIN_POSITIVE.max_angle_deg)
        & ~eye
    )
    negative = (
        ~same_world | (distance > TRAIN_NEGATIVE.max_distance_m) | (angle > TRAIN_NEGATIVE.max_angle_deg)
    )
    return positive, negative & ~eye


def contrastive_loss(
    descriptors: torch.Tensor, positive: torch.Tensor, negative: torch.Tensor, temperature: float
) -> torch.Tensor:
    """Multi-positive InfoNCE: for each view with a positive, -log of the softmax mass that its
    positives get among its positives and negatives (ignored pairs take no part)."""
    logits = descriptors @ descriptors.T / temperature
    candidates = positive | negative
    masked = logits.masked_fill(~candidates, float("-inf"))
    log_all = torch.logsumexp(masked, dim=1)
    log_pos = torch.logsumexp(logits.masked_fill(~positive, float("-inf")), dim=1)
    has = positive.any(dim=1)
    return (log_all[has] - log_pos[has]).mean()


class BatchSampler:
    """Anchors with a revisit positive, ``anchors_per_world`` from each of ``worlds_per_batch``
    worlds, each followed by one of its positives."""

    def __init__(self, worlds: list[RenderedWorld], s: TrainSettings) -> None:
        self.worlds = worlds
        self.positives = [revisit_positives(w) for w in worlds]
        self.anchors = [np.flatnonzero([len(p) > 0 for p in pos]) for pos in self.positives]
        self.usable = [i for i, a in enumerate(self.anchors) if len(a) > 0]
        if not self.usable:
            raise ConfigError("no training frame has a revisit: render more frames per world")
        self.s = s
        self.rng = np.random.default_rng([s.seed, 0xBA7C])

    def sample(self) -> tuple[ImageArray, IntArray, FloatArray, FloatArray]:
        s, rng = self.s, self.rng
        chosen = rng.choice(self.usable, size=min(s.worlds_per_batch, len(self.usable)), replace=False)
        images, world_ids, positions, directions = [], [], [], []
        for w in chosen.tolist():
            world = self.worlds[w]
            anchors = rng.choice(
                self.anchors[w], size=min(s.anchors_per_world, len(self.anchors[w])), replace=False
            )
            for a in anchors.tolist():
                for i in (a, int(rng.choice(self.positives[w][a]))):
                    images.append(world.images[i])
                    world_ids.append(w)
                    positions.append(world.positions[i])
                    directions.append(world.directions[i])
        return (
            np.stack(images),
            np.array(world_ids, np.int64),
            np.array(positions, np.float64),
            np.array(directions, np.float64),
        )


# --- evaluation ---------------------------------------------------------------------------------


def describe_torch(model: PlaceDescriptor, images: ImageArray, batch_size: int = 256) -> FloatArray:
    descriptors: FloatArray = run_torch(model, images, batch_size)
    return descriptors


def describe_onnx(session: ort.InferenceSession, images: ImageArray, batch_size: int = 256) -> FloatArray:
    return run_onnx(session, images, INPUT_NAME, OUTPUT_NAME, batch_size)


def tiny_image(images: ImageArray) -> FloatArray:
    """The baseline: each image as a 16 x 12 grey thumbnail, zero mean, unit norm (192-d)."""
    out = []
    for rgb in images:
        grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        thumb = cv2.resize(grey, (BASELINE_HW[1], BASELINE_HW[0]), interpolation=cv2.INTER_AREA)
        v = thumb.astype(np.float64).ravel()
        v -= v.mean()
        out.append(v / max(float(np.linalg.norm(v)), 1e-12))
    return np.stack(out)


def world_metrics(world: RenderedWorld, descriptors: FloatArray) -> RetrievalMetrics:
    thresholds = PlaceThresholds()
    closures = same_place(world.positions, world.directions, world.frames, thresholds)
    eligible = eligible_pairs(world.frames, thresholds.exclusion_frames)
    return retrieval_metrics(descriptors, closures, eligible)[0]


def pooled(per_world: list[RetrievalMetrics]) -> dict[str, float]:
    """Recall pooled over every query of every world; AUC averaged over the worlds."""
    matched = sum(m.queries_with_match for m in per_world)
    return {
        "recall_at_1": sum(m.recall_at_1 * m.queries_with_match for m in per_world) / max(matched, 1),
        "recall_at_5": sum(m.recall_at_5 * m.queries_with_match for m in per_world) / max(matched, 1),
        "auc": float(np.mean([m.auc for m in per_world])),
        "queries": sum(m.queries for m in per_world),
        "queries_with_match": matched,
    }


def main(settings: TrainSettings) -> TrainResult:
    """Render the worlds, train, keep the step with the best validation recall@1, export it to
    ONNX, check it against torch and write ``descriptor.onnx`` and ``metrics.json``."""
    s = settings
    torch.set_num_threads(s.threads)
    torch.manual_seed(s.seed)
    generator = torch.Generator().manual_seed(s.seed)
    out = Path(s.out)
    out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()

    train = render_split(s.data_seeds[0], s.train_worlds, s, vary=True, stride=s.frame_stride)
    val = render_split(s.data_seeds[1], s.val_worlds, s, vary=False, stride=s.frame_stride)
    test = render_split(s.data_seeds[2], s.test_worlds, s, vary=False, stride=max(1, s.frame_stride // 2))
    render_s = time.perf_counter() - started
    log(
        f"rendered {sum(map(len, train))} train, {sum(map(len, val))} val, "
        f"{sum(map(len, test))} test frames in {render_s:.1f} s"
    )

    pixels = np.concatenate([w.images[::10].reshape(-1, 3) for w in train]).astype(np.float64) / 255.0
    model = PlaceDescriptor(pixels.mean(axis=0).tolist(), pixels.std(axis=0).tolist(), s.vlad_clusters)
    n_params = sum(p.numel() for p in model.parameters())
    sampler = BatchSampler(train, s)
    optimiser = torch.optim.AdamW(model.parameters(), lr=s.lr, weight_decay=s.weight_decay)
    # A short linear warm-up, then cosine decay to a tenth: from scratch the contrastive loss
    # needs the warm-up, or the NetVLAD assignment collapses onto one cluster in the first steps.
    span = s.schedule_steps or s.steps
    warmup = max(1, min(150, span // 10))

    def lr_factor(step: int) -> float:
        if step < warmup:
            return (step + 1) / warmup
        return 0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * (step - warmup) / max(1, span - warmup)))

    scheduler = torch.optim.lr_scheduler.LambdaLR(optimiser, lr_factor)

    history: list[dict[str, float]] = []
    best_recall, best_step, best_state = -1.0, 0, copy.deepcopy(model.state_dict())
    steps, loss_sum, loss_count = 0, 0.0, 0
    train_started = time.perf_counter()
    deadline = train_started + 60.0 * s.max_minutes
    while steps < s.steps:
        model.train()
        images, world_ids, positions, directions = sampler.sample()
        x = augment(to_input(images), generator)
        positive, negative = pair_masks(
            torch.from_numpy(world_ids), torch.from_numpy(positions), torch.from_numpy(directions)
        )
        loss = contrastive_loss(model(x), positive, negative, s.temperature)
        optimiser.zero_grad()
        loss.backward()  # type: ignore[no-untyped-call]  # untyped in torch's stubs
        optimiser.step()
        scheduler.step()
        steps += 1
        loss_sum += float(loss.item())
        loss_count += 1
        timed_out = time.perf_counter() > deadline
        if steps % s.val_every == 0 or steps == s.steps or timed_out:
            val_recall = pooled([world_metrics(w, describe_torch(model, w.images)) for w in val])[
                "recall_at_1"
            ]
            history.append(
                {
                    "step": steps,
                    "loss": loss_sum / loss_count,
                    "val_recall_at_1": val_recall,
                    "lr": optimiser.param_groups[0]["lr"],
                    "seconds": time.perf_counter() - train_started,
                }
            )
            log(
                f"step {steps:5d}/{s.steps}  loss {loss_sum / loss_count:.3f}  "
                f"val recall@1 {val_recall:.3f}  ({history[-1]['seconds']:.0f} s)"
            )
            loss_sum, loss_count = 0.0, 0
            if val_recall > best_recall:
                best_recall, best_step, best_state = val_recall, steps, copy.deepcopy(model.state_dict())
        if timed_out:
            log(f"stopping after {s.max_minutes} minutes at step {steps}")
            break
    train_s = time.perf_counter() - train_started
    model.load_state_dict(best_state)
    model.eval()

    model_path = out / MODEL_FILE
    test_images = np.concatenate([w.images for w in test])
    example = to_input(test_images[:4])
    export_onnx(
        model, model_path, example, input_name=INPUT_NAME, output_name=OUTPUT_NAME, dynamic_batch="image"
    )
    session = onnx_session(model_path, s.threads)
    torch_desc = describe_torch(model, test_images)
    onnx_desc = describe_onnx(session, test_images)
    max_diff = float(np.abs(torch_desc - onnx_desc).max())
    if s.check_arrays:
        np.save(out / CHECK_INPUTS_FILE, to_input(test_images[:_CHECK_BATCH]).numpy())
        np.save(out / CHECK_TORCH_FILE, describe_torch(model, test_images[:_CHECK_BATCH]).astype(np.float32))

    t0 = time.perf_counter()
    describe_onnx(session, test_images[:256], batch_size=1)
    ms_per_frame = 1000 * (time.perf_counter() - t0) / min(256, len(test_images))
    model_worlds, baseline_worlds, offset = [], [], 0
    for w in test:
        model_worlds.append(world_metrics(w, onnx_desc[offset : offset + len(w)]))
        baseline_worlds.append(world_metrics(w, tiny_image(w.images)))
        offset += len(w)
    test_metrics, baseline = pooled(model_worlds), pooled(baseline_worlds)
    metrics: dict[str, Any] = {
        "model": MODEL_FILE,
        "test": test_metrics,
        "test_per_world": [asdict(m) | {"seed": w.seed} for m, w in zip(model_worlds, test, strict=True)],
        "baseline": {
            "what": f"tiny image: {BASELINE_HW[1]}x{BASELINE_HW[0]} grey thumbnail of the model input, "
            "zero mean, unit norm (192-d)",
            **pooled(baseline_worlds),
        },
        "baseline_per_world": [
            asdict(m) | {"seed": w.seed} for m, w in zip(baseline_worlds, test, strict=True)
        ],
        "places": {
            "same_place": asdict(PlaceThresholds()),
            "train_positive": asdict(TRAIN_POSITIVE),
            "train_negative": asdict(TRAIN_NEGATIVE),
            "revisit_frames": REVISIT_FRAMES,
        },
        "onnx_max_abs_diff": max_diff,
        "onnx_tolerance": EXPORT_TOLERANCE,
        "ms_per_frame_batch_1": ms_per_frame,
        "parameters": n_params,
        "model_bytes": model_path.stat().st_size,
        "best_step": best_step,
        "best_val_recall_at_1": best_recall,
        "steps": steps,
        "history": history,
        "worlds": {
            "train": [w.seed for w in train],
            "val": [w.seed for w in val],
            "test": [w.seed for w in test],
        },
        "sizes": {"train": sum(map(len, train)), "val": sum(map(len, val)), "test": len(test_images)},
        "seconds": {"render": render_s, "train": train_s, "total": time.perf_counter() - started},
        "settings": {**asdict(s), "out": str(s.out), "cache": str(s.cache) if s.cache else None},
        "input": {
            "name": INPUT_NAME,
            "shape": ["N", 3, *INPUT_HW],
            "dtype": "float32",
            "range": "RGB 0..1, normalised inside the graph",
        },
        "output": {
            "name": OUTPUT_NAME,
            "shape": ["N", DIMENSION],
            "dtype": "float32",
            "meaning": "unit L2 rows",
        },
        "opset": OPSET,
        "versions": versions(),
    }
    metrics_path = write_json(out / METRICS_FILE, metrics)
    log(
        f"test recall@1 {test_metrics['recall_at_1']:.3f} @5 {test_metrics['recall_at_5']:.3f} "
        f"AUC {test_metrics['auc']:.3f} (baseline {baseline['recall_at_1']:.3f} / "
        f"{baseline['recall_at_5']:.3f} / {baseline['auc']:.3f}), {n_params} parameters, "
        f"{metrics['model_bytes']} bytes, "
        f"torch vs onnxruntime max diff {max_diff:.2e}"
    )
    check_export(max_diff, EXPORT_TOLERANCE)
    return TrainResult(model_path, metrics_path, test_metrics["recall_at_1"], max_diff, metrics)


def parse_args(argv: Sequence[str] | None = None) -> TrainSettings:
    d = TrainSettings()
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, default=d.out, help="output folder (default: beside this script)")
    p.add_argument("--train-worlds", type=int, default=d.train_worlds)
    p.add_argument("--val-worlds", type=int, default=d.val_worlds)
    p.add_argument("--test-worlds", type=int, default=d.test_worlds)
    p.add_argument("--world-frames", type=int, default=d.world_frames, help="frames of each generated world")
    p.add_argument("--frame-stride", type=int, default=d.frame_stride, help="render every n-th frame")
    p.add_argument("--data-seeds", type=int, nargs=3, default=d.data_seeds, metavar=("TRAIN", "VAL", "TEST"))
    p.add_argument("--seed", type=int, default=d.seed, help="seed of initialisation, sampling, augmentation")
    p.add_argument("--steps", type=int, default=d.steps, help="optimiser steps (3 for a smoke run)")
    p.add_argument("--max-minutes", type=float, default=d.max_minutes, help="stop training after this long")
    p.add_argument(
        "--schedule-steps", type=int, help="steps the learning-rate schedule spans (default: --steps)"
    )
    p.add_argument("--worlds-per-batch", type=int, default=d.worlds_per_batch)
    p.add_argument("--anchors-per-world", type=int, default=d.anchors_per_world)
    p.add_argument("--lr", type=float, default=d.lr)
    p.add_argument("--weight-decay", type=float, default=d.weight_decay)
    p.add_argument("--temperature", type=float, default=d.temperature)
    p.add_argument("--val-every", type=int, default=d.val_every)
    p.add_argument("--threads", type=int, default=d.threads, help="torch and onnxruntime threads")
    p.add_argument("--workers", type=int, default=d.workers, help="rendering processes")
    p.add_argument("--cache", type=Path, help="folder to keep rendered worlds in and reuse them from")
    p.add_argument(
        "--check-arrays", action="store_true", help=f"also write {CHECK_INPUTS_FILE}, {CHECK_TORCH_FILE}"
    )
    a = p.parse_args(argv)
    return TrainSettings(
        out=a.out,
        train_worlds=a.train_worlds,
        val_worlds=a.val_worlds,
        test_worlds=a.test_worlds,
        world_frames=a.world_frames,
        frame_stride=a.frame_stride,
        data_seeds=(a.data_seeds[0], a.data_seeds[1], a.data_seeds[2]),
        seed=a.seed,
        steps=a.steps,
        max_minutes=a.max_minutes,
        schedule_steps=a.schedule_steps,
        worlds_per_batch=a.worlds_per_batch,
        anchors_per_world=a.anchors_per_world,
        lr=a.lr,
        weight_decay=a.weight_decay,
        temperature=a.temperature,
        val_every=a.val_every,
        threads=a.threads,
        workers=a.workers,
        check_arrays=a.check_arrays,
        cache=a.cache,
    )


if __name__ == "__main__":
    run_script(main, parse_args)
