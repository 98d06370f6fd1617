"""The paper's Figs. 6 and 7: relative AUC and worst balance ratio, the mean as a line and
every run as a dot (slightly spread sideways so equal values stay visible)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")  # files only: never needs a display

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.ticker import MaxNLocator

__all__ = ["plot_sweep"]


def plot_sweep(
    rows: list[dict[str, Any]],
    key: str,
    xlabel: str,
    path: Path,
    title: str,
    balanced: dict[str, Any] | None = None,
) -> None:
    """Two panels over ``row[key]``: relative AUC (top) and worst balance ratio (bottom).
    ``balanced``: the re-balanced runs (:mod:`swarmrec.vpr.balance`), drawn as stars at their
    starting clusters per robot."""
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(6, 6), sharex=True)
    xs = np.array([row[key] for row in rows], np.float64)
    spread = 0.12 * float(np.min(np.diff(xs))) if len(xs) > 1 else 0.1
    for ax, metric, label in (
        (top, "relative_auc", "relative AUC\n(decentralized / centralized)"),
        (bottom, "worst_balance_ratio", "worst balance ratio"),
    ):
        for x, row in zip(xs, rows, strict=True):
            runs = np.asarray(row[f"{metric}_runs"], np.float64)
            offsets = np.linspace(-spread, spread, len(runs)) if len(runs) > 1 else np.zeros(1)
            ax.scatter(x + offsets, runs, s=9, color="tab:blue", alpha=0.55, linewidths=0)
        ax.plot(
            xs, [row[f"{metric}_mean"] for row in rows], "-", color="tab:blue", label="random (paper), mean"
        )
        if balanced is not None:
            runs = np.asarray(balanced[f"{metric}_runs"], np.float64)
            x0 = float(balanced["clusters_per_robot_start"])
            ax.scatter(np.full(len(runs), x0), runs, marker="*", s=40, color="tab:red", alpha=0.6,
                       label="re-balanced from observed load")  # fmt: skip
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    bottom.axhline(1.0, color="grey", lw=0.8, ls=":")
    bottom.xaxis.set_major_locator(MaxNLocator(integer=True))  # robots and clusters are counts
    top.legend(fontsize=7, loc="lower left")
    bottom.set_xlabel(xlabel)
    top.set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
