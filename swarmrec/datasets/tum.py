"""TUM RGB-D trajectory files (``groundtruth.txt``), and the constants of the TUM RGB-D format.

Format: comment lines start with ``#``; every other line is
``timestamp tx ty tz qx qy qz qw`` (camera to world, metres, unit quaternion).
The RGB-D frames themselves are read by :mod:`swarmrec.datasets.tum_rgbd`;
its constants live here so that settings can name them without loading OpenCV.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import numpy.typing as npt

from swarmrec.core.types import Trajectory
from swarmrec.errors import DatasetError, MalformedLineError

__all__ = ["DEFAULT_MAX_DT", "TUM_DEPTH_SCALE", "associate_poses", "read_trajectory", "write_trajectory"]

#: Depth units per metre in TUM's 16-bit depth PNGs (and in the synthetic renders).
TUM_DEPTH_SCALE = 5000.0
#: Seconds; TUM's associate.py default for pairing RGB and depth images, well under the
#: 1/30 s between frames.
DEFAULT_MAX_DT = 0.02


def read_trajectory(path: str | Path) -> Trajectory:
    """Read a TUM trajectory; every bad line is an error naming file and line."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(path, f"cannot read trajectory: {exc}") from exc
    rows: list[list[float]] = []
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        tokens = line.replace(",", " ").split()
        if len(tokens) != 8:
            raise MalformedLineError(
                path,
                f"expected 8 columns 'timestamp tx ty tz qx qy qz qw', got {len(tokens)}",
                number,
            )
        try:
            values = [float(t) for t in tokens]
        except ValueError:
            raise MalformedLineError(path, f"not a number in {line!r}", number) from None
        if not all(math.isfinite(v) for v in values):
            raise MalformedLineError(path, f"non-finite value in {line!r}", number)
        norm = math.sqrt(sum(v * v for v in values[4:]))
        if not 0.9 < norm < 1.1:
            raise MalformedLineError(path, f"quaternion norm {norm:.3f} is not 1", number)
        if rows and values[0] <= rows[-1][0]:
            raise MalformedLineError(path, "timestamps must increase", number)
        rows.append(values)
    if not rows:
        raise DatasetError(path, "trajectory has no poses")
    data = np.array(rows)
    return Trajectory(data[:, 0], data[:, 1:4], data[:, 4:8])


def write_trajectory(traj: Trajectory, path: str | Path) -> None:
    """Write ``traj`` in TUM format with a header comment."""
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for t, p, q in zip(traj.timestamps, traj.positions, traj.quaternions, strict=True):
        lines.append(f"{t:.6f} " + " ".join(f"{v:.9f}" for v in (*p, *q)))
    Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")


def associate_poses(
    traj: Trajectory, timestamps: npt.ArrayLike, max_dt: float = 0.05
) -> npt.NDArray[np.int64]:
    """Index of the pose nearest in time to each timestamp.

    On an exact tie the later pose wins, as in the published evaluation.
    A frame with no pose within ``max_dt`` seconds is an error: silently
    borrowing a far pose would corrupt the ground truth.
    """
    t = np.asarray(timestamps, dtype=np.float64)
    gt = traj.timestamps
    after = np.clip(np.searchsorted(gt, t, side="left"), 0, len(gt) - 1)
    before = np.clip(after - 1, 0, len(gt) - 1)
    pick_before = np.abs(gt[after] - t) > np.abs(t - gt[before])
    idx = np.where(pick_before, before, after)
    gap = np.abs(gt[idx] - t)
    if np.any(gap > max_dt):
        worst = int(np.argmax(gap))
        raise DatasetError(
            "trajectory",
            f"frame at t={t[worst]:.6f} has no pose within {max_dt} s "
            f"(nearest {gap[worst]:.3f} s away)",
        )
    return idx.astype(np.int64)
