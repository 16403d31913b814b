"""Ground truth of a simulated recording: per-frame messages and trial-level figures.

For evaluation only: no pipeline stage may read it.

Per frame (:class:`gaitflow.schemas.truth.GroundTruth`): marker centres in camera mm (20, 3),
their projected pixels (u, v), in-view-and-visible and occluded flags, knee flexion from
the simulated markers (180 - angle HIP-KNE-ANK) and the source's Plug-in Gait knee flexion.

Per trial (:func:`spatiotemporal`): the source's labelled events mapped onto both passes,
and step/stride length, stance/swing time from the ground-truth heel trajectories at those
events. Times in s from the recording's first frame, lengths in mm.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from gaitflow.markers import MARKER_INDEX

# Ground-truth positions are the markers at the middle of the exposure, exactly (readers
# that used to correct for a half-blur-sample lag can check this).
TRUTH_AT_MID_EXPOSURE = True

# A marker counts as visible when at least this fraction of its image footprint is seen.
VISIBLE_FRACTION = 0.5


def visibility(seen: np.ndarray, in_view: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(visible, occluded) flags (N,) from the rendered footprint fraction and in-view flag."""
    visible = in_view & (seen >= VISIBLE_FRACTION)
    occluded = in_view & ~visible
    return visible, occluded


# Two blobs whose discs come closer than this (px) join under 8-connectivity: partly covered
# rim pixels bridge the gap.
MERGE_GAP_PX = 1.0


def merged_flags(streak_px: np.ndarray, radius_px: np.ndarray, visible: np.ndarray) -> np.ndarray:
    """Visible markers whose image footprint touches another visible marker's.

    Parameters
    ----------
    streak_px : (B, N, 2) projected centres (u, v) at the B instants of the exposure.
    radius_px : (B, N) projected sphere radius, px.
    visible : (N,) bool.

    Returns
    -------
    (N,) bool: visible, and some other visible marker's disc at any instant of the exposure
    comes within ``MERGE_GAP_PX`` of this one's at any instant (motion-blur streaks count).
    """
    n = streak_px.shape[1]
    out = np.zeros(n, dtype=bool)
    idx = np.flatnonzero(visible)
    if len(idx) < 2:
        return out
    p = streak_px[:, idx]  # (B, V, 2)
    r = radius_px[:, idx]
    # gap[b, i, b2, j]: edge-to-edge distance between marker i at instant b and j at b2.
    d = np.linalg.norm(p[:, :, None, None, :] - p[None, None, :, :, :], axis=-1)
    gap = np.nan_to_num(d - r[:, :, None, None] - r[None, None, :, :], nan=np.inf)
    close = gap.min(axis=(0, 2)) < MERGE_GAP_PX
    np.fill_diagonal(close, False)
    out[idx] = close.any(axis=1)
    return out


def _mean(xs: list[float]) -> float:
    return float(np.mean(xs)) if xs else float("nan")


def spatiotemporal(
    events: list[tuple[float, str, str, str]],
    heel_at: Any,
    directions: dict[str, np.ndarray],
) -> dict[str, Any]:
    """Step/stride lengths and stance/swing times from events and heel trajectories.

    Parameters
    ----------
    events : (time_s, side, kind, pass) with kind FS/FO, sorted by time.
    heel_at : callable t (K,) -> (K, 2, 3) world heel centres (L, R) in mm.
    directions : pass name -> (3,) unit walking direction (world).

    Returns
    -------
    dict with ``steps`` (one record per foot strike that has a previous contralateral
    strike in the same pass), ``strides``, and ``mean`` per side.

    Step length = distance along the walking direction from the contralateral heel at its
    previous strike to the striking heel at this strike; stride length = distance the same
    heel moved between consecutive strikes; stance = FS to the next FO of that foot;
    swing = FO to the next FS of that foot.
    """
    side_idx = {"L": 0, "R": 1}
    steps, strides = [], []
    for pname, direction in directions.items():
        evs = [e for e in events if e[3] == pname]
        fs = [e for e in evs if e[2] == "FS"]
        fo = [e for e in evs if e[2] == "FO"]
        if fs:
            hp = heel_at(np.array([e[0] for e in fs]))  # (K, 2, 3)
        for i, (t, side, _kind, _p) in enumerate(fs):
            s = side_idx[side]
            along = hp[i] @ direction
            prev_other = [j for j in range(i) if fs[j][1] != side]
            if prev_other:
                steps.append(
                    {
                        "pass": pname,
                        "side": side,
                        "time_s": t,
                        "length_mm": float(along[s] - hp[prev_other[-1]][1 - s] @ direction),
                        "time_from_contralateral_s": t - fs[prev_other[-1]][0],
                    }
                )
            prev_same = [j for j in range(i) if fs[j][1] == side]
            if prev_same:
                j = prev_same[-1]
                t0 = fs[j][0]
                length = float(along[s] - hp[j][s] @ direction)
                off = [e[0] for e in fo if e[1] == side and t0 < e[0] < t]
                rec = {
                    "pass": pname,
                    "side": side,
                    "start_s": t0,
                    "end_s": t,
                    "length_mm": length,
                    "time_s": t - t0,
                }
                if off:
                    rec["stance_s"] = off[0] - t0
                    rec["swing_s"] = t - off[0]
                    rec["stance_pct"] = 100.0 * rec["stance_s"] / rec["time_s"]
                    rec["swing_pct"] = 100.0 * rec["swing_s"] / rec["time_s"]
                strides.append(rec)
    mean: dict[str, Any] = {}
    for side in ("L", "R"):
        st = [r for r in strides if r["side"] == side]
        sp = [r for r in steps if r["side"] == side]
        mean[side] = {
            "step_length_mm": _mean([r["length_mm"] for r in sp]),
            "stride_length_mm": _mean([r["length_mm"] for r in st]),
            "stride_time_s": _mean([r["time_s"] for r in st]),
            "stance_s": _mean([r["stance_s"] for r in st if "stance_s" in r]),
            "swing_s": _mean([r["swing_s"] for r in st if "swing_s" in r]),
            "stance_pct": _mean([r["stance_pct"] for r in st if "stance_pct" in r]),
            "swing_pct": _mean([r["swing_pct"] for r in st if "swing_pct" in r]),
        }
    stride_t = [r["time_s"] for r in strides]
    mean["cadence_steps_per_min"] = 120.0 / _mean(stride_t) if stride_t else float("nan")
    lengths = [r["length_mm"] for r in strides]
    mean["speed_m_s"] = (
        _mean(lengths) / 1000.0 / _mean(stride_t) if stride_t and lengths else float("nan")
    )
    return {"steps": steps, "strides": strides, "mean": mean}


def heel_indices() -> list[int]:
    return [MARKER_INDEX["L_HEE"], MARKER_INDEX["R_HEE"]]
