"""Train the landmark classifier: the WNBC paper's shallow 5-layer CNN on rendered facade views.

Brent, Yuan and Stegagno (SAC '21) give each robot "a 5-layered CNN with 19 different
categories", kept shallow for the robots' computers, and no more detail. We read it
as the textbook shallow CNN: three 3x3 convolution layers (each with ReLU, 2x2 max
pooling and batch norm) and two fully connected layers, softmax over the 19 landmarks;
five layers with weights (batch norm, a per-channel affine map at inference, is not
counted). The views come from :mod:`swarmrec.fusion.facades`, the renderer the street
simulation uses, so training, validation and test sets are disjoint draws of one
distribution (each split its own seed, each shard of a split its own stream).

The model ships as ONNX (input ``image``: float32 ``[N, 3, 64, 64]`` RGB scaled to
0..1, the per-channel normalisation is inside the graph; output ``probabilities``:
``[N, 19]`` softmax) because the services run it on onnxruntime: torch is only
needed here, in the separate training environment::

    python3 -m venv .venv-train
    .venv-train/bin/pip install -r models/requirements-train.txt
    .venv-train/bin/pip install --no-deps -e .
    .venv-train/bin/python models/landmarks/train.py                 # writes models/landmarks/
    .venv-train/bin/python models/landmarks/train.py --per-class 4 --epochs 1 --max-steps 3 --out /tmp/smoke

Test metrics are computed with onnxruntime on the exported file, so they describe the
artefact that ships; the export is checked against torch on the whole test set.
"""

from __future__ import annotations

import argparse
import copy
import itertools
import math
import multiprocessing
import sys
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import onnxruntime as ort  # type: ignore[import-untyped]  # onnxruntime ships no type hints
import torch
import torch.nn.functional as F
from torch import nn

from swarmrec.errors import ConfigError
from swarmrec.fusion.facades import FACADE_DESIGNS, IMAGE_SIZE, FacadeDesign, render_view, sample_view

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
LabelArray = npt.NDArray[np.int64]
FloatArray = npt.NDArray[np.float64]

HERE = Path(__file__).resolve().parent
MODEL_FILE = "landmark_cnn.onnx"
METRICS_FILE = "metrics.json"
CONFUSION_FILE = "confusion_matrix.png"
#: Written with ``--check-arrays``: a test batch as fed to the model and torch's outputs on it.
CHECK_INPUTS_FILE = "check_inputs.npy"
CHECK_TORCH_FILE = "check_torch_probabilities.npy"
INPUT_NAME = "image"
OUTPUT_NAME = "probabilities"
N_CLASSES = len(FACADE_DESIGNS)
#: Largest allowed |torch - onnxruntime| over the test set's probabilities.
EXPORT_TOLERANCE = 1e-4
#: Views per class in one render shard. Fixed, so a split is the same whatever the worker count.
_SHARD = 25
_CHECK_BATCH = 32


@dataclass(frozen=True)
class TrainSettings:
    """Everything a training run depends on; ``val_per_class`` and ``test_per_class``
    default to a tenth and a quarter of ``per_class`` (at least 2), so a smoke run
    with a tiny ``per_class`` renders tiny held-out sets too."""

    out: Path = HERE
    per_class: int = 600
    val_per_class: int | None = None
    test_per_class: int | None = None
    #: Seeds of the training, validation and test renders (distinct, so the splits are disjoint).
    data_seeds: tuple[int, int, int] = (1, 2, 3)
    #: Seed of weight initialisation, shuffling and augmentation.
    seed: int = 0
    epochs: int = 10
    #: Stop after this many epochs without a better validation accuracy.
    patience: int = 4
    #: Stop after this many optimiser steps in all (smoke runs); None: no limit.
    max_steps: int | None = None
    batch_size: int = 64
    #: Peak learning rate of the one-cycle schedule.
    lr: float = 3e-3
    weight_decay: float = 1e-4
    #: Random shifts of up to this many pixels (replicate-padded); 0 turns augmentation off.
    shift: int = 4
    threads: int = 2
    #: Processes rendering the views (1: render in this process).
    workers: int = 2
    #: Also write a test batch and torch's probabilities on it, for a test to compare with onnxruntime.
    check_arrays: bool = False

    def __post_init__(self) -> None:
        for name in ("per_class", "epochs", "patience", "batch_size", "threads", "workers"):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("val_per_class", "test_per_class", "max_steps"):
            value = getattr(self, name)
            if value is not None and value < 1:
                raise ConfigError(f"{name} must be >= 1 or unset, got {value}")
        if len(set(self.data_seeds)) != 3:
            raise ConfigError(f"the three data seeds must differ (disjoint splits), got {self.data_seeds}")
        if not (math.isfinite(self.lr) and self.lr > 0):
            raise ConfigError(f"lr must be > 0, got {self.lr}")
        if not (math.isfinite(self.weight_decay) and self.weight_decay >= 0):
            raise ConfigError(f"weight_decay must be >= 0, got {self.weight_decay}")
        if not 0 <= self.shift < IMAGE_SIZE // 4:
            raise ConfigError(f"shift must be in [0, {IMAGE_SIZE // 4}), got {self.shift}")

    @property
    def val_size(self) -> int:
        return self.val_per_class or max(2, self.per_class // 10)

    @property
    def test_size(self) -> int:
        return self.test_per_class or max(2, self.per_class // 4)


@dataclass(frozen=True)
class TrainResult:
    """Where the run wrote its files, and the numbers a caller checks first."""

    model: Path
    metrics_file: Path
    test_accuracy: float
    onnx_max_abs_diff: float
    metrics: dict[str, Any] = field(repr=False)


class LandmarkCNN(nn.Module):
    """Three conv layers (3x3, ReLU, 2x2 max pooling, batch norm: 64 -> 32 -> 16 -> 8 px) and
    two fully connected ones. A last 2x2 pooling to 4x4 keeps where things are (door left or right,
    roof on top) at a quarter of the first FC layer's weights, which keeps the file small.
    ``mean``/``std`` are the training set's per-channel statistics, stored in the graph
    so that callers feed plain 0..1 RGB."""

    def __init__(self, mean: Sequence[float], std: Sequence[float], n_classes: int = N_CLASSES) -> None:
        super().__init__()
        self.mean: torch.Tensor
        self.std: torch.Tensor
        self.register_buffer("mean", torch.tensor(mean, dtype=torch.float32).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor(std, dtype=torch.float32).view(1, 3, 1, 1))
        self.features = nn.Sequential(
            *self._block(3, 24), *self._block(24, 48), *self._block(48, 96), nn.MaxPool2d(2)
        )
        self.classifier = nn.Sequential(
            nn.Flatten(),
            nn.Linear(96 * 4 * 4, 128),
            nn.ReLU(),
            nn.Dropout(0.3),
            nn.Linear(128, n_classes),
        )

    @staticmethod
    def _block(n_in: int, n_out: int) -> list[nn.Module]:
        # Batch norm after the pooling, on a quarter of the pixels: on 2 CPU cores it costs ~15 %
        # per step and gets far more per epoch (0.82 against 0.67 validation accuracy after 8).
        return [nn.Conv2d(n_in, n_out, 3, padding=1), nn.ReLU(), nn.MaxPool2d(2), nn.BatchNorm2d(n_out)]

    def logits(self, image: torch.Tensor) -> torch.Tensor:
        out: torch.Tensor = self.classifier(self.features((image - self.mean) / self.std))
        return out

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        return torch.softmax(self.logits(image), dim=1)


Split = tuple[ImageArray, LabelArray, FloatArray]


def _render_shard(job: tuple[int, int, int]) -> Split:
    """``count`` views of every landmark from the stream ``(seed, shard)``, class-interleaved
    as :func:`swarmrec.fusion.facades.render_dataset` draws them."""
    seed, shard, count = job
    rng = np.random.default_rng([seed, shard])
    images, geometry = [], []
    for _, landmark in itertools.product(range(count), range(N_CLASSES)):
        view = sample_view(rng)
        images.append(render_view(landmark, view, rng))
        geometry.append((view.distance, math.degrees(abs(view.view_angle))))
    labels = np.tile(np.arange(N_CLASSES, dtype=np.int64), count)
    return np.stack(images), labels, np.array(geometry, np.float64)


def render_split(per_class: int, seed: int, workers: int) -> Split:
    """``per_class`` views of each landmark: ``(N, 64, 64, 3)`` uint8 RGB, labels, and each
    view's distance (m) and obliquity (degrees off head-on), to break errors down by view."""
    jobs = [(seed, s, min(_SHARD, per_class - s * _SHARD)) for s in range(math.ceil(per_class / _SHARD))]
    if workers == 1 or len(jobs) == 1:
        parts = [_render_shard(job) for job in jobs]
    else:
        # spawn: forking a process that has started torch's thread pools can deadlock.
        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
            parts = list(pool.map(_render_shard, jobs))
    images, labels, geometry = zip(*parts, strict=True)
    return np.concatenate(images), np.concatenate(labels), np.concatenate(geometry)


def _shift(batch: torch.Tensor, shift: int, generator: torch.Generator) -> torch.Tensor:
    """Each image moved by up to ``shift`` px each way: the camera aims a little off.
    (No flips: a door on the left is a different landmark from one on the right.)"""
    padded = F.pad(batch, (shift, shift, shift, shift), mode="replicate")
    offsets = torch.randint(0, 2 * shift + 1, (batch.shape[0], 2), generator=generator).tolist()
    size = batch.shape[-1]
    return torch.stack([padded[i, :, y : y + size, x : x + size] for i, (y, x) in enumerate(offsets)])


def predict(model: LandmarkCNN, images: ImageArray, batch_size: int = 256) -> FloatArray:
    """torch's probabilities for uint8 images, in eval mode."""
    probabilities: FloatArray = run_torch(model, images, batch_size)
    return probabilities


def predict_onnx(session: ort.InferenceSession, images: ImageArray, batch_size: int = 256) -> FloatArray:
    """onnxruntime's probabilities for uint8 images."""
    return run_onnx(session, images, INPUT_NAME, OUTPUT_NAME, batch_size)


def _top_confusions(confusion: npt.NDArray[np.int64], count: int = 8) -> list[dict[str, Any]]:
    """The largest off-diagonal cells, with what the two designs have in common."""
    rates = confusion / np.maximum(confusion.sum(axis=1, keepdims=True), 1)
    np.fill_diagonal(rates, 0.0)
    cells = []
    for flat in np.argsort(rates, axis=None)[::-1][:count]:
        true, pred = (int(v) for v in np.unravel_index(flat, rates.shape))
        if rates[true, pred] == 0:
            break
        a, b = FACADE_DESIGNS[true].attributes(), FACADE_DESIGNS[pred].attributes()
        names = [f.name for f in fields(FacadeDesign)]  # the order of FacadeDesign.attributes()
        shared = {n: x for n, x, y in zip(names, a, b, strict=True) if x == y}
        cells.append({"true": true, "predicted": pred, "rate": float(rates[true, pred]), "shared": shared})
    return cells


#: Bins of the per-view breakdown: distance (m) and obliquity (degrees); sample_view stops at 25 m, 80 deg.
_DISTANCE_BINS = (0.0, 4.0, 8.0, 12.0, 16.0, 25.0)
_ANGLE_BINS = (0.0, 20.0, 40.0, 60.0, 80.0)


def _accuracy_by_view(correct: npt.NDArray[np.bool_], views: FloatArray) -> dict[str, list[dict[str, Any]]]:
    """Test accuracy per distance and per obliquity bin: where the model's errors come from."""
    table: dict[str, list[dict[str, Any]]] = {}
    for name, column, edges in (("distance_m", 0, _DISTANCE_BINS), ("angle_deg", 1, _ANGLE_BINS)):
        rows = []
        for lo, hi in itertools.pairwise(edges):
            inside = (views[:, column] >= lo) & (views[:, column] < hi)
            accuracy = float(correct[inside].mean()) if inside.any() else None
            rows.append({"range": [lo, hi], "views": int(inside.sum()), "accuracy": accuracy})
        table[name] = rows
    return table


def _plot_confusion(confusion: npt.NDArray[np.int64], accuracy: float, path: Path) -> None:
    import matplotlib  # only for the figure; imported here so a headless backend is set first

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rates = confusion / np.maximum(confusion.sum(axis=1, keepdims=True), 1)
    fig, ax = plt.subplots(figsize=(7.5, 6.5), dpi=100)
    im = ax.imshow(rates, cmap="Blues", vmin=0.0, vmax=1.0)
    for (i, j), rate in np.ndenumerate(rates):
        if rate >= 0.01:
            colour = "white" if rate > 0.5 else "black"
            ax.text(j, i, f"{round(100 * rate)}", ha="center", va="center", fontsize=6, color=colour)
    ax.set_xticks(range(N_CLASSES))
    ax.set_yticks(range(N_CLASSES))
    ax.tick_params(labelsize=7)
    ax.set_xlabel("predicted landmark")
    ax.set_ylabel("true landmark")
    ax.set_title(f"Landmark CNN, held-out test views: {100 * accuracy:.1f} % correct (row %)")
    fig.colorbar(im, ax=ax, fraction=0.046)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main(settings: TrainSettings) -> TrainResult:
    """Render the splits, train with early stopping on validation accuracy, export the
    best epoch to ONNX, check it against torch, score it on the test set and write
    ``landmark_cnn.onnx``, ``metrics.json`` and ``confusion_matrix.png`` to ``settings.out``."""
    s = settings
    torch.set_num_threads(s.threads)
    torch.manual_seed(s.seed)
    generator = torch.Generator().manual_seed(s.seed)
    out = Path(s.out)
    out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()

    train_x, train_y, _ = render_split(s.per_class, s.data_seeds[0], s.workers)
    val_x, val_y, _ = render_split(s.val_size, s.data_seeds[1], s.workers)
    test_x, test_y, test_views = render_split(s.test_size, s.data_seeds[2], s.workers)
    render_s = time.perf_counter() - started
    log(f"rendered {len(train_y)} train, {len(val_y)} val, {len(test_y)} test views in {render_s:.1f} s")

    pixels = train_x.reshape(-1, 3).astype(np.float64) / 255.0
    model = LandmarkCNN(pixels.mean(axis=0).tolist(), pixels.std(axis=0).tolist())
    n_params = sum(p.numel() for p in model.parameters())
    optimiser = torch.optim.AdamW(model.parameters(), lr=s.lr, weight_decay=s.weight_decay)
    inputs, labels = to_input(train_x), torch.from_numpy(train_y)
    # One cycle (warm up, then anneal to ~0) fits a CPU budget of minutes: on 300 views per
    # class and 8 epochs it reached 0.85 validation accuracy, cosine decay from 2e-3 0.82.
    # (OneCycleLR divides by the length of its warm-up, so a smoke run's few steps are padded to 8.)
    total_steps = max(8, s.epochs * math.ceil(len(labels) / s.batch_size))
    scheduler = torch.optim.lr_scheduler.OneCycleLR(
        optimiser, max_lr=s.lr, total_steps=total_steps, pct_start=0.25
    )

    history: list[dict[str, float]] = []
    best_acc, best_epoch, best_state = -1.0, 0, copy.deepcopy(model.state_dict())
    steps, train_started = 0, time.perf_counter()
    for epoch in range(1, s.epochs + 1):
        epoch_started = time.perf_counter()
        model.train()
        order = torch.randperm(len(labels), generator=generator)
        loss_sum, correct, seen = 0.0, 0, 0
        for i in range(0, len(order), s.batch_size):
            idx = order[i : i + s.batch_size]
            x, y = inputs[idx], labels[idx]
            if s.shift:
                x = _shift(x, s.shift, generator)
            logits = model.logits(x)
            loss = F.cross_entropy(logits, y)
            optimiser.zero_grad()
            loss.backward()  # type: ignore[no-untyped-call]  # untyped in torch's stubs
            optimiser.step()
            scheduler.step()
            loss_sum += loss.item() * len(y)
            correct += int((logits.argmax(1) == y).sum())
            seen += len(y)
            steps += 1
            if s.max_steps is not None and steps >= s.max_steps:
                break
        val_acc = float((predict(model, val_x).argmax(1) == val_y).mean())
        history.append(
            {
                "epoch": epoch,
                "loss": loss_sum / seen,
                "train_accuracy": correct / seen,
                "val_accuracy": val_acc,
                "lr": optimiser.param_groups[0]["lr"],
                "seconds": time.perf_counter() - epoch_started,
            }
        )
        log(
            f"epoch {epoch:2d}/{s.epochs}  loss {loss_sum / seen:.3f}  train acc {correct / seen:.3f}  "
            f"val acc {val_acc:.3f}  ({history[-1]['seconds']:.1f} s)"
        )
        if val_acc > best_acc:
            best_acc, best_epoch, best_state = val_acc, epoch, copy.deepcopy(model.state_dict())
        if s.max_steps is not None and steps >= s.max_steps:
            log(f"stopping: reached {steps} steps")
            break
        if epoch - best_epoch >= s.patience:
            log(f"early stop: no better validation accuracy for {s.patience} epochs")
            break
    train_s = time.perf_counter() - train_started
    model.load_state_dict(best_state)
    model.eval()

    model_path = out / MODEL_FILE
    export_onnx(
        model,
        model_path,
        to_input(test_x[:8]),
        input_name=INPUT_NAME,
        output_name=OUTPUT_NAME,
        dynamic_batch="image",
    )
    session = onnx_session(model_path, s.threads)
    torch_probs = predict(model, test_x)
    onnx_probs = predict_onnx(session, test_x)
    max_diff = float(np.abs(torch_probs - onnx_probs).max())
    if s.check_arrays:
        np.save(out / CHECK_INPUTS_FILE, to_input(test_x[:_CHECK_BATCH]).numpy())
        np.save(out / CHECK_TORCH_FILE, predict(model, test_x[:_CHECK_BATCH]).astype(np.float32))

    predicted = onnx_probs.argmax(1)
    confusion = np.zeros((N_CLASSES, N_CLASSES), np.int64)
    np.add.at(confusion, (test_y, predicted), 1)
    per_class = (np.diag(confusion) / np.maximum(confusion.sum(axis=1), 1)).tolist()
    accuracy = float((predicted == test_y).mean())
    metrics: dict[str, Any] = {
        "model": MODEL_FILE,
        "test_accuracy": accuracy,
        "torch_test_accuracy": float((torch_probs.argmax(1) == test_y).mean()),
        "per_class_accuracy": per_class,
        "worst_class": int(np.argmin(per_class)),
        "confusion_matrix": confusion.tolist(),
        "confusion_rows": "true landmark",
        "top_confusions": _top_confusions(confusion),
        "accuracy_by_view": _accuracy_by_view(predicted == test_y, test_views),
        "mean_top1_probability": float(onnx_probs.max(axis=1).mean()),
        "onnx_max_abs_diff": max_diff,
        "onnx_tolerance": EXPORT_TOLERANCE,
        "parameters": n_params,
        "model_bytes": model_path.stat().st_size,
        "best_epoch": best_epoch,
        "best_val_accuracy": best_acc,
        "epochs_run": len(history),
        "steps": steps,
        "history": history,
        "sizes": {"train": len(train_y), "val": len(val_y), "test": len(test_y)},
        "seconds": {"render": render_s, "train": train_s, "total": time.perf_counter() - started},
        "settings": {
            **asdict(s),
            "out": str(s.out),
            "val_per_class": s.val_size,
            "test_per_class": s.test_size,
        },
        "input": {
            "name": INPUT_NAME,
            "shape": ["N", 3, IMAGE_SIZE, IMAGE_SIZE],
            "dtype": "float32",
            "range": "RGB 0..1, normalised inside the graph",
        },
        "output": {"name": OUTPUT_NAME, "shape": ["N", N_CLASSES], "dtype": "float32", "meaning": "softmax"},
        "opset": OPSET,
        "versions": versions(),
        "threads": s.threads,
    }
    metrics_path = write_json(out / METRICS_FILE, metrics)
    _plot_confusion(confusion, accuracy, out / CONFUSION_FILE)
    log(
        f"test accuracy {accuracy:.3f} (worst landmark {metrics['worst_class']}: {min(per_class):.3f}), "
        f"{n_params} parameters, {metrics['model_bytes']} bytes, torch vs onnxruntime max diff {max_diff:.2e}"
    )
    check_export(max_diff, EXPORT_TOLERANCE)
    return TrainResult(model_path, metrics_path, accuracy, max_diff, metrics)


def parse_args(argv: Sequence[str] | None = None) -> TrainSettings:
    d = TrainSettings()
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, default=d.out, help="output folder (default: beside this script)")
    p.add_argument("--per-class", type=int, default=d.per_class, help="training views per landmark")
    p.add_argument("--val-per-class", type=int, help="validation views per landmark (default per-class/10)")
    p.add_argument("--test-per-class", type=int, help="test views per landmark (default per-class/4)")
    p.add_argument("--data-seeds", type=int, nargs=3, default=d.data_seeds, metavar=("TRAIN", "VAL", "TEST"))
    p.add_argument("--seed", type=int, default=d.seed, help="seed of initialisation, shuffling, augmentation")
    p.add_argument("--epochs", type=int, default=d.epochs, help="most epochs")
    p.add_argument("--patience", type=int, default=d.patience, help="early stop after this many flat epochs")
    p.add_argument("--max-steps", type=int, help="stop after this many optimiser steps (smoke runs)")
    p.add_argument("--batch-size", type=int, default=d.batch_size)
    p.add_argument("--lr", type=float, default=d.lr)
    p.add_argument("--weight-decay", type=float, default=d.weight_decay)
    p.add_argument("--shift", type=int, default=d.shift, help="random shift augmentation, px (0: off)")
    p.add_argument("--threads", type=int, default=d.threads, help="torch and onnxruntime threads")
    p.add_argument("--workers", type=int, default=d.workers, help="rendering processes")
    p.add_argument(
        "--check-arrays", action="store_true", help=f"also write {CHECK_INPUTS_FILE}, {CHECK_TORCH_FILE}"
    )
    a = p.parse_args(argv)
    return TrainSettings(
        out=a.out,
        per_class=a.per_class,
        val_per_class=a.val_per_class,
        test_per_class=a.test_per_class,
        data_seeds=(a.data_seeds[0], a.data_seeds[1], a.data_seeds[2]),
        seed=a.seed,
        epochs=a.epochs,
        patience=a.patience,
        max_steps=a.max_steps,
        batch_size=a.batch_size,
        lr=a.lr,
        weight_decay=a.weight_decay,
        shift=a.shift,
        threads=a.threads,
        workers=a.workers,
        check_arrays=a.check_arrays,
    )


if __name__ == "__main__":
    run_script(main, parse_args)
