"""TUM RGB-D trajectory files (``groundtruth.txt``), and the constants of the TUM RGB-D format.

Format: comment lines start with ``#``; every other line is
``timestamp tx ty tz qx qy qz qw`` (camera to world, metres, unit quaternion).
The RGB-D frames themselves are read by :mod:`swarmrec.datasets.tum_rgbd`;
its constants live here so that settings can name them without loading OpenCV.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from swarmrec.core.types import Trajectory
from swarmrec.errors import DatasetError, MalformedLineError

__all__ = [
    "DEFAULT_MAX_DT",
    "POSE_MAX_DT",
    "POSE_WARN_DT",
    "TUM_DEPTH_SCALE",
    "PoseAssociation",
    "associate_poses",
    "read_trajectory",
    "write_trajectory",
]

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


#: Seconds: a frame whose nearest pose is farther than this is reported (the motion-capture
#: rate is 100 Hz, so a good match is within 0.005 s; TUM's tools warn at 0.02 s).
POSE_WARN_DT = 0.05
#: Seconds: a frame whose nearest pose is farther than this has no usable pose (it is refused,
#: never given a pose of another part of the path).
POSE_MAX_DT = 0.5


@dataclass(frozen=True)
class PoseAssociation:
    """The pose of each frame (``index``) and how far in time it is (``gap``, seconds)."""

    index: npt.NDArray[np.int64]
    gap: npt.NDArray[np.float64]
    warn_dt: float

    @property
    def far(self) -> npt.NDArray[np.int64]:
        """Frames whose nearest pose is more than ``warn_dt`` away."""
        return np.flatnonzero(self.gap > self.warn_dt)

    def describe(self) -> str:
        """One line for a warning (empty when every pose is close)."""
        far = self.far
        if not far.size:
            return ""
        worst = int(far[np.argmax(self.gap[far])])
        return (
            f"{far.size} frame(s) matched to a pose more than {self.warn_dt:g} s away "
            f"(nearest pose in time, as the published evaluation does; worst: frame {worst}, "
            f"{self.gap[worst]:.3f} s)"
        )


def associate_poses(
    traj: Trajectory, timestamps: npt.ArrayLike, max_dt: float = POSE_MAX_DT, warn_dt: float = POSE_WARN_DT
) -> PoseAssociation:
    """The pose nearest in time to each timestamp, as the published evaluation matches them.

    On an exact tie the later pose wins, as in the published evaluation. A frame
    whose nearest pose is more than ``warn_dt`` away is listed (:attr:`PoseAssociation.far`:
    the first frames of a recording often start before its motion capture); a
    frame with no pose within ``max_dt`` is an error, since borrowing a pose from
    another part of the path would corrupt the ground truth.
    """
    if not 0 < warn_dt <= max_dt:
        raise ValueError(f"need 0 < warn_dt <= max_dt, got {warn_dt}, {max_dt}")
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
            f"frame {worst} at t={t[worst]:.6f} has no pose within {max_dt} s "
            f"(nearest {gap[worst]:.3f} s away): is this the sequence's own groundtruth.txt?",
        )
    return PoseAssociation(idx.astype(np.int64), gap, warn_dt)
