"""A simulated object detector: world objects -> noisy object-to-point detections.

It mimics what the real TUM constellations were made with (YOLOv3 on COCO,
detection threshold zero, the median 3D point of the depth pixels in each box):

* an object is *visible* when its centre projects inside the 640x480 image at a
  depth inside the sensor's range; the noise-free constellation of a frame is
  exactly its visible objects (occluded or not);
* a visible object is *detected* with a probability that falls with depth,
  near the image border, for small or hard-to-see classes (a per-class recall
  table), for screens seen from behind, behind a nearer large object, and in
  frames blurred by a fast camera turn; half of the instances of each class
  (not lone ones) are *hard* and rarely found at all;
* the random draws deciding misses, confusions, duplicates and background
  hits vary smoothly in time (a real detector gives almost the same boxes for
  almost the same image), with a little frame-to-frame flicker on top;
* a detection's point is the true centre moved along the viewing ray by a
  per-object depth bias (background pixels in the box pull the median behind
  thin or see-through objects), sometimes by a jump onto the background
  (more often far away), plus a slowly varying error of standard deviation
  ``sigma_base_m + sigma_depth_quad * z**2`` and a small frame-to-frame jitter;
* some labels are confused with plausible look-alikes (cup <-> bowl, book <->
  laptop, mouse <-> remote, tvmonitor <-> laptop...), some objects get a
  second, duplicate box, and a few false positives with random labels
  (weighted towards the common classes) appear at random pixels and depths;
  a frame never comes out empty (threshold zero always finds something).

Detections of a frame are ordered by decreasing confidence, as a detector
lists its boxes after non-maximum suppression; false positives and
duplicates have low confidence, so they tend to come last.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from swarmrec.synthetic.camera import PinholeCamera
from swarmrec.synthetic.config import OfficeConfig
from swarmrec.synthetic.labels import N_COCO_LABELS, label_index
from swarmrec.synthetic.world import OfficeWorld

__all__ = [
    "CLASS_DEPTH_BIAS_M",
    "CLASS_RECALL",
    "CONFUSIONS",
    "FALSE_POSITIVE_WEIGHTS",
    "Detections",
    "camera_points",
    "detect",
    "visible_mask",
]

IntArray = npt.NDArray[np.int64]
FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

#: Recall of a close, unoccluded object of each class (classes not listed: 0.6).
#: Small flat things (cutlery, phones) and tables are found less often.
CLASS_RECALL: dict[str, float] = {
    "bottle": 0.95,
    "book": 0.65,
    "chair": 1.0,
    "tvmonitor": 0.9,
    "mouse": 0.95,
    "keyboard": 0.85,
    "cup": 0.65,
    "teddy bear": 0.35,
    "spoon": 0.3,
    "knife": 0.35,
    "fork": 0.25,
    "bowl": 0.3,
    "scissors": 0.2,
    "diningtable": 0.1,
    "laptop": 0.3,
    "cell phone": 0.2,
    "person": 0.95,
    "refrigerator": 0.9,
    "vase": 0.1,
    "remote": 0.5,
    "sports ball": 0.08,
    "microwave": 0.6,
    "cake": 0.4,
    "donut": 0.5,
    "backpack": 0.5,
    "handbag": 0.4,
}
_DEFAULT_RECALL = 0.6

#: Typical depth bias along the ray of the median-of-box point (classes not
#: listed: 0.03 m). See-through and thin objects let the background fill
#: their box; flat, box-filling objects (screens, keyboards, books) do not.
CLASS_DEPTH_BIAS_M: dict[str, float] = {
    "chair": 0.30,
    "bottle": 0.12,
    "spoon": 0.15,
    "knife": 0.15,
    "fork": 0.15,
    "scissors": 0.10,
    "cup": 0.06,
    "vase": 0.06,
    "person": 0.10,
    "teddy bear": 0.03,
    "laptop": 0.05,
    "tvmonitor": 0.0,
    "keyboard": 0.0,
    "book": 0.0,
    "diningtable": 0.0,
    "refrigerator": 0.0,
}

#: (true label, reported label, probability) of label confusions.
CONFUSIONS: tuple[tuple[str, str, float], ...] = (
    ("cup", "bowl", 0.04),
    ("bowl", "cup", 0.10),
    ("cup", "vase", 0.01),
    ("book", "laptop", 0.02),
    ("laptop", "book", 0.05),
    ("laptop", "tvmonitor", 0.08),
    ("tvmonitor", "laptop", 0.03),
    ("keyboard", "laptop", 0.02),
    ("mouse", "remote", 0.02),
    ("remote", "mouse", 0.10),
    ("remote", "cell phone", 0.08),
    ("cell phone", "remote", 0.06),
    ("spoon", "knife", 0.08),
    ("knife", "spoon", 0.08),
    ("fork", "spoon", 0.10),
    ("bottle", "vase", 0.003),
    ("bottle", "cup", 0.01),
    ("vase", "bottle", 0.10),
    ("teddy bear", "person", 0.01),
    ("chair", "diningtable", 0.01),
    ("diningtable", "chair", 0.05),
    ("donut", "cake", 0.10),
    ("cake", "donut", 0.10),
    ("backpack", "handbag", 0.10),
    ("handbag", "backpack", 0.10),
    ("microwave", "tvmonitor", 0.05),
)

#: Relative frequency of the labels of false positives (a detector at
#: threshold zero hallucinates mostly the classes it sees most).
FALSE_POSITIVE_WEIGHTS: dict[str, float] = {
    "bottle": 30.0,
    "book": 12.0,
    "chair": 10.0,
    "cup": 8.0,
    "tvmonitor": 5.0,
    "person": 5.0,
    "cell phone": 4.0,
    "spoon": 4.0,
    "knife": 3.0,
    "bowl": 3.0,
    "remote": 2.0,
    "vase": 2.0,
    "sports ball": 2.0,
    "scissors": 2.0,
    "teddy bear": 2.0,
    "handbag": 1.0,
    "backpack": 1.0,
    "donut": 1.0,
    "cake": 0.5,
    "hair drier": 0.5,
    "toothbrush": 0.5,
    "cat": 0.5,
    "clock": 0.5,
    "pottedplant": 0.5,
}

# Logistic fall-off width of the detection probability with depth.
_DEPTH_SOFTNESS_M = 0.5
# Objects closer than near + this are cut by the image and found less often.
_NEAR_RAMP_M = 0.3
# An occluder hides objects at least this much behind it.
_OCCLUSION_GAP_M = 0.15
# Jump of the median depth when it lands on the background behind the object.
_BACKGROUND_JUMP_M = (0.2, 1.5)
# Depth range of false positives (they sit on whatever surface the box covers).
_FALSE_POSITIVE_DEPTH_M = (0.5, 4.5)


@dataclass(frozen=True, eq=False)
class Detections:
    """All detections of a sequence, flat, sorted by frame then decreasing confidence.

    ``source[k]`` is the index of the world object detection ``k`` comes from,
    ``-1`` for a false positive; ``true_labels[k]`` is that object's real label
    (``-1`` for a false positive), ``labels[k]`` the reported one.
    """

    frame: IntArray
    labels: IntArray
    positions: FloatArray
    confidence: FloatArray
    source: IntArray
    true_labels: IntArray


def camera_points(
    world_positions: FloatArray, cam_positions: FloatArray, cam_rotations: FloatArray
) -> FloatArray:
    """World points (``n x 3``) in each camera frame (``frames x n x 3``).

    With ``p_world = R p_cam + t``, ``p_cam = R^T (p_world - t)``.
    """
    rel = world_positions[None, :, :] - cam_positions[:, None, :]
    return np.asarray(np.einsum("fji,fnj->fni", cam_rotations, rel))


def visible_mask(p_cam: FloatArray, camera: PinholeCamera, depth_range_m: tuple[float, float]) -> BoolArray:
    """Which points (``... x 3``, camera frame) are in the image and the depth range."""
    z = p_cam[..., 2]
    in_depth = (z >= depth_range_m[0]) & (z <= depth_range_m[1])
    safe_z = np.where(in_depth, z, 1.0)
    u = camera.fx * p_cam[..., 0] / safe_z + camera.cx
    v = camera.fy * p_cam[..., 1] / safe_z + camera.cy
    in_image = (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    return np.asarray(in_depth & in_image)


def angular_speed(cam_rotations: FloatArray, rate_hz: float) -> FloatArray:
    """Rotation speed of the camera (rad/s) at each frame (the first repeats the second)."""
    if cam_rotations.shape[0] < 2:
        return np.zeros(cam_rotations.shape[0])
    rel_trace = np.einsum("fij,fij->f", cam_rotations[1:], cam_rotations[:-1])
    angle = np.arccos(np.clip((rel_trace - 1.0) / 2.0, -1.0, 1.0)) * rate_hz
    return np.concatenate([angle[:1], angle])


def detection_probability(
    config: OfficeConfig,
    world: OfficeWorld,
    p_cam: FloatArray,
    cam_positions: FloatArray,
    cam_rotations: FloatArray,
    camera: PinholeCamera,
    visible: BoolArray,
) -> FloatArray:
    """Probability (``frames x objects``) that a detector finds each visible object."""
    z = np.where(visible, p_cam[..., 2], 1.0)
    u = camera.fx * p_cam[..., 0] / z + camera.cx
    v = camera.fy * p_cam[..., 1] / z + camera.cy

    recall = (
        np.array([CLASS_RECALL.get(name, _DEFAULT_RECALL) for name in world.label_names])
        ** config.class_recall_exponent
    )
    p = config.detection_prob * recall[world.labels][None, :] * np.ones_like(z)

    depth_term = 1.0 / (1.0 + np.exp((z - config.half_detection_depth_m) / _DEPTH_SOFTNESS_M))
    # Normalised so that a close object keeps the full probability.
    depth_term /= 1.0 / (1.0 + np.exp(-config.half_detection_depth_m / _DEPTH_SOFTNESS_M))
    near_term = np.clip((z - config.depth_range_m[0]) / _NEAR_RAMP_M, 0.0, 1.0) ** 0.5
    p *= depth_term * near_term
    blur = 1.0 / (1.0 + (angular_speed(cam_rotations, config.rate_hz) / config.blur_half_rad_s) ** 2)
    p *= blur[:, None]

    if config.border_margin_px > 0:
        border = np.minimum.reduce([u, camera.width - 1 - u, v, camera.height - 1 - v])
        p *= 0.3 + 0.7 * np.clip(border / config.border_margin_px, 0.0, 1.0)

    faced = np.linalg.norm(world.facing, axis=1) > 0
    if faced.any():
        to_cam = cam_positions[:, None, :] - world.positions[None, faced, :]
        to_cam /= np.linalg.norm(to_cam, axis=2, keepdims=True)
        cos = np.einsum("fnj,nj->fn", to_cam, world.facing[faced])
        b = config.back_view_factor
        p[:, faced] *= b + (1.0 - b) * np.clip(2.0 * cos + 0.5, 0.0, 1.0)

    occ = np.flatnonzero(world.occluder_radius > 0)
    if occ.size and config.occluded_factor < 1.0:
        p *= np.where(_occluded(world, p_cam, visible, camera, occ), config.occluded_factor, 1.0)
    return np.asarray(np.where(visible, np.clip(p, 0.0, 1.0), 0.0))


def _occluded(
    world: OfficeWorld,
    p_cam: FloatArray,
    visible: BoolArray,
    camera: PinholeCamera,
    occ: IntArray,
) -> BoolArray:
    """Whether each object is behind a nearer occluder's disc in the image."""
    z = np.where(visible, p_cam[..., 2], 1.0)
    u = camera.fx * p_cam[..., 0] / z
    v = camera.fy * p_cam[..., 1] / z
    zo, uo, vo = z[:, occ, None], u[:, occ, None], v[:, occ, None]
    radius_px = camera.fx * world.occluder_radius[occ][None, :, None] / zo
    dist_px = np.hypot(u[:, None, :] - uo, v[:, None, :] - vo)
    hides = visible[:, occ, None] & (zo < z[:, None, :] - _OCCLUSION_GAP_M) & (dist_px < radius_px)
    hides[:, np.arange(occ.size), occ] = False
    return np.asarray(hides.any(axis=1))


def _ar1(n_frames: int, rho: FloatArray, rng: np.random.Generator) -> FloatArray:
    """Stationary unit-variance AR(1) processes along axis 0 (``frames x len(rho)``)."""
    white = rng.standard_normal((n_frames, rho.shape[0]))
    out = np.empty_like(white)
    out[0] = white[0]
    innovation = np.sqrt(1.0 - rho * rho)
    for f in range(1, n_frames):
        out[f] = rho * out[f - 1] + innovation * white[f]
    return out


def _rho(corr_frames: float) -> float:
    return float(np.exp(-1.0 / corr_frames)) if corr_frames > 0 else 0.0


def _to_uniform(gauss: FloatArray) -> FloatArray:
    """Standard normal -> (almost exactly) uniform on (0, 1).

    The logistic curve with slope 1.702 stays within 0.01 of the normal CDF,
    which is plenty for drawing misses, and needs no erf.
    """
    return np.asarray(1.0 / (1.0 + np.exp(-1.702 * gauss)))


def _confusion_matrix(config: OfficeConfig) -> FloatArray:
    """Row-stochastic matrix: ``m[true, reported]``."""
    m = np.zeros((N_COCO_LABELS, N_COCO_LABELS))
    for true, reported, prob in CONFUSIONS:
        m[label_index(true), label_index(reported)] += prob * config.confusion_scale
    # Never give away more than 90 % of a class, whatever the scale.
    off = m.sum(axis=1, keepdims=True)
    m = np.where(off > 0.9, m * 0.9 / np.maximum(off, 1e-12), m)
    m[np.arange(N_COCO_LABELS), np.arange(N_COCO_LABELS)] = 1.0 - m.sum(axis=1)
    return m


def _hard_objects(labels: IntArray, share: float, rng: np.random.Generator) -> BoolArray:
    """Which objects are hard for the detector: ``share`` of each class's instances.

    Drawn per class (the count rounded up or down at random) so that the label
    proportions do not swing from seed to seed; an object alone in its class
    is never hard, its class's recall already says how often it is found.
    """
    hard = np.zeros(labels.shape[0], dtype=bool)
    for label in np.unique(labels):
        members = np.flatnonzero(labels == label)
        if members.size < 2:
            continue
        n_hard = int(np.floor(share * members.size + rng.random()))
        hard[rng.permutation(members)[:n_hard]] = True
    return hard


def _sample_rows(m: FloatArray, rows: IntArray, draw: FloatArray) -> IntArray:
    """One column index per entry of ``rows``, from ``m[row]``, by inverse CDF of ``draw``."""
    cum = np.cumsum(m[rows], axis=1)
    index = np.minimum((draw[:, None] > cum).sum(axis=1), m.shape[1] - 1)
    return np.asarray(index, dtype=np.int64)


def detect(
    config: OfficeConfig,
    world: OfficeWorld,
    p_cam: FloatArray,
    cam_positions: FloatArray,
    cam_rotations: FloatArray,
    camera: PinholeCamera,
    rng: np.random.Generator,
) -> Detections:
    """Simulate the detector on every frame (``p_cam``: ``frames x objects x 3``)."""
    n_frames, n_objects = p_cam.shape[:2]
    visible = visible_mask(p_cam, camera, config.depth_range_m)
    prob = detection_probability(config, world, p_cam, cam_positions, cam_rotations, camera, visible)
    hard = _hard_objects(world.labels, config.hard_object_share, rng)
    prob = prob * np.where(hard, config.hard_object_factor, 1.0)[None, :]

    # Smoothly varying random draws per object: 4 uniforms (detection,
    # confusion, background hit, duplicate) and a 3D slow position error.
    rho = np.concatenate(
        [
            np.full(4 * n_objects, _rho(config.miss_corr_frames)),
            np.full(3 * n_objects, _rho(config.noise_corr_frames)),
        ]
    )
    smooth = _ar1(n_frames, rho, rng)
    share = config.flicker
    draws = _to_uniform(
        np.sqrt(1.0 - share) * smooth[:, : 4 * n_objects]
        + np.sqrt(share) * rng.standard_normal((n_frames, 4 * n_objects))
    ).reshape(n_frames, 4, n_objects)
    u_det, u_conf, u_bg, u_dup = (draws[:, k, :] for k in range(4))
    slow = smooth[:, 4 * n_objects :].reshape(n_frames, 3, n_objects).transpose(0, 2, 1)

    found = visible & (u_det < prob)
    frame, obj = np.nonzero(found)
    # Confidence is higher the more certainly the object was found.
    p_found = prob[frame, obj]
    conf = p_found * (0.6 + 0.4 * (p_found - u_det[frame, obj]) / p_found)

    # Duplicate boxes: the same object again, a little less confident and,
    # covering only part of it, a little off.
    dup = u_dup[frame, obj] < config.duplicate_rate
    n_dup = int(dup.sum())
    frame = np.concatenate([frame, frame[dup]])
    obj = np.concatenate([obj, obj[dup]])
    conf = np.concatenate([conf, conf[dup] * rng.uniform(0.3, 0.7, n_dup)])
    offset = np.concatenate([np.zeros((found.sum(), 3)), rng.normal(0.0, 0.05, (n_dup, 3))])

    true_labels = world.labels[obj]
    labels = _sample_rows(_confusion_matrix(config), true_labels, u_conf[frame, obj])

    points = p_cam[frame, obj]
    depth = points[:, 2]
    class_bias = np.array([CLASS_DEPTH_BIAS_M.get(name, 0.03) for name in world.label_names])
    bias = config.depth_bias_scale * class_bias[world.labels] + rng.normal(
        0.0, config.depth_bias_spread_m, n_objects
    )
    hit_rate = np.minimum(config.background_hit_rate * (depth / 2.0) ** 2, 0.5)
    u = u_bg[frame, obj]
    jump_fraction = np.where(u < hit_rate, u / np.maximum(hit_rate, 1e-12), -1.0)
    lo, hi = _BACKGROUND_JUMP_M
    jump = np.where(jump_fraction >= 0, lo + (hi - lo) * jump_fraction, 0.0)
    dist = np.linalg.norm(points, axis=1)
    sigma = config.sigma_base_m + config.sigma_depth_quad * depth**2
    jitter = config.jitter_base_m + config.jitter_depth_quad * depth**2
    positions = (
        points * ((dist + bias[obj] + jump) / dist)[:, None]
        + slow[frame, obj] * sigma[:, None]
        + rng.standard_normal((frame.size, 3)) * jitter[:, None]
        + offset
    )

    # False positives: random label, random pixel, random depth.
    n_true = np.bincount(frame, minlength=n_frames)
    n_fp = np.maximum(rng.poisson(config.false_positives_per_frame, n_frames), config.min_detections - n_true)
    fp_frame = np.repeat(np.arange(n_frames), n_fp)
    weights = np.array([FALSE_POSITIVE_WEIGHTS.get(name, 0.0) for name in world.label_names])
    fp_labels = rng.choice(len(weights), size=fp_frame.size, p=weights / weights.sum())
    fp_points = camera.unproject(
        rng.uniform(0.0, camera.width, fp_frame.size),
        rng.uniform(0.0, camera.height, fp_frame.size),
        rng.uniform(*_FALSE_POSITIVE_DEPTH_M, fp_frame.size),
    )
    fp_conf = rng.uniform(0.02, 0.5, fp_frame.size)

    all_frame = np.concatenate([frame, fp_frame]).astype(np.int64)
    all_conf = np.concatenate([conf, fp_conf])
    order = np.lexsort((-all_conf, all_frame))
    minus_one = np.full(fp_frame.size, -1, dtype=np.int64)
    return Detections(
        frame=all_frame[order],
        labels=np.concatenate([labels, fp_labels]).astype(np.int64)[order],
        positions=np.concatenate([positions, fp_points])[order],
        confidence=all_conf[order],
        source=np.concatenate([obj, minus_one]).astype(np.int64)[order],
        true_labels=np.concatenate([true_labels, minus_one]).astype(np.int64)[order],
    )
