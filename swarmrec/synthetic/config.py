"""Settings of the synthetic office world: one frozen, validated object.

Every knob of the world, the camera path and the simulated detector lives in
:class:`OfficeConfig`; the defaults make the world look like the real TUM
``freiburg3_long_office_household`` constellations (see docs/synthetic-world.md).
Named presets bundle the knobs for common uses::

    OfficeConfig.preset("default")            # the project's default dataset
    OfficeConfig.preset("easy", seed=3)       # short, almost noise-free, for quick tests
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

from swarmrec.errors import ConfigError

__all__ = ["PRESETS", "OfficeConfig"]

#: Names accepted by :meth:`OfficeConfig.preset`.
PRESETS: tuple[str, ...] = ("default", "easy", "hard")


@dataclass(frozen=True)
class OfficeConfig:
    """All settings of :func:`swarmrec.synthetic.generate_office`.

    Lengths are metres, angles degrees, rates per second unless a name says otherwise.
    """

    # --- randomness and timing -------------------------------------------------
    #: Seed of the numpy Generator: same seed and settings give the same dataset.
    seed: int = 0
    #: Number of camera frames (TUM's sequence has 2585).
    n_frames: int = 2500
    #: Frame rate; consecutive timestamps are ``1 / rate_hz`` apart.
    rate_hz: float = 30.0
    #: Whole seconds of the first timestamp (frame ids look like TUM's, "1000000000.000000").
    start_time_s: int = 1_000_000_000

    # --- world -----------------------------------------------------------------
    #: Desks in the central block, two back-to-back rows; must be even. Six desks
    #: and a 2.5 m orbit make the paper's 2 m ground truth about as selective as on
    #: TUM (AUC under the paper preset is in docs/synthetic-world.md).
    n_desks: int = 6
    #: Standard deviation of the per-copy offset of objects of a repeated desk
    #: layout: small values make the two copies near-identical (perceptual aliasing).
    alias_jitter_m: float = 0.03

    # --- camera path -------------------------------------------------------------
    #: Loops around the desk block (two or more give revisits).
    n_loops: float = 2.0
    #: Mean of the two semi-axes of the elliptic orbit around the desk block.
    orbit_radius_m: float = 2.5
    #: Lowest and highest camera height above the floor.
    camera_height_m: tuple[float, float] = (1.1, 1.7)
    #: Amplitude of the hand wobble of the yaw (pitch 0.7x, roll 0.5x of it).
    wobble_deg: float = 15.0
    #: Quick looks away from the desks, per minute of sequence.
    glances_per_minute: float = 3.0

    # --- simulated detector (YOLO + median depth in the box) -------------------
    #: Near and far limit of the depth sensor; outside, nothing is detected.
    depth_range_m: tuple[float, float] = (0.4, 5.0)
    #: Detection probability of an easy object close to the image centre.
    detection_prob: float = 0.95
    #: Depth at which the detection probability has dropped to half.
    half_detection_depth_m: float = 2.5
    #: Objects closer than this to the image border are harder to detect (cut boxes).
    border_margin_px: float = 40.0
    #: How much the per-class recall table matters: recall ** exponent (0 = all alike).
    class_recall_exponent: float = 1.0
    #: Share of the objects that are hard for the detector (lying flat, half
    #: hidden, an unusual look): their detection probability is multiplied by
    #: ``hard_object_factor`` in every frame, so the detector misses the same
    #: objects on every visit, as a real one does.
    hard_object_share: float = 0.5
    hard_object_factor: float = 0.15
    #: Detection probability factor of an object hidden behind a nearer large object.
    occluded_factor: float = 0.1
    #: Detection probability factor of a screen (monitor, laptop...) seen from behind.
    back_view_factor: float = 0.4
    #: Motion blur: at this angular speed of the camera the detection
    #: probability halves (fast turns and glances give frames with few objects).
    blur_half_rad_s: float = 2.5
    #: A detector gives nearly the same boxes for nearly the same image: the
    #: random draws behind misses, confusions, duplicates and background hits
    #: of an object vary smoothly, with this correlation time (frames)...
    miss_corr_frames: float = 60.0
    #: ...plus this share of frame-to-frame independent randomness (flicker).
    flicker: float = 0.05
    #: Slowly varying position error, standard deviation
    #: ``sigma_base_m + sigma_depth_quad * z**2``, correlation time ``noise_corr_frames``.
    sigma_base_m: float = 0.01
    sigma_depth_quad: float = 0.015
    noise_corr_frames: float = 45.0
    #: Frame-to-frame position jitter, ``jitter_base_m + jitter_depth_quad * z**2``.
    jitter_base_m: float = 0.003
    jitter_depth_quad: float = 0.001
    #: Depth bias along the ray: the median of a box's depth pixels lies behind
    #: the object's centre when background shows through (chairs, bottles,
    #: cutlery). Per object it is ``depth_bias_scale`` x the class's typical
    #: bias (``detections.CLASS_DEPTH_BIAS_M``) + Normal(0, ``depth_bias_spread_m``).
    depth_bias_scale: float = 1.0
    depth_bias_spread_m: float = 0.04
    #: Probability, for an object 2 m away (growing with depth squared), that the
    #: median depth lands on the background behind the object (a jump of 0.2-1.5 m).
    background_hit_rate: float = 0.05
    #: Multiplies the label-confusion table (0 = no confusions).
    confusion_scale: float = 1.0
    #: Mean number of false-positive detections per frame (Poisson).
    false_positives_per_frame: float = 0.3
    #: Probability that a detected object gets a second, duplicate box.
    duplicate_rate: float = 0.04
    #: A detector run at threshold zero always reports something: a frame with
    #: fewer detections gets false positives to make up this many.
    min_detections: int = 1

    def __post_init__(self) -> None:
        _check_int(self, "seed", low=0)
        _check_int(self, "n_frames", low=2)
        _check_int(self, "start_time_s", low=0)
        _check_int(self, "n_desks", low=2)
        if self.n_desks % 2:
            raise ConfigError(f"n_desks must be even (two back-to-back rows), got {self.n_desks}")
        _check_int(self, "min_detections", low=0)
        _check_range(self, "rate_hz", 0.1, 1000.0)
        _check_range(self, "alias_jitter_m", 0.0, 0.5)
        _check_range(self, "n_loops", 0.1, 50.0)
        _check_range(self, "orbit_radius_m", 0.5, 20.0)
        _check_pair(self, "camera_height_m", 0.1, 3.0)
        _check_range(self, "wobble_deg", 0.0, 45.0)
        _check_range(self, "glances_per_minute", 0.0, 60.0)
        _check_pair(self, "depth_range_m", 0.05, 50.0)
        _check_range(self, "detection_prob", 0.0, 1.0)
        _check_range(self, "half_detection_depth_m", 0.1, 50.0)
        _check_range(self, "border_margin_px", 0.0, 240.0)
        _check_range(self, "miss_corr_frames", 0.0, 1e4)
        _check_range(self, "flicker", 0.0, 1.0)
        _check_range(self, "noise_corr_frames", 0.0, 1e4)
        _check_range(self, "jitter_base_m", 0.0, 1.0)
        _check_range(self, "jitter_depth_quad", 0.0, 1.0)
        _check_range(self, "hard_object_share", 0.0, 1.0)
        _check_range(self, "hard_object_factor", 0.0, 1.0)
        _check_range(self, "occluded_factor", 0.0, 1.0)
        _check_range(self, "blur_half_rad_s", 0.01, 1e3)
        _check_range(self, "back_view_factor", 0.0, 1.0)
        _check_range(self, "class_recall_exponent", 0.0, 10.0)
        _check_range(self, "sigma_base_m", 0.0, 1.0)
        _check_range(self, "sigma_depth_quad", 0.0, 1.0)
        _check_range(self, "depth_bias_scale", 0.0, 10.0)
        _check_range(self, "depth_bias_spread_m", 0.0, 1.0)
        _check_range(self, "background_hit_rate", 0.0, 1.0)
        _check_range(self, "confusion_scale", 0.0, 5.0)
        _check_range(self, "false_positives_per_frame", 0.0, 50.0)
        _check_range(self, "duplicate_rate", 0.0, 1.0)
        if self.depth_range_m[0] >= self.depth_range_m[1]:
            raise ConfigError(f"depth_range_m must be (near, far) with near < far, got {self.depth_range_m}")
        clearance = self.orbit_radius_m - sum(self.block_half_extent_m) / 2
        if clearance < MIN_CLEARANCE_M:
            raise ConfigError(
                f"orbit_radius_m={self.orbit_radius_m} is too small for {self.n_desks} desks: "
                f"the camera would pass {clearance:.2f} m from the desk block "
                f"(at least {MIN_CLEARANCE_M} m needed; use orbit_radius_m >= "
                f"{self.orbit_radius_m - clearance + MIN_CLEARANCE_M:.2f})"
            )

    @property
    def block_half_extent_m(self) -> tuple[float, float]:
        """Half size (x, y) of the central block of desks."""
        return (DESK_WIDTH_M * self.n_desks / 4, DESK_DEPTH_M)

    @property
    def orbit_semi_axes_m(self) -> tuple[float, float]:
        """Semi-axes (x, y) of the camera's elliptic orbit.

        The ellipse keeps the same clearance from the desk block on all sides and
        the mean of its semi-axes is ``orbit_radius_m``.
        """
        hx, hy = self.block_half_extent_m
        clearance = self.orbit_radius_m - (hx + hy) / 2
        return (hx + clearance, hy + clearance)

    @property
    def duration_s(self) -> float:
        return self.n_frames / self.rate_hz

    @classmethod
    def preset(cls, name: str, **overrides: Any) -> OfficeConfig:
        """A named preset, with some settings overridden.

        ``default``: the project's default dataset, TUM-like statistics.
        ``easy``: 600 frames, no false positives, confusions, duplicates or
        background hits, little noise and wobble: for quick tests.
        ``hard``: about twice the noise, flicker, confusions and false
        positives, more glances away, near-identical copies of a desk layout.
        """
        if name not in PRESETS:
            raise ConfigError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
        base: dict[str, Any] = {}
        if name == "easy":
            base = {
                "n_frames": 600,
                "wobble_deg": 3.0,
                "glances_per_minute": 0.0,
                "detection_prob": 1.0,
                "half_detection_depth_m": 8.0,
                "jitter_base_m": 0.001,
                "jitter_depth_quad": 0.0,
                "occluded_factor": 1.0,
                "hard_object_share": 0.0,
                "back_view_factor": 1.0,
                "blur_half_rad_s": 1e3,
                "class_recall_exponent": 0.0,
                "border_margin_px": 0.0,
                "sigma_base_m": 0.002,
                "sigma_depth_quad": 0.002,
                "depth_bias_scale": 0.0,
                "depth_bias_spread_m": 0.0,
                "background_hit_rate": 0.0,
                "confusion_scale": 0.0,
                "false_positives_per_frame": 0.0,
                "duplicate_rate": 0.0,
                "min_detections": 0,
            }
        elif name == "hard":
            base = {
                "glances_per_minute": 6.0,
                "sigma_base_m": 0.02,
                "sigma_depth_quad": 0.03,
                "depth_bias_spread_m": 0.08,
                "background_hit_rate": 0.1,
                "flicker": 0.2,
                "confusion_scale": 2.0,
                "false_positives_per_frame": 0.6,
                "alias_jitter_m": 0.01,
            }
        fields = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(overrides) - fields)
        if unknown:
            raise ConfigError(f"unknown OfficeConfig setting(s): {', '.join(unknown)}")
        base.update(overrides)
        return cls(**base)


#: Size of one desk (width along the row, depth across it).
DESK_WIDTH_M = 1.4
DESK_DEPTH_M = 0.8
#: The camera keeps at least this far from the desks' edges (it may pass over a chair).
MIN_CLEARANCE_M = 0.5


def _check_int(cfg: OfficeConfig, name: str, *, low: int) -> None:
    value = getattr(cfg, name)
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError(f"{name} must be an integer, got {value!r}")
    if value < low:
        raise ConfigError(f"{name} must be >= {low}, got {value}")


def _check_range(cfg: OfficeConfig, name: str, low: float, high: float) -> None:
    value = getattr(cfg, name)
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ConfigError(f"{name} must be a number, got {value!r}")
    if not math.isfinite(value) or not low <= value <= high:
        raise ConfigError(f"{name} must be in [{low}, {high}], got {value}")


def _check_pair(cfg: OfficeConfig, name: str, low: float, high: float) -> None:
    value = getattr(cfg, name)
    ok = (
        isinstance(value, tuple)
        and len(value) == 2
        and all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
    )
    if not ok:
        raise ConfigError(f"{name} must be a (low, high) pair of numbers, got {value!r}")
    lo, hi = value
    if not (math.isfinite(lo) and math.isfinite(hi) and low <= lo <= hi <= high):
        raise ConfigError(f"{name} must satisfy {low} <= low <= high <= {high}, got {value}")
