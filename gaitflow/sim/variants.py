"""Named simulator variants: the plausible set-ups a clinic's recordings differ by.

The pipeline is judged on real trials recorded elsewhere, so the benchmarks run it on
simulated sessions that change the *scene*, never a stage parameter: marker size (20-30 mm),
camera distance, height and tilt, another camera unit's intrinsics, a noisier sensor, a
slow walker, marker-like stray reflectors, and more. ``gaitflow bench mocap --variants``
and ``gaitflow bench gait --variant`` take these names; :func:`sim_config` builds the
quick-protocol configuration of one.

Units as in :class:`gaitflow.sim.config.SimConfig`: mm, degrees.
"""

from __future__ import annotations

from dataclasses import asdict, replace
from typing import Any

from gaitflow.camera import Camera
from gaitflow.errors import ConfigError

# Another Kinect v2 unit: the factory intrinsics of these sensors differ by a few px in focal
# length and principal point and by a few hundredths in the radial terms (published
# per-device calibrations, e.g. Lachat et al. 2015, Pagliari and Pinto 2015).
OTHER_UNIT = Camera(fx=361.2, fy=361.0, cx=259.3, cy=209.6, k1=0.0841, k2=-0.249, k3=0.0812)

# A Kinect-v2-class sensor of another make: Azure Kinect's depth camera in its narrow
# field-of-view mode (640 x 576 px, about 75 x 65 deg), typical factory intrinsics.
AZURE_NFOV = Camera(
    width=640,
    height=576,
    fx=504.2,
    fy=504.3,
    cx=322.1,
    cy=330.6,
    k1=0.12,
    k2=-0.06,
    k3=0.0,
    model="azure-kinect-nfov",
)

# Marker-like reflectors fixed in the room (world mm: x along the walkway, y away from the
# camera, z up; the default walking line is at y = 2750, the back wall at 4250): reflective
# tape on the wall at hip, knee and shoulder height (sphere centres 14 mm off the wall), a
# marker left on the floor 0.6 m behind the line, and one 0.5 m in front of it.
STRAYS = (
    (-600.0, 4236.0, 950.0),
    (1300.0, 4236.0, 480.0),
    (2000.0, 4236.0, 1400.0),
    (400.0, 3350.0, 13.5),
    (-1100.0, 2250.0, 13.5),
)

VARIANTS: dict[str, tuple[dict[str, Any], str]] = {
    "base": (
        {},
        "the defaults: 25 mm markers taped to the skin, walking line 2.75 m away, camera"
        " 0.8 m high",
    ),
    "d20": ({"marker_diameter_mm": 20.0}, "20 mm markers"),
    "d30": ({"marker_diameter_mm": 30.0}, "30 mm markers"),
    "near": ({"walk_distance_mm": 2000.0}, "walking line 2.0 m from the camera"),
    "far": ({"walk_distance_mm": 3500.0}, "walking line 3.5 m from the camera"),
    "high": (
        {"camera_height_mm": 1200.0, "tilt_deg": 8.0},
        "camera 1.2 m high, tilted 8 deg down",
    ),
    "low": ({"camera_height_mm": 500.0, "tilt_deg": -3.0}, "camera 0.5 m high, tilted 3 deg up"),
    "unit2": ({"camera": OTHER_UNIT}, "another sensor unit's intrinsics and distortion"),
    "k4a": ({"camera": AZURE_NFOV}, "another sensor: 640 x 576 px, narrower field of view"),
    "noisy": (
        {"depth_noise_scale": 2.0, "ir_read_noise": 36.0, "flying_prob": 0.8},
        "twice the depth noise, three times the IR read noise, more flying pixels",
    ),
    "slow": ({"speed_factor": 0.6}, "the trial played at 0.6x speed (a slow walker)"),
    "veryslow": (
        {"speed_factor": 0.35},
        "the trial played at 0.35x speed (about 0.4 m/s: a frail or post-stroke walker's speed)",
    ),
    "paretic": (
        {"paretic_swing": 1.5, "speed_factor": 0.7},
        "the left leg's swing 1.5 times as long, the body slowing while it swings, at 0.7x"
        " speed (a hemiparetic walker's asymmetric timing, about 0.8 m/s)",
    ),
    "crouch": (
        {"crouch_mm": 30.0},
        "a crouch gait: pelvis and trunk 30 mm lower with the feet unchanged, so the knees"
        " stay flexed 30 deg or more (as in cerebral palsy); the static pose is crouched too",
    ),
    "skew": (
        {"pan_deg": 6.0, "roll_deg": 3.0},
        "camera turned 6 deg along the walkway and rolled 3 deg (a tripod set up by hand)",
    ),
    "drops": (
        {"drop_prob": 0.05},
        "one frame in 20 dropped by the sensor or the recording tool (the default: 1 in 100)",
    ),
    "offline": (
        {"return_offset_mm": 300.0},
        "the walk back 0.3 m farther from the camera than the walk out (off the taped line)",
    ),
    "child": (
        {"body_scale": 0.72},
        "a child of about 1.25 m: the trial's subject scaled to 0.72 of its size, walking"
        " the same gait with dynamic similarity (times x 0.85), the same 25 mm markers",
    ),
    "fps15": (
        {"camera": Camera(fps=15.0)},
        "15 frames/s (a sensor mode, or a tool that keeps every other frame)",
    ),
    "wands": (
        {"wand_mount": "stick"},
        "the source lab's thigh and tibia wands (markers over 25 mm off the limb) as thin"
        " sticks, no skin under the sphere",
    ),
    "patch": (
        {"wand_mount": "patch"},
        "the default before 27 Nov: a skin patch floating under each of the source lab's"
        " thigh and tibia wands",
    ),
    "strays": (
        {"static_reflectors": STRAYS},
        "five marker-like reflectors fixed in the room, saturating like the markers: on the"
        " back wall at hip, knee and shoulder height, a marker left on the floor 0.6 m"
        " behind the walking line and one 0.5 m in front of it",
    ),
    "strays_late": (
        {"static_reflectors": STRAYS, "reflectors_from": "static"},
        "the same five reflectors put down after the empty walkway was recorded: the"
        " calibration has not seen them, the static pose and the walks have",
    ),
    "shoes": (
        {"shoe_reflectors": ((60.0, -10.0, 45.0),)},
        "a marker-like reflective patch on the outer side of each shoe, 60 mm ahead of the"
        " heel marker (a trainer's logo or strip); it moves with the foot, so clean cannot"
        " learn it",
    ),
    "dim": (
        {"marker_gain": 0.8},
        "markers returning a fifth of the default's light (worn, dusty or another make):"
        " their cores saturate only nearer than 2.2 m, on the walking line they reach 2/3 of"
        " full scale",
    ),
    "faint": (
        {"marker_gain": 0.3},
        "markers returning under a tenth of the default's light: a quarter of full scale on"
        " the walking line, 7 times the skin's IR (the method is built on markers that saturate)",
    ),
    "glare": (
        {"glare_fraction": 0.03},
        "lens glare around the markers: 3 % of their light scattered over the pixels around"
        " them, which brightens the IR there and pulls the depth towards the marker's or makes"
        " it invalid: depth holes about a pixel wider than the markers' images",
    ),
    "mirror": (
        {"start_side": "right"},
        "the camera on the walkway's other side: the subject starts at the image's right edge"
        " and shows the left side first, in the static pose too",
    ),
    "inview": (
        {"walk_margin_mm": -400.0},
        "a short walkway: each pass starts and ends 0.4 m inside the image, so the subject"
        " starts, stops and turns in view",
    ),
}


def variants_help(skip_base: bool = False) -> str:
    """Every set-up with its description, for a command's ``--help`` (argparse's ``%``
    escaped)."""
    items = (f"{k}: {v[1]}" for k, v in VARIANTS.items() if not (skip_base and k == "base"))
    return "; ".join(items).replace("%", "%%")


def variant_changes(name: str) -> dict[str, Any]:
    """The SimConfig changes of variant ``name``; ConfigError naming it if unknown.

    Names joined by ``+`` combine set-ups (``child+far+noisy``): their changes are merged.
    Two camera changes merge field by field (``unit2+fps15``: the other unit's intrinsics
    at 15 frames/s); any other key set by two parts to different values is a ConfigError,
    as is a camera field both parts change (``unit2+k4a``).
    """
    changes: dict[str, Any] = {}
    for part in name.split("+"):
        if part not in VARIANTS:
            raise ConfigError(
                f"simulator variant {part!r} in {name!r} is unknown (known: {list(VARIANTS)};"
                " join names with '+' to combine them)"
            )
        for key, value in VARIANTS[part][0].items():
            changes[key] = _merged(name, key, changes[key], value) if key in changes else value
    return changes


def _merged(name: str, key: str, old: Any, new: Any) -> Any:
    """One SimConfig value set by two parts of combined variant ``name``."""
    if isinstance(old, Camera) and isinstance(new, Camera):
        default = asdict(Camera())
        was, now = asdict(old), asdict(new)
        both = [f for f in default if was[f] != default[f] and now[f] != default[f]]
        clash = [f for f in both if was[f] != now[f]]
        if clash:
            raise ConfigError(
                f"simulator variant {name!r}: two parts set the camera's {', '.join(clash)}"
            )
        return replace(old, **{f: now[f] for f in default if now[f] != default[f]})
    if old != new:
        raise ConfigError(f"simulator variant {name!r}: two parts set {key} ({old!r}, {new!r})")
    return old


def sim_config(name: str = "base", quick: bool = True) -> Any:
    """The SimConfig of variant ``name`` (the quick protocol unless ``quick`` is false)."""
    from gaitflow.sim import SimConfig

    changes = variant_changes(name)
    return SimConfig.quick(**changes) if quick else SimConfig(**changes)
