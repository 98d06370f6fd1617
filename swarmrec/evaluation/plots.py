"""Figures of an evaluation: similarity matrix, PR curves, holder load, bytes, the loop-closure funnel."""

from __future__ import annotations

from collections.abc import Sequence
from itertools import pairwise
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only: never needs a display

import matplotlib.pyplot as plt
import numpy as np
import numpy.typing as npt
from matplotlib.colors import PowerNorm

from swarmrec.evaluation.bandwidth import HolderLoad
from swarmrec.evaluation.pr import PRCurve

__all__ = ["block_max", "plot_bytes", "plot_funnel", "plot_holder_load", "plot_pr", "plot_similarity"]


#: The most rows and columns a similarity image shows; bigger matrices are shown by block maxima.
SIMILARITY_BINS = 500


def block_max(
    scores: npt.NDArray[np.float64], bins: int = SIMILARITY_BINS
) -> tuple[npt.NDArray[np.float64], int]:
    """``scores`` shrunk to at most ``bins`` x ``bins`` by the maximum of each block, and the
    block size. An image of 2500 frames is drawn on a few hundred pixels: a pixel showing any
    one frame pair of its block would hide most of a sparse matrix's scores; its maximum
    shows each one."""
    n = scores.shape[0]
    if n <= bins:
        return scores, 1
    f = -(-n // bins)
    pad = (-n) % f
    padded = np.pad(scores, ((0, pad), (0, pad)), constant_values=0.0)
    m = padded.shape[0] // f
    return padded.reshape(m, f, m, f).max(axis=(1, 3)), f


def plot_similarity(
    dense: npt.NDArray[np.float64],
    title: str,
    path: Path,
    best_threshold: float = 0.25,
    robot_starts: Sequence[int] = (),
) -> None:
    """Scores as an image (negative sentinels shown as 0; a big matrix by block maxima), with
    each frame's best match above ``best_threshold`` marked, as in the paper's Fig. 4, and
    the robots' blocks of frames marked where ``robot_starts`` (each robot's first frame) says."""
    n = dense.shape[0]
    shown, block = block_max(np.clip(dense, 0.0, 1.0))
    positive = shown[shown > 0]
    # The colour scale ends at the 99th percentile of the scores present, and a square-root
    # norm lifts the many small ones off the background.
    top = float(np.quantile(positive, 0.99)) if positive.size else 1.0
    fig, ax = plt.subplots(figsize=(6.2, 5.6))
    img = ax.imshow(
        shown,
        cmap="magma_r",
        norm=PowerNorm(0.5, vmin=0.0, vmax=max(top, 1e-6)),
        interpolation="nearest",
        extent=(0, n, n, 0),
    )
    best = np.argmax(dense, axis=1)
    score = dense[np.arange(n), best]
    keep = score > best_threshold
    ax.scatter(
        best[keep] + 0.5,
        np.flatnonzero(keep) + 0.5,
        s=2,
        c="tab:cyan",
        label=f"best match > {best_threshold}",
    )
    starts = [int(s) for s in robot_starts if 0 < s < n]
    for s in starts:
        ax.axhline(s, color="0.55", lw=0.6)
        ax.axvline(s, color="0.55", lw=0.6)
    if robot_starts:
        edges = [0, *starts, n]
        top_axis = ax.secondary_xaxis("top")
        top_axis.set_xticks([(a + b) / 2 for a, b in pairwise(edges)])
        top_axis.set_xticklabels([f"r{r}" for r in range(len(edges) - 1)], fontsize=7)
        top_axis.tick_params(length=0)
    ax.set_xlabel("frame")
    ax.set_ylabel("frame")
    ax.set_title(title + (f" (max of {block}x{block} blocks)" if block > 1 else ""), fontsize=9)
    ax.legend(loc="lower left", fontsize=7, markerscale=4)
    fig.colorbar(img, ax=ax, fraction=0.046, label="score")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


#: The robots' trajectories: no green and no red, which mark true and false closures.
_ROBOT_COLOURS = (
    "tab:blue",
    "tab:orange",
    "tab:purple",
    "tab:brown",
    "tab:pink",
    "tab:gray",
    "tab:olive",
    "tab:cyan",
)


def plot_closures_map(
    positions: npt.NDArray[np.float64],
    robot_starts: Sequence[int],
    closures: Sequence[tuple[int, int]],
    truth: npt.NDArray[np.bool_] | None,
    title: str,
    path: Path,
) -> tuple[int, int]:
    """The camera trajectory seen from above (x, y of ``positions``, one colour per robot's
    block of frames from ``robot_starts``) with each loop closure (two frame indices) drawn
    between its frames: green where ``truth`` says the pair is a true closure, red where not,
    grey without a truth. Returns (true, false) closures drawn."""
    n = positions.shape[0]
    edges = [*[int(s) for s in robot_starts], n] if robot_starts else [0, n]
    fig, ax = plt.subplots(figsize=(6.2, 5.6))
    for r, (a, b) in enumerate(pairwise(edges)):
        colour = _ROBOT_COLOURS[r % len(_ROBOT_COLOURS)]
        ax.plot(positions[a:b, 0], positions[a:b, 1], lw=1.4, color=colour, label=f"robot {r}")
    right = wrong = 0
    for q, m in closures:
        ok = None if truth is None else bool(truth[q, m])
        right, wrong = right + (ok is True), wrong + (ok is False)
        colour = "0.4" if ok is None else ("tab:green" if ok else "tab:red")
        ax.plot(*zip(positions[q, :2], positions[m, :2], strict=True), lw=0.7, color=colour, alpha=0.85)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    said = f"{right} true, {wrong} false" if truth is not None else f"{len(closures)}"
    ax.set_title(f"{title}: loop closures on the trajectory ({said})", fontsize=9)
    if len(edges) - 1 <= 12:
        ax.legend(loc="best", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return right, wrong


def plot_pr(curves: dict[str, PRCurve], path: Path) -> None:
    """Precision over recall, one line per mode, AUC in the legend (paper Fig. 5)."""
    fig, ax = plt.subplots(figsize=(5, 4))
    for name, curve in curves.items():
        ax.plot(curve.recall, curve.precision, label=f"{name}, AUC = {curve.auc:.4f}")
    ax.set_xlabel("recall")
    ax.set_ylabel("precision")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1.05)
    ax.grid(alpha=0.4)
    ax.legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_holder_load(
    load: HolderLoad, label_counts: npt.NDArray[np.int64], label_names: tuple[str, ...], path: Path
) -> None:
    """Left: share of each label among detected objects, coloured by holder
    (paper Fig. 6). Right: partial queries received by each holder."""
    n_holders = len(load.partial_queries)
    colors = plt.get_cmap("tab10" if n_holders <= 10 else "tab20")
    holder = np.repeat(np.arange(n_holders), np.diff(load.bounds))
    share = 100.0 * label_counts / max(int(label_counts.sum()), 1)
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 3.6), gridspec_kw={"width_ratios": [2, 1]})
    left.bar(np.arange(len(share)), share, color=[colors(h % colors.N) for h in holder], width=0.9)
    for idx in np.argsort(-share)[:5]:
        if share[idx] > 0:
            left.annotate(label_names[idx], (idx, share[idx]), fontsize=7, ha="center", va="bottom")
    left.set_xlabel("label index")
    left.set_ylabel("% of detected objects")
    left.set_title("labels, coloured by range holder")
    right.bar(
        np.arange(n_holders),
        load.partial_queries,
        color=[colors(h % colors.N) for h in range(n_holders)],
    )
    mean = float(np.mean(load.partial_queries))
    right.axhline(mean, color="k", ls="--", lw=1, label=f"mean; busiest/mean = {load.balance_ratio:.2f}")
    right.set_xlabel("range holder")
    right.set_ylabel("partial queries received")
    right.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_bytes(per_query_by_message: dict[str, float], path: Path) -> None:
    """Bytes sent between robots per query, by message type (measured)."""
    names = list(per_query_by_message)
    values = [per_query_by_message[n] for n in names]
    fig, ax = plt.subplots(figsize=(6, 3.2))
    ax.barh(names, values, color="tab:blue")
    for y, v in enumerate(values):
        ax.text(v, y, f" {v:.1f}", va="center", fontsize=8)
    ax.set_xlabel(f"bytes per query between robots (total {sum(values):.1f} B)")
    ax.grid(axis="x", alpha=0.4)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_funnel(
    levels: list[tuple[str, int]],
    stops_by_robot: dict[int, dict[str, int]],
    path: Path,
    order: list[str] | None = None,
) -> None:
    """Left: the loop-closure funnel, candidates left after each stage. Right: where the
    candidates of each robot's queries stopped, stacked by reason (in ``order`` from the
    bottom; by name without it)."""
    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 3.8), gridspec_kw={"width_ratios": [1, 1.3]})
    names = [name for name, _n in levels][::-1]
    values = [n for _name, n in levels][::-1]
    top = max(values, default=0) or 1
    left.barh(names, values, color="tab:blue")
    for y, v in enumerate(values):
        left.text(v, y, f" {v} ({100 * v / top:.1f} %)", va="center", fontsize=8)
    left.set_xlim(0, top * 1.35)
    left.set_xlabel("candidates (distinct frames per query)")
    left.set_title("the loop-closure funnel")
    left.grid(axis="x", alpha=0.4)
    robots = sorted(stops_by_robot)
    present = {r for stops in stops_by_robot.values() for r in stops}
    reasons = [r for r in order if r in present] if order else sorted(present)
    colors = plt.get_cmap("tab20")
    bottom = np.zeros(len(robots))
    for i, reason in enumerate(reasons):
        counts = np.array([stops_by_robot[r].get(reason, 0) for r in robots], dtype=np.float64)
        right.bar(robots, counts, bottom=bottom, label=reason, color=colors(i % colors.N))
        bottom += counts
    right.set_xlabel("querying robot")
    right.set_ylabel("candidates")
    right.set_title("where each robot's candidates stopped")
    right.set_xticks(robots)
    right.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
