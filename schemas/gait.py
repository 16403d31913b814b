"""Streams ``gait`` (per-frame kinematics and events) and ``summary`` (per trial pass).

Per-frame arrays are per side, axis 0 = (L, R). Angles in degrees, heights in mm, times in
seconds from the trial's first frame. Events are ``[side, kind, time_s]`` records with kind
``heel_strike`` or ``toe_off``. The summary carries the results document of
``../shared/spec/results.md`` as a msgpack map.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from gaitflow.schemas._codec import Message, array_field, register, value_field


@register
@dataclass(frozen=True, eq=False)
class GaitFrame(Message):
    """Kinematics of one frame and the gait events detected so far in the pass."""

    STREAM = "gait"
    VERSION = 1

    knee_flexion: np.ndarray = array_field("float64", (2,), "(L, R) deg, 180 - HIP-KNE-ANK")
    heel_height: np.ndarray = array_field("float64", (2,), "(L, R) heel height above floor, mm")
    toe_height: np.ndarray = array_field("float64", (2,), "(L, R) toe height above floor, mm")
    time_s: float = value_field(float, 0.0, "seconds since the trial's first frame")
    events: list = value_field(list, [], "new [side, kind, time_s] events since last frame")


@register
@dataclass(frozen=True, eq=False)
class TrialSummary(Message):
    """The results of one walking trial (results.md, version 1)."""

    STREAM = "summary"
    VERSION = 1

    results: dict = value_field(dict, meaning="the trial results document of results.md")
    warnings: list = value_field(list, [], "human-readable warnings about this trial")
