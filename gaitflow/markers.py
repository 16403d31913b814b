"""The marker set: names, order, and the Alg. 3 cluster mode of each marker.

Marker order is fixed across the whole pipeline: axis 1 of every (F, 20, ...) array and
axis 0 of every (20, ...) array follows :data:`MARKER_NAMES`.
"""

from __future__ import annotations

SIDES = ("L", "R")
SITES = ("SHO", "ASI", "PSI", "HIP", "THI", "KNE", "TIB", "ANK", "HEE", "TOE")
MARKER_NAMES: tuple[str, ...] = tuple(f"{s}_{m}" for s in SIDES for m in SITES)
MARKER_INDEX = {name: i for i, name in enumerate(MARKER_NAMES)}

# Alg. 3 cluster modes, in the order locate publishes them (axis 1 of its positions).
CLUSTER_MODES = ("normal", "top", "bottom")
# algorithms.md section 4: bottom for markers an arm swings in front of; top for heel,
# toe and shoulder; normal for the rest ("never occluded").
SITE_MODE = {
    "SHO": "top",
    "ASI": "bottom",
    "PSI": "bottom",
    "HIP": "bottom",
    "THI": "bottom",
    "KNE": "normal",
    "TIB": "normal",
    "ANK": "normal",
    "HEE": "top",
    "TOE": "top",
}


def cluster_mode(name: str) -> str:
    """Alg. 3 cluster mode for a marker name such as ``"R_HEE"``."""
    return SITE_MODE[name.split("_", 1)[1]]


def trial_kind(trial: str) -> str:
    """Kind of a recording from its session-folder name: calibration, static or walk."""
    if trial == "calibration":
        return "calibration"
    if trial == "static":
        return "static"
    return "walk"
