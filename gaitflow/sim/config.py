"""Every knob of the Kinect v2 simulator in one frozen dataclass.

Units: mm, s, degrees, IR amplitude counts (0..65535). Defaults follow the clinical set-up
of the paper (sensor about 0.8 m high, walking line 2.5-3 m away, about 4 m of walkway)
and published Kinect v2 characteristics; each default says where it comes from.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

from gaitflow.camera import Camera
from gaitflow.errors import ConfigError

# What carries a thigh or tibia marker that the source lab put on a wand (sim/body.py).
WAND_MOUNTS = ("patch", "stick", "skin")


RECORDING_KINDS = ("calibration", "static", "walk")  # in protocol order


@dataclass(frozen=True)
class SimConfig:
    """Simulator configuration.

    Geometry: the world frame has x along the walkway (left to right in the image), y away
    from the camera, z up, origin on the floor below the camera's optical centre.
    """

    camera: Camera = field(default_factory=Camera)
    camera_height_mm: float = 800.0
    walk_distance_mm: float = 2750.0  # camera to the walking line (pelvis path)
    tilt_deg: float = 1.5  # positive = looking down
    pan_deg: float = 1.0  # positive = optical axis turned towards +x
    roll_deg: float = 0.4
    back_wall_mm: float = 1500.0  # wall this far behind the walking line; 0 = none
    marker_diameter_mm: float = 25.0
    source_marker_diameter_mm: float = 14.0  # Plug-in Gait markers of the source labs
    marker_base_mm: float = 2.0  # marker base (and tape) between the sphere and the skin
    skin_patch_mm: float = 70.0  # width of the skin surface modelled under each marker
    wand_mount: str = "skin"  # what carries a wand marker: patch, stick or skin (body.py)
    wand_mm: float = 25.0  # THI/TIB whose base stands this far off the limb are on wands
    # Exposure and anti-aliasing.
    exposure_ms: float = 12.0  # ToF integration window (motion blur)
    blur_samples: int = 4  # time samples over the exposure
    supersample: int = 4  # sub-pixel samples per axis for marker coverage
    # IR radiometry: I = ir_gain * albedo * cos(incidence) / (r / 1 m)^2 * vignetting.
    ir_gain: float = 30000.0
    skin_albedo: float = 0.55
    clothes_albedo: float = 0.45  # T-shirt (and the operator's clothes)
    shorts_albedo: float = 0.25  # dark shorts
    floor_albedo: float = 0.3
    wall_albedo: float = 0.45
    marker_gain: float = 4.0  # marker radiance at 2.5 m, in multiples of saturation
    vignetting: float = 0.35  # relative IR loss at the image corners
    ir_read_noise: float = 12.0  # counts
    ir_shot_noise: float = 1.5  # variance per count
    ir_min_valid: float = 30.0  # below this amplitude the depth is invalid (0)
    # Depth.
    depth_noise_scale: float = 1.0  # multiplies the Fankhauser et al. (2015) sigma
    min_range_mm: float = 500.0
    max_range_mm: float = 4500.0
    max_incidence_deg: float = 82.0  # grazing surfaces return no depth
    edge_jump_mm: float = 80.0  # a neighbour this much farther makes a depth edge
    flying_prob: float = 0.5  # an edge pixel becomes a mixed-depth ("flying") pixel
    edge_invalid_prob: float = 0.25  # an edge pixel becomes invalid (0)
    hole_coverage: float = 0.25  # marker coverage above which depth is 0
    # Lens glare: this share of each marker's light scattered over a Gaussian of
    # glare_sigma_px around it, pulling the depth there towards the marker's and making it
    # invalid where the stray light is more than glare_invalid_share of a pixel's light
    # (render._glare). 0 = none (the default).
    glare_fraction: float = 0.0
    glare_sigma_px: float = 1.2
    glare_invalid_share: float = 0.25
    # Frames.
    drop_prob: float = 0.01
    jitter_ms: float = 0.4
    # Scene.
    stray_reflectors: bool = True
    # Marker-like retro-reflective spheres fixed in the scene (world centres, mm; the
    # markers' diameter): a leftover floor marker, reflective tape on equipment or a sign.
    # They saturate and cut depth holes like the body markers, and are never in the truth.
    static_reflectors: tuple[tuple[float, float, float], ...] = ()
    # The first recording in which they are there: "calibration" (the room has them), or
    # "static" / "walk" (put down after the empty walkway was recorded).
    reflectors_from: str = "calibration"
    # Marker-like reflectors on the subject's shoes (a reflective logo or strip), one sphere
    # per entry and foot: (forward from the heel marker along the foot, up, outward to the
    # foot's lateral side), mm, scaled with body_scale. They move with the feet, so clean
    # never learns them, and they are never in the truth.
    shoe_reflectors: tuple[tuple[float, float, float], ...] = ()
    # Subject.
    subject_id: str = "S01"
    arm_swing_gain: float = 0.7  # shoulder angle / contralateral thigh angle
    speed_factor: float = 1.0  # >1 plays the trial faster
    body_scale: float = 1.0  # the subject's size (a child < 1; body.scale_trial)
    # An asymmetric (hemiparetic-like) gait: the paretic leg's swing lasts this many times
    # as long, the whole body slowing while it swings (1 = the source's own timing;
    # walk.WalkMotion's clock).
    paretic_swing: float = 1.0
    paretic_side: str = "L"
    crouch_mm: float = 0.0  # pelvis and trunk this much lower, feet kept (body.crouch_trial)
    # Protocol durations.
    calibration_markers: int = 4
    calib_still_s: float = 1.2
    calib_place_s: float = 2.0
    static_s: float = 3.0
    turn_s: float = 1.5
    lead_in_s: float = 0.3  # still standing before each pass
    n_walks: int = 1
    walk_margin_mm: float = 1000.0  # each pass starts and ends this far outside the image
    return_offset_mm: float = 0.0  # the return pass this much farther from the camera
    # Which image edge the first pass starts from: "left" (the right side faces the camera
    # first) or "right" (the camera on the walkway's other side: the left side first).
    start_side: str = "left"
    show_operator: bool = True

    def __post_init__(self) -> None:
        if not 20.0 <= self.marker_diameter_mm <= 30.0:
            raise ConfigError(
                f"SimConfig.marker_diameter_mm={self.marker_diameter_mm} is outside 20..30 mm"
            )
        if not 0.0 <= self.drop_prob < 0.5:
            raise ConfigError(f"SimConfig.drop_prob={self.drop_prob} is outside [0, 0.5)")
        if self.supersample < 1 or self.blur_samples < 1:
            raise ConfigError("SimConfig.supersample and blur_samples must be >= 1")
        if not 0.5 <= self.body_scale <= 1.3:
            raise ConfigError(f"SimConfig.body_scale={self.body_scale} is outside 0.5..1.3")
        if self.speed_factor <= 0:
            raise ConfigError(f"SimConfig.speed_factor={self.speed_factor} must be positive")
        if not 1.0 <= self.paretic_swing <= 3.0:
            raise ConfigError(f"SimConfig.paretic_swing={self.paretic_swing} is outside 1..3")
        if not 0.0 <= self.crouch_mm <= 150.0:
            raise ConfigError(f"SimConfig.crouch_mm={self.crouch_mm} is outside 0..150 mm")
        if self.start_side not in ("left", "right"):
            raise ConfigError(f"SimConfig.start_side={self.start_side!r} is not left or right")
        if self.paretic_side not in ("L", "R"):
            raise ConfigError(f"SimConfig.paretic_side={self.paretic_side!r} is not L or R")
        if self.wand_mount not in WAND_MOUNTS:
            raise ConfigError(
                f"SimConfig.wand_mount={self.wand_mount!r} is not one of {', '.join(WAND_MOUNTS)}"
            )
        if self.reflectors_from not in RECORDING_KINDS:
            raise ConfigError(
                f"SimConfig.reflectors_from={self.reflectors_from!r} is not one of"
                f" {', '.join(RECORDING_KINDS)}"
            )
        if any(len(o) != 3 or not all(math.isfinite(v) for v in o) for o in self.shoe_reflectors):
            raise ConfigError(
                f"SimConfig.shoe_reflectors={self.shoe_reflectors!r}: each must be three finite mm"
            )
        if not 0.0 <= self.glare_fraction < 0.5 or self.glare_sigma_px <= 0:
            raise ConfigError(
                f"SimConfig.glare_fraction={self.glare_fraction} must be in [0, 0.5) and"
                f" glare_sigma_px={self.glare_sigma_px} positive"
            )
        if self.n_walks < 1:
            raise ConfigError(f"SimConfig.n_walks={self.n_walks} must be >= 1")

    @property
    def marker_radius_mm(self) -> float:
        return 0.5 * self.marker_diameter_mm

    def with_(self, **changes: Any) -> SimConfig:
        """A copy with some fields changed."""
        return replace(self, **changes)

    @classmethod
    def quick(cls, **changes: Any) -> SimConfig:
        """Short protocol durations for tests and benchmarks."""
        base = dict(calib_still_s=0.4, calib_place_s=0.6, static_s=0.5, turn_s=0.6, lead_in_s=0.1)
        base.update(changes)
        return cls(**base)
