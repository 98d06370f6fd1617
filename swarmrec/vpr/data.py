"""Rendered office worlds for place recognition: frames at the descriptor's size, with poses.

One definition of the worlds that the descriptor is trained on, that k-means centres are
trained on and that the evaluation deploys to, shared by ``models/descriptor/train.py``
(torch, no faiss) and the runtime, so it needs only numpy, OpenCV and the renderer.

* A *default* world is ``OfficeConfig(seed=..., n_frames=...)``: the office a swarm replays.
* A *varied* world draws its desk count (4, 6 or 8), loops, orbit, camera heights, wobble
  and glances from its seed too: the "general" data of the paper's Fig. 3, whose descriptor
  distribution covers more than one deployment's.

Frames are rendered at 256 x 192 and area-averaged to the model's 128 x 96, as a 640 x 480
camera frame resized with ``cv2.INTER_AREA`` would be.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from swarmrec.synthetic import OfficeConfig, generate_office
from swarmrec.synthetic.config import MIN_CLEARANCE_M
from swarmrec.synthetic.render import RenderSettings, SequenceRenderer
from swarmrec.vpr.places import view_directions

__all__ = ["INPUT_HW", "RENDER_HW", "RenderedWorld", "render_world", "to_model_size", "world_config"]

ImageArray = npt.NDArray[np.uint8]
FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

#: The descriptor's input (height, width) and the render size it is area-averaged from.
INPUT_HW = (96, 128)
RENDER_HW = (192, 256)


@dataclass(frozen=True, eq=False)
class RenderedWorld:
    """Frames of one world at the model's size (RGB) and each frame's pose."""

    seed: int
    images: ImageArray  # (N, 96, 128, 3) RGB
    frames: IntArray  # index of each image in the world's sequence
    positions: FloatArray  # (N, 3) camera positions, world frame
    directions: FloatArray  # (N, 3) unit viewing directions

    def __len__(self) -> int:
        return int(self.images.shape[0])


def world_config(seed: int, frames: int, vary: bool) -> OfficeConfig:
    """The default office of ``seed``; with ``vary``, its layout and camera path drawn from
    ``seed`` too (more orbits, heights and looks around the room than a swarm's world)."""
    if not vary:
        return OfficeConfig(seed=seed, n_frames=frames)
    rng = np.random.default_rng([seed, 0xD35C])
    n_desks = int(rng.choice([4, 6, 8]))
    # The smallest orbit the world accepts for this block, read from a config that is surely valid.
    half_x, half_y = OfficeConfig(n_desks=n_desks, orbit_radius_m=20.0).block_half_extent_m
    least = MIN_CLEARANCE_M + (half_x + half_y) / 2
    low, high = sorted((float(rng.uniform(0.9, 1.25)), float(rng.uniform(1.45, 1.85))))
    return OfficeConfig(
        seed=seed,
        n_frames=frames,
        n_desks=n_desks,
        n_loops=float(rng.choice([2.0, 2.0, 2.5, 3.0])),
        orbit_radius_m=round(least + float(rng.uniform(0.2, 1.3)), 3),
        camera_height_m=(round(low, 3), round(high, 3)),
        wobble_deg=round(float(rng.uniform(8.0, 24.0)), 2),
        glances_per_minute=round(float(rng.uniform(2.0, 9.0)), 2),
    )


def to_model_size(bgr: ImageArray, input_hw: tuple[int, int] = INPUT_HW) -> ImageArray:
    """A BGR frame of any size as the model's RGB input (area average, like a camera frame)."""
    small = cv2.resize(bgr, (input_hw[1], input_hw[0]), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(small[:, :, ::-1])


def render_world(seed: int, frames: int, stride: int, vary: bool, *, offset: bool = True) -> RenderedWorld:
    """Every ``stride``-th frame of the world ``seed`` of ``frames`` frames. With ``offset`` the
    first frame is drawn from the seed, so two worlds do not sample the same phases of their paths."""
    ds = generate_office(world_config(seed, frames, vary))
    renderer = SequenceRenderer(ds, RenderSettings(width=RENDER_HW[1], height=RENDER_HW[0]))
    start = int(np.random.default_rng([seed, 1]).integers(stride)) if offset else 0
    indices = np.arange(start, len(renderer), stride, dtype=np.int64)
    images = np.stack([to_model_size(renderer.render(int(i)).rgb) for i in indices])
    quaternions = ds.trajectory.quaternions[indices]
    return RenderedWorld(
        seed, images, indices, ds.trajectory.positions[indices], view_directions(quaternions)
    )
