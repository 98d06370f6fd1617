"""TUM RGB-D sequences: the RGB and depth frames a detector runs on, with their poses.

A sequence folder holds ``rgb.txt`` and ``depth.txt`` (``timestamp filename``
lines, ``#`` comments; file names relative to the folder) and optionally
``groundtruth.txt`` (read by :func:`swarmrec.datasets.tum.read_trajectory`).
RGB and depth are captured separately, so frames are made by association,
as TUM's ``associate.py`` does it: every pair closer than ``max_dt`` is a
candidate, and pairs are taken greedily by smallest time difference, each
image used at most once. Unpaired images are counted, not errors: the
camera drops frames. A frame gets the ground-truth pose nearest in time
when one is within ``pose_max_dt`` (ground truth has gaps where the motion
capture lost the camera), otherwise ``None``.

Images are decoded only when asked for (:meth:`TumRgbdSequence.images`), RGB
as BGR ``uint8`` and depth as the PNG's ``uint16`` (:data:`TUM_DEPTH_SCALE`
units per metre). An image that cannot be used raises :class:`RgbdImageError`,
whose ``problem`` says why (missing, corrupt, size mismatch), so a replay can
count its skips by cause.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import numpy.typing as npt

from swarmrec.core.geometry import quaternion_to_matrix
from swarmrec.datasets.tum import DEFAULT_MAX_DT, TUM_DEPTH_SCALE, associate_poses, read_trajectory
from swarmrec.errors import ConfigError, DatasetError, MalformedLineError

__all__ = [
    "DEFAULT_MAX_DT",
    "TUM_DEPTH_SCALE",
    "ImageProblem",
    "RgbdFrame",
    "RgbdImageError",
    "TumRgbdSequence",
    "associate",
    "frame_id_of",
    "load_rgbd",
    "read_file_list",
    "read_tum_rgbd",
]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
ImageArray = npt.NDArray[np.uint8]
DepthArray = npt.NDArray[np.uint16]

#: Why a frame's image cannot be used: ``missing`` (no such file), ``corrupt`` (unreadable, not
#: an image, or a depth image that is not 16-bit single-channel), ``size_mismatch`` (RGB and depth
#: of different sizes).
ImageProblem = Literal["missing", "corrupt", "size_mismatch"]


@dataclass
class RgbdImageError(DatasetError):
    """One frame's RGB or depth image cannot be used; ``source`` is the file, ``problem`` the cause."""

    problem: ImageProblem = "corrupt"


@dataclass(frozen=True, eq=False)
class RgbdFrame:
    """One associated frame; ``pose`` is the 4 x 4 camera-to-world matrix, or None without ground truth."""

    index: int
    timestamp: float
    rgb_path: Path
    depth_path: Path
    pose: FloatArray | None


@dataclass(frozen=True, eq=False)
class TumRgbdSequence:
    """The associated frames of a sequence, in time order (frame timestamp = RGB timestamp).

    ``skipped`` counts the images left without a partner:
    ``rgb_without_depth`` and ``depth_without_rgb``.
    """

    root: Path
    frames: tuple[RgbdFrame, ...]
    has_groundtruth: bool
    skipped: dict[str, int]

    def __len__(self) -> int:
        return len(self.frames)

    def __iter__(self) -> Iterator[RgbdFrame]:
        return iter(self.frames)

    def images(
        self, errors: list[DatasetError] | None = None
    ) -> Iterator[tuple[RgbdFrame, ImageArray, DepthArray]]:
        """Each frame with its decoded RGB (BGR) and depth images.

        A missing, corrupt or mismatched image raises :class:`DatasetError`;
        with an ``errors`` list given, the frame is skipped instead and its
        error appended, so a long replay survives one bad file and still
        reports it (``len(errors)`` is the count).
        """
        for frame in self.frames:
            try:
                rgb, depth = load_rgbd(frame.rgb_path, frame.depth_path)
            except DatasetError as exc:
                if errors is None:
                    raise
                errors.append(exc)
                continue
            yield frame, rgb, depth


def read_file_list(path: str | Path) -> tuple[FloatArray, list[str]]:
    """Timestamps and file names of a TUM ``rgb.txt`` / ``depth.txt``.

    Commas and tabs separate like spaces, as in TUM's tools. Every bad line
    is an error naming file and line; timestamps must increase, since
    association by time is meaningless with repeated stamps.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(path, f"cannot read file list: {exc}") from exc
    stamps: list[float] = []
    names: list[str] = []
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        tokens = line.replace(",", " ").split()
        if len(tokens) != 2:
            raise MalformedLineError(
                path, f"expected 'timestamp filename', got {len(tokens)} column(s)", number
            )
        try:
            stamp = float(tokens[0])
        except ValueError:
            raise MalformedLineError(path, f"timestamp {tokens[0]!r} is not a number", number) from None
        if not math.isfinite(stamp):
            raise MalformedLineError(path, f"non-finite timestamp {tokens[0]!r}", number)
        if stamps and stamp <= stamps[-1]:
            raise MalformedLineError(path, "timestamps must increase", number)
        stamps.append(stamp)
        names.append(tokens[1])
    return np.array(stamps, dtype=np.float64), names


def associate(first: npt.ArrayLike, second: npt.ArrayLike, max_dt: float = DEFAULT_MAX_DT) -> IntArray:
    """Index pairs ``(i, j)`` (``m x 2``, sorted by ``i``) matching two increasing timestamp lists.

    TUM ``associate.py``'s rule: candidates are pairs with ``|first[i] -
    second[j]| < max_dt``, taken by increasing difference (ties by ``i``,
    then ``j``), skipping any whose ``i`` or ``j`` is already taken. Greedy
    one-to-one rather than plain nearest, so two RGB frames never share one
    depth image.
    """
    if not max_dt > 0:
        raise ConfigError(f"max_dt must be positive (seconds), got {max_dt}")
    a = np.asarray(first, dtype=np.float64).reshape(-1)
    b = np.asarray(second, dtype=np.float64).reshape(-1)
    # A window twice as wide as needed, so rounding at its edges never loses a candidate;
    # the exact test below decides.
    lo = np.searchsorted(b, a - 2 * max_dt, side="left")
    hi = np.searchsorted(b, a + 2 * max_dt, side="right")
    counts = hi - lo
    ai = np.repeat(np.arange(a.size), counts)
    bi = np.repeat(lo, counts) + np.arange(ai.size) - np.repeat(np.cumsum(counts) - counts, counts)
    diff = np.abs(a[ai] - b[bi])
    close = diff < max_dt
    ai, bi, diff = ai[close], bi[close], diff[close]
    taken_a = np.zeros(a.size, dtype=bool)
    taken_b = np.zeros(b.size, dtype=bool)
    pairs: list[tuple[int, int]] = []
    # Both lists increase, so ordering by index is ordering by timestamp, as associate.py's tuple sort.
    for k in np.lexsort((bi, ai, diff)).tolist():
        i, j = int(ai[k]), int(bi[k])
        if not (taken_a[i] or taken_b[j]):
            taken_a[i] = taken_b[j] = True
            pairs.append((i, j))
    pairs.sort()
    return np.array(pairs, dtype=np.int64).reshape(-1, 2)


def read_tum_rgbd(
    root: str | Path, *, max_dt: float = DEFAULT_MAX_DT, pose_max_dt: float = DEFAULT_MAX_DT
) -> TumRgbdSequence:
    """Read and associate a TUM RGB-D sequence folder; no image is decoded here.

    A pose is attached when the nearest ground-truth stamp is within
    ``pose_max_dt`` seconds (inclusive, as
    :func:`swarmrec.datasets.tum.associate_poses`); TUM's ground truth runs
    at 100 Hz, so a wider gap means the motion capture lost the camera.
    """
    root = Path(root)
    if not pose_max_dt > 0:
        raise ConfigError(f"pose_max_dt must be positive (seconds), got {pose_max_dt}")
    rgb_t, rgb_names = read_file_list(root / "rgb.txt")
    depth_t, depth_names = read_file_list(root / "depth.txt")
    pairs = associate(rgb_t, depth_t, max_dt)
    stamps = rgb_t[pairs[:, 0]]
    gt_path = root / "groundtruth.txt"
    poses: list[FloatArray | None] = [None] * len(pairs)
    if gt_path.exists():
        traj = read_trajectory(gt_path)
        # Nearest pose with the trajectory reader's tie rule; the gap is checked here, per frame.
        nearest = associate_poses(traj, stamps, max_dt=math.inf, warn_dt=math.inf).index
        rotations = quaternion_to_matrix(traj.quaternions[nearest])
        for k, g in enumerate(nearest.tolist()):
            if abs(traj.timestamps[g] - stamps[k]) <= pose_max_dt:
                pose = np.eye(4)
                pose[:3, :3] = rotations[k]
                pose[:3, 3] = traj.positions[g]
                poses[k] = pose
    frames = tuple(
        RgbdFrame(k, float(stamps[k]), root / rgb_names[i], root / depth_names[j], poses[k])
        for k, (i, j) in enumerate(pairs.tolist())
    )
    skipped = {
        "rgb_without_depth": len(rgb_names) - len(pairs),
        "depth_without_rgb": len(depth_names) - len(pairs),
    }
    return TumRgbdSequence(root, frames, gt_path.exists(), skipped)


def _decode(path: Path, flags: int, what: str) -> npt.NDArray[np.generic]:
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise RgbdImageError(path, f"{what} image is missing", problem="missing") from None
    except OSError as exc:
        raise RgbdImageError(path, f"cannot read {what} image: {exc}") from exc
    try:
        image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), flags)
    except cv2.error as exc:
        raise RgbdImageError(path, f"cannot decode {what} image: {exc}") from exc
    if image is None:
        raise RgbdImageError(path, f"cannot decode {what} image (corrupt, truncated or not an image)")
    result: npt.NDArray[np.generic] = image
    return result


def load_rgbd(rgb_path: str | Path, depth_path: str | Path) -> tuple[ImageArray, DepthArray]:
    """The BGR ``uint8`` image and ``uint16`` depth image of one frame, checked to fit together.

    A depth image of another type (an 8-bit or colour PNG) would silently
    give wrong metres, and depth of another size than the RGB image would put
    every object's depth at the wrong pixels: both are errors naming the file
    (:class:`RgbdImageError`, as are a missing or undecodable image).
    """
    rgb_path, depth_path = Path(rgb_path), Path(depth_path)
    rgb = _decode(rgb_path, cv2.IMREAD_COLOR, "RGB")
    depth = _decode(depth_path, cv2.IMREAD_UNCHANGED, "depth")
    if depth.dtype != np.uint16 or depth.ndim != 2:
        raise RgbdImageError(
            depth_path, f"depth must be a 16-bit single-channel PNG, got {depth.dtype} of shape {depth.shape}"
        )
    if rgb.shape[:2] != depth.shape:
        raise RgbdImageError(
            depth_path,
            f"depth is {depth.shape[1]}x{depth.shape[0]} but its RGB image {rgb_path.name} "
            f"is {rgb.shape[1]}x{rgb.shape[0]}",
            problem="size_mismatch",
        )
    return rgb.astype(np.uint8, copy=False), depth.astype(np.uint16, copy=False)


def frame_id_of(frame: RgbdFrame) -> str:
    """A frame's id: its RGB timestamp with TUM's six decimals (the constellation files' names)."""
    return f"{frame.timestamp:.6f}"
