"""The per-trial HTML report: one self-contained file that opens offline.

Built from a results document alone (``gaitflow.results``), so it can be regenerated from
the JSON. Figures are inline SVG drawn with matplotlib's Agg/SVG backend; no script, font or
style is fetched from the network.

Contents: knee flexion over the gait cycle per side (every cycle, their mean, toe off
marked) against a reference band; knee flexion over time with the heel strikes and toe offs
marked; a table of spatio-temporal parameters per side; left/right symmetry indices; the
eight gait phases; the event timing uncertainty of a 30 fps camera.

The reference band (``gaitflow/data/knee_norm.json``) is the mean +/- 1 SD of Plug-in Gait
knee flexion of public motion-capture trials (see :func:`build_normative` and the file's
``sources``): every complete cycle of the straight overground trials of ``shared/gaitdata``
that are not documented as pathological, time-normalised between labelled foot strikes.

Conventions: times in s, angles in degrees, lengths in mm (m/s for speed), gait cycle in %
from a heel strike to the next heel strike of the same foot.
"""

from __future__ import annotations

import argparse
import csv
import html
import io
import itertools
import json
import math
from collections.abc import Mapping, Sequence
from datetime import UTC, datetime
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from gaitflow import __version__
from gaitflow.errors import InputError
from gaitflow.gaitcore import PHASES
from gaitflow.results import floats

SIDES = ("L", "R")
SIDE_NAME = {"L": "Left", "R": "Right"}
COLOURS = {"L": "#c0392b", "R": "#1f5fa8"}
# Initial contact is the instant a cycle starts; the seven phases after it have durations.
PHASE_NAMES = PHASES[1:]


def normative() -> dict[str, Any]:
    """The packaged knee-flexion reference band (``gaitflow/data/knee_norm.json``)."""
    return json.loads(resources.files("gaitflow").joinpath("data/knee_norm.json").read_text())


# ---------------------------------------------------------------------------------------------
# figures from a results document


def knee_cycles(doc: Mapping[str, Any], side: str, min_known: float = 0.5) -> np.ndarray:
    """Knee flexion of every complete gait cycle of one side, normalised to 101 points.

    A cycle runs from a heel strike to the next heel strike of the same foot (the
    ``cycles`` records of the results). Points where the knee is unknown stay NaN (a marker
    hidden for longer than the gap filler bridges); cycles with less than ``min_known`` of
    their points known are left out. Returns (C, 101) deg.
    """
    kt = floats(doc["knee_flexion_deg"]["time_s"])
    kd = floats(doc["knee_flexion_deg"][side])
    out = []
    for c in doc.get("cycles", []):
        if c["side"] != side or "next_heel_strike_s" not in c:
            continue
        a, b = c["heel_strike_s"], c["next_heel_strike_s"]
        sel = (kt >= a - 1e-6) & (kt <= b + 1e-6)
        if sel.sum() < 10:
            continue
        t, k = kt[sel], kd[sel]
        ok = np.isfinite(k)
        if ok.sum() < 5:
            continue
        g = np.linspace(a, b, 101)
        v = np.interp(g, t[ok], k[ok])
        nearest = np.clip(np.searchsorted(t, g), 0, len(t) - 1)
        v[~ok[nearest]] = np.nan
        if np.isfinite(v).mean() >= min_known:
            out.append(v)
    return np.array(out).reshape(-1, 101)


def knee_windows(
    doc: Mapping[str, Any], side: str, period_s: float, min_known: float = 0.9
) -> np.ndarray:
    """Knee flexion minimum and maximum (deg) over windows of one stride time, for a side
    without a complete heel-strike-to-heel-strike cycle.

    The knee angle repeats every stride, so any window of one stride time holds one
    cycle's maximum and minimum, wherever it starts: a side whose strikes were not all
    seen (one camera sees a foot's strike only when that foot is near it) still has a
    ROM. Windows are laid end to end from the first known sample of each run of the
    knee's time base; one counts when ``min_known`` of its samples are known. Returns (W, 2)
    = (min, max) per window.
    """
    kt = floats(doc["knee_flexion_deg"]["time_s"])
    kd = floats(doc["knee_flexion_deg"][side])
    if not (np.isfinite(period_s) and period_s > 0) or not np.isfinite(kd).any():
        return np.zeros((0, 2))
    out = []
    a = float(np.nanmin(kt[np.isfinite(kd)]))
    end = float(np.nanmax(kt[np.isfinite(kd)]))
    while a + period_s <= end + 1e-9:
        sel = (kt >= a) & (kt < a + period_s)
        k = kd[sel]
        if len(k) >= 10 and np.isfinite(k).mean() >= min_known:
            out.append((float(np.nanmin(k)), float(np.nanmax(k))))
            a += period_s
        else:
            # slide on to the next known sample after the first unknown one
            nxt = kt[(kt > a) & np.isfinite(kd)]
            gap = kt[(kt > a) & ~np.isfinite(kd)]
            a = float(nxt[nxt > gap[0]][0]) if gap.size and (nxt > gap[0]).any() else end
    return np.array(out).reshape(-1, 2)


def _cycle_mean(cyc: np.ndarray) -> np.ndarray:
    """Mean over cycles of each point, NaN where no cycle is known there."""
    out = np.full(101, np.nan)
    if len(cyc):
        known = np.isfinite(cyc).any(axis=0)
        out[known] = np.nanmean(cyc[:, known], axis=0)
    return out


def toe_off_pct(doc: Mapping[str, Any], side: str) -> list[float]:
    """Toe off as % of each complete cycle of one side."""
    out = []
    for c in doc.get("cycles", []):
        if c["side"] == side and "next_heel_strike_s" in c and "toe_off_s" in c:
            dur = c["next_heel_strike_s"] - c["heel_strike_s"]
            if dur > 0:
                out.append(100.0 * (c["toe_off_s"] - c["heel_strike_s"]) / dur)
    return out


def _mean_sd(xs: Sequence[float | None]) -> tuple[float, float, int]:
    v = [x for x in xs if x is not None and math.isfinite(x)]
    if not v:
        return float("nan"), float("nan"), 0
    return float(np.mean(v)), float(np.std(v, ddof=1)) if len(v) > 1 else 0.0, len(v)


def side_summary(doc: Mapping[str, Any]) -> dict[str, dict[str, float]]:
    """Per side: steps, means of the spatio-temporal lists, stance/swing %, knee ROM.

    Knee ROM is the mean over complete cycles of (max - min) knee flexion, or, for a side
    without one, over windows of one stride time (:func:`knee_windows`; the stride time
    from the cadence); ``rom_windows`` counts those. Stance % is the mean stance time over
    the mean stride time (stance + swing). The peak comes from the same cycles or windows.
    """
    st = doc["spatiotemporal"]
    out: dict[str, dict[str, float]] = {}
    for s in SIDES:
        d = st[s]
        step, step_sd, n_step = _mean_sd(d["step_length_mm"])
        stride, stride_sd, n_stride = _mean_sd(d["stride_length_mm"])
        stance, stance_sd, _ = _mean_sd(d["stance_s"])
        swing, swing_sd, _ = _mean_sd(d["swing_s"])
        # ROM and peak from the cycles known over at least 90 % of their points, else from
        # windows of one stride time
        cyc = knee_cycles(doc, s, min_known=0.9)
        rom = float(np.mean(np.nanmax(cyc, 1) - np.nanmin(cyc, 1))) if len(cyc) else float("nan")
        peak = float(np.mean(np.nanmax(cyc, axis=1))) if len(cyc) else float("nan")
        windows = np.zeros((0, 2))
        if not len(cyc):
            cadence = st.get("cadence_steps_per_min") or float("nan")
            windows = knee_windows(doc, s, 120.0 / cadence if cadence > 0 else float("nan"))
            if len(windows):
                rom = float(np.mean(windows[:, 1] - windows[:, 0]))
                peak = float(np.mean(windows[:, 1]))
        total = stance + swing
        out[s] = {
            "steps": float(sum(1 for c in doc.get("cycles", []) if c["side"] == s)),
            "step_length_mm": step,
            "step_length_sd": step_sd,
            "n_steps_measured": float(n_step),
            "stride_length_mm": stride,
            "stride_length_sd": stride_sd,
            "n_strides": float(n_stride),
            "stance_s": stance,
            "stance_sd": stance_sd,
            "swing_s": swing,
            "swing_sd": swing_sd,
            "stance_pct": 100.0 * stance / total if total > 0 else float("nan"),
            "swing_pct": 100.0 * swing / total if total > 0 else float("nan"),
            "knee_rom_deg": rom,
            "knee_peak_deg": peak,
            "cycles": float(len(cyc)),
            "rom_windows": float(len(windows)),
        }
    return out


def symmetry_index(left: float, right: float) -> float:
    """Robinson's symmetry index, % : 100 (L - R) / (0.5 (L + R)); 0 = symmetric."""
    if not (math.isfinite(left) and math.isfinite(right)) or left + right == 0:
        return float("nan")
    return 100.0 * (left - right) / (0.5 * (left + right))


def svg_of(fig: Any) -> str:
    """A matplotlib figure as inline SVG markup (from ``<svg``, no XML prologue)."""
    buf = io.StringIO()
    fig.savefig(buf, format="svg", bbox_inches="tight")
    text = buf.getvalue()
    return text[text.index("<svg") :]


def cycle_figure(doc: Mapping[str, Any], norm: Mapping[str, Any]) -> str:
    """SVG: knee flexion over the gait cycle, one panel per side, against the band."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pct = np.asarray(norm["percent"], dtype=float)
    m = np.asarray(norm["mean_deg"], dtype=float)
    sd = np.asarray(norm["sd_deg"], dtype=float)
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6), sharey=True)
    for ax, s in zip(axes, SIDES, strict=True):
        ax.fill_between(pct, m - sd, m + sd, color="0.85", label="reference mean ± 1 SD")
        ax.plot(pct, m, color="0.55", lw=1, ls="--")
        ax.axvline(norm["toe_off_pct_mean"], color="0.6", lw=0.8, ls=":")
        cyc = knee_cycles(doc, s)
        x = np.arange(101)
        for c in cyc:
            ax.plot(x, c, color=COLOURS[s], lw=0.7, alpha=0.35)
        if len(cyc):
            ax.plot(x, _cycle_mean(cyc), color=COLOURS[s], lw=2.2, label=f"mean of {len(cyc)}")
        to = toe_off_pct(doc, s)
        if to:
            ax.axvline(float(np.mean(to)), color=COLOURS[s], lw=1.2, ls="--", label="toe off")
        ax.plot([0, 100], [ax.get_ylim()[0]] * 2, ls="none")
        ax.set_title(f"{SIDE_NAME[s]} knee ({len(cyc)} cycle{'s' if len(cyc) != 1 else ''})")
        ax.set_xlabel("gait cycle, % (heel strike to heel strike)")
        ax.set_xlim(0, 100)
        ax.grid(alpha=0.3)
        ax.legend(loc="upper left", fontsize=8, frameon=False)
        if not len(cyc):
            ax.text(50, 30, "no complete cycle with the knee seen", ha="center", color="0.4")
    axes[0].set_ylabel("knee flexion, deg")
    fig.tight_layout()
    out = svg_of(fig)
    plt.close(fig)
    return out


def time_figure(doc: Mapping[str, Any]) -> str:
    """SVG: knee flexion over the trial with heel strikes (v) and toe offs (^) marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    kt = floats(doc["knee_flexion_deg"]["time_s"])
    fig, ax = plt.subplots(figsize=(10, 3.0))
    for p in doc.get("passes", []):
        ax.axvspan(p["start_s"], p["end_s"], color="0.93")
        arrow = "→" if p["direction"] > 0 else "←"
        ax.text(p["start_s"], 1.0, f" pass {arrow}", transform=ax.get_xaxis_transform(),
                va="top", fontsize=8, color="0.4")  # fmt: skip
    for s in SIDES:
        kd = floats(doc["knee_flexion_deg"][s])
        ax.plot(kt, kd, color=COLOURS[s], lw=1.2, label=f"{SIDE_NAME[s]}")
        for e in doc["events"]:
            if e["side"] != s:
                continue
            y = np.interp(e["time_s"], kt, np.nan_to_num(kd, nan=0.0)) if len(kt) else 0.0
            mk = "v" if e["kind"] == "heel_strike" else "^"
            ax.plot([e["time_s"]], [y], marker=mk, color=COLOURS[s], ms=6, mec="k", mew=0.5)
    ax.plot([], [], "kv", ms=5, label="heel strike")
    ax.plot([], [], "k^", ms=5, label="toe off")
    ax.set_xlabel("time, s")
    ax.set_ylabel("knee flexion, deg")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper right", fontsize=8, ncol=4, frameon=False)
    fig.tight_layout()
    out = svg_of(fig)
    plt.close(fig)
    return out


# ---------------------------------------------------------------------------------------------
# HTML


def fmt_value(v: float, nd: int = 1, sd: float | None = None) -> str:
    """``v`` with ``nd`` decimals (and ``± sd`` when given), "–" when unknown."""
    if v is None or not math.isfinite(v):
        return "–"
    if sd is not None and math.isfinite(sd) and sd > 0:
        return f"{v:.{nd}f} ± {sd:.{nd}f}"
    return f"{v:.{nd}f}"


CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Helvetica,Arial,sans-serif;margin:24px auto;
max-width:1060px;color:#222;line-height:1.4}
h1{font-size:1.5em;margin-bottom:0}
h2{font-size:1.15em;margin-top:1.6em;border-bottom:1px solid #ddd}
.meta{color:#555;font-size:.9em}
.warn{background:#fff4e0;border-left:4px solid #e69500;padding:6px 10px}
.note{background:#eef4fb;border-left:4px solid #1f5fa8;padding:6px 10px;font-size:.92em}
table{border-collapse:collapse;font-size:.92em;margin:6px 0}
td,th{border:1px solid #ccc;padding:4px 10px;text-align:right}th{background:#f3f3f3}
td:first-child,th:first-child{text-align:left}.L{color:#c0392b}.R{color:#1f5fa8}
.small{font-size:.82em;color:#555}svg{max-width:100%;height:auto}
"""


def render_html(doc: Mapping[str, Any], norm: Mapping[str, Any] | None = None) -> str:
    """The whole report as one HTML string (no external resource)."""
    norm = norm or normative()
    esc = html.escape
    summ = side_summary(doc)
    st = doc["spatiotemporal"]
    fps = doc.get("camera_fps") or 30.0
    half_ms = 500.0 / fps
    passes = doc.get("passes", [])
    parts = [
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>",
        f"<title>gaitflow report: {esc(doc['session'])} {esc(doc['trial'])}</title>",
        f"<style>{CSS}</style></head><body>",
        f"<h1>Gait report: {esc(doc['trial'])}</h1>",
        f"<p class='meta'>session <b>{esc(doc['session'] or '–')}</b> · camera {fps:.1f} fps · "
        f"{len(doc['frames'])} frames · {len(passes)} walking pass(es) · "
        f"{len(doc['events'])} gait events · generated "
        f"{datetime.now(UTC).strftime('%Y-%m-%d %H:%M UTC')} by gaitflow {__version__}</p>",
    ]
    for w in doc.get("warnings", []):
        parts.append(f"<p class='warn'>⚠ {esc(w)}</p>")
    if passes:
        rows = "".join(
            f"<tr><td>{i + 1}</td><td>{'left → right' if p['direction'] > 0 else 'right → left'}"
            f"</td><td>{p['start_s']:.2f}–{p['end_s']:.2f}</td>"
            f"<td>{esc(p.get('near_side') or '–')}</td></tr>"
            for i, p in enumerate(passes)
        )
        parts.append(
            "<table><tr><th>pass</th><th>direction (image)</th><th>time, s</th>"
            f"<th>side facing the camera</th></tr>{rows}</table>"
        )
    parts.append("<h2>Knee flexion over the gait cycle</h2>")
    parts.append(cycle_figure(doc, norm))
    src = "; ".join(
        f"{esc(s['trial'])} ({esc(s['source'])}, {esc(s['licence'])})" for s in norm["sources"]
    )
    parts.append(
        f"<p class='small'>Knee flexion = 180° − angle HIP–KNE–ANK from the 3D markers (gap-filled,"
        f" resampled to 100 Hz). Thin lines: each complete cycle; thick: their mean; dashed "
        f"vertical: mean toe off of this trial (grey dotted: reference toe off, "
        f"{norm['toe_off_pct_mean']:.0f} %). Grey band: reference mean ± 1 SD from "
        f"{norm['n_cycles']} cycles of {norm['n_subjects']} adults (Plug-in Gait knee flexion, "
        f"public motion-capture trials, not a clinical normative database; note that Plug-in "
        f"Gait uses joint centres, markers read a few degrees differently): {src}.</p>"
    )
    parts.append("<h2>Knee flexion and gait events over time</h2>")
    parts.append(time_figure(doc))
    parts.append("<h2>Spatio-temporal parameters</h2>")
    rows_def = [
        ("heel strikes", "steps", 0, None),
        ("step length, mm", "step_length_mm", 0, "step_length_sd"),
        ("stride length, mm", "stride_length_mm", 0, "stride_length_sd"),
        ("stance, s", "stance_s", 3, "stance_sd"),
        ("swing, s", "swing_s", 3, "swing_sd"),
        ("stance, % of cycle", "stance_pct", 1, None),
        ("swing, % of cycle", "swing_pct", 1, None),
        ("knee ROM, deg", "knee_rom_deg", 1, None),
        ("peak knee flexion, deg", "knee_peak_deg", 1, None),
    ]
    body = "".join(
        f"<tr><td>{label}</td>"
        + "".join(
            f"<td class='{s}'>{fmt_value(summ[s][key], nd, summ[s][sd] if sd else None)}</td>"
            for s in SIDES
        )
        + "</tr>"
        for label, key, nd, sd in rows_def
    )
    parts.append(
        "<table><tr><th>parameter (mean ± SD)</th><th class='L'>Left</th>"
        f"<th class='R'>Right</th></tr>{body}</table>"
    )
    for s in SIDES:
        if summ[s]["rom_windows"]:
            n = int(summ[s]["rom_windows"])
            parts.append(
                f"<p class='small'>{SIDE_NAME[s]} knee ROM and peak: no complete gait cycle "
                f"with the knee seen, so from {n} window{'s' if n != 1 else ''} of one stride "
                "time (120 / cadence) with the knee known over 90 % of it.</p>"
            )
    parts.append(
        f"<table><tr><th>both sides</th><th>value</th></tr>"
        f"<tr><td>cadence, steps/min</td>"
        f"<td>{fmt_value(st.get('cadence_steps_per_min'), 1)}</td></tr>"
        f"<tr><td>walking speed, m/s</td><td>{fmt_value(st.get('speed_m_s'), 2)}</td></tr></table>"
    )
    parts.append("<h2>Left/right symmetry</h2>")
    sym_rows = [
        ("step length", "step_length_mm"),
        ("stride length", "stride_length_mm"),
        ("stance time", "stance_s"),
        ("swing time", "swing_s"),
        ("knee ROM", "knee_rom_deg"),
    ]
    body = "".join(
        f"<tr><td>{label}</td><td>{fmt_value(symmetry_index(summ['L'][k], summ['R'][k]), 1)}</td>"
        f"<td>{fmt_value(summ['L'][k] / summ['R'][k] if summ['R'][k] else float('nan'), 3)}"
        "</td></tr>"
        for label, k in sym_rows
    )
    parts.append(
        "<table><tr><th>parameter</th><th>symmetry index, %</th><th>ratio L/R</th></tr>"
        f"{body}</table><p class='small'>Symmetry index = 100 (L − R) / ½(L + R) "
        "(Robinson et al. 1987); 0 = symmetric, positive = left larger.</p>"
    )
    phases = doc.get("phases", {})
    if any(phases.get(s) for s in SIDES):
        parts.append("<h2>Gait phases (% of the gait cycle, mean)</h2>")
        head = "".join(f"<th>{p.replace('_', ' ')}</th>" for p in PHASE_NAMES)
        body = ""
        for s in SIDES:
            cyc = phases.get(s, [])
            if not cyc:
                continue
            starts = {p: [] for p in PHASE_NAMES}
            for c in cyc:
                dur = c["end"] - c["initial_contact"]
                names = [*PHASE_NAMES[1:], "end"]
                for p, nxt in zip(PHASE_NAMES, names, strict=True):
                    starts[p].append(100.0 * (c[nxt] - c[p]) / dur)
            cells = "".join(f"<td>{fmt_value(float(np.mean(v)), 1)}</td>" for v in starts.values())
            body += f"<tr><td class='{s}'>{SIDE_NAME[s]} ({len(cyc)})</td>{cells}</tr>"
        parts.append(
            f"<table><tr><th>side (cycles)</th>{head}</tr>{body}</table><p class='small'>Initial "
            "contact is the heel strike itself. Phase ends: contralateral toe off, heel rise, "
            "contralateral heel strike, toe off, feet adjacent, tibia vertical, next heel "
            "strike.</p>"
        )
    parts.append(
        "<h2>Event timing uncertainty</h2><p class='note'>"
        f"The camera samples the markers every {1000.0 / fps:.1f} ms ({fps:.0f} fps). Heel "
        f"strikes and toe offs are located on curves resampled to 100 Hz, but an event can "
        f"fall anywhere between two camera frames: each event time is uncertain by about "
        f"±{half_ms:.1f} ms (half a frame), so a stance or swing duration by up to "
        f"±{2 * half_ms:.0f} ms (about ±{200 * half_ms / 600:.0f} % of a 0.6 s stance). "
        "Averages over several strides are more precise than single values.</p>"
    )
    params = doc.get("parameters", {})
    if params:
        parts.append(
            "<p class='small'>Method: Bezier gap filling (max "
            f"{params.get('max_gap_s', '?')} s), Catmull-Rom resampling to "
            f"{params.get('resample_hz', '?')} Hz, Alg. 6 inflection search on heel and toe "
            f"heights (γ = {params.get('gamma')}, ξ = {params.get('xi')}, φ = "
            f"{params.get('phi')}, τ = {params.get('tau')}), event refinement "
            f"'{esc(str(params.get('refine')))}'.</p>"
        )
    parts.append("</body></html>")
    return "\n".join(parts)


def write_report(doc: Mapping[str, Any], path: str | Path) -> Path:
    """Write the HTML report of one results document."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(render_html(doc), encoding="utf-8")
    return p


# ---------------------------------------------------------------------------------------------
# the reference band


def build_normative(trials_dir: str | Path) -> dict[str, Any]:
    """Build the knee-flexion reference band from ``shared/gaitdata/trials``.

    Trials: overground (not treadmill), with Plug-in Gait knee angles, whose population is
    not documented as pathological. Every complete cycle (foot strike to the next foot
    strike of that foot, from the labelled events) of each side is time-normalised to 101
    points by linear interpolation; mean and SD are over all cycles pooled.
    """
    root = Path(trials_dir)
    try:
        rows = list(csv.DictReader((root / "index.csv").open()))
    except OSError as exc:
        raise InputError(root / "index.csv", f"cannot read: {exc}") from exc
    cycles: list[np.ndarray] = []
    toe: list[float] = []
    used = []
    for r in rows:
        if (
            r["task"] != "overground walking"
            or not r["ref_angle_source"].startswith("Plug")
            or "pathological" in r["population"]
            or r["treadmill_like"] != "False"
        ):
            continue
        d = np.load(root / f"{r['trial_id']}.npz", allow_pickle=True)
        names = list(d["ref_angle_names"])
        angles = d["ref_angles"]
        t = np.arange(len(angles)) / float(d["rate_hz"])
        n0 = len(cycles)
        for s in SIDES:
            if f"{s}KneeAngles" not in names:
                continue
            k = angles[:, names.index(f"{s}KneeAngles"), 0]
            sel = d["event_sides"] == s
            fs = sorted(d["event_times"][sel & (d["event_kinds"] == "FS")])
            fo = d["event_times"][sel & (d["event_kinds"] == "FO")]
            for a, b in itertools.pairwise(fs):
                v = np.interp(np.linspace(a, b, 101), t, k)
                if not np.all(np.isfinite(v)):
                    continue
                cycles.append(v)
                o = [x for x in fo if a < x < b]
                if o:
                    toe.append(100.0 * (o[0] - a) / (b - a))
        if len(cycles) > n0:
            used.append(
                {
                    "trial": r["trial_id"],
                    "source": r["source"].split(" :")[0],
                    "licence": r["licence"],
                    "subject": r["subject"],
                }
            )
    allc = np.array(cycles)
    return {
        "title": "Knee flexion reference band over the gait cycle (adult overground walking)",
        "description": "Mean and SD of Plug-in Gait knee flexion (deg) at 0..100 % of the gait "
        "cycle, pooled over every complete cycle of the straight overground trials of "
        "shared/gaitdata that are not documented as pathological; built by "
        "gaitflow.report.build_normative. A small reference band from public sample data, not "
        "a clinical normative database.",
        "n_cycles": len(allc),
        "n_subjects": len({u["subject"] for u in used}),
        "toe_off_pct_mean": round(float(np.mean(toe)), 2) if toe else None,
        "toe_off_pct_sd": round(float(np.std(toe, ddof=1)), 2) if len(toe) > 1 else None,
        "percent": list(range(101)),
        "mean_deg": [round(float(x), 2) for x in allc.mean(axis=0)],
        "sd_deg": [round(float(x), 2) for x in allc.std(axis=0, ddof=1)],
        "sources": used,
    }


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m gaitflow.report``: render a results JSON, or rebuild the band."""
    from gaitflow.results import read_results

    p = argparse.ArgumentParser(prog="python -m gaitflow.report", description=__doc__)
    p.add_argument("results", nargs="?", help="a <trial>.json results file to render")
    p.add_argument("--out", help="HTML output (default: beside the JSON)")
    p.add_argument("--build-norm", metavar="TRIALS_DIR", help="rebuild data/knee_norm.json")
    args = p.parse_args(argv)
    if args.build_norm:
        doc = build_normative(args.build_norm)
        out = Path(__file__).parent / "data" / "knee_norm.json"
        out.write_text(json.dumps(doc, indent=1) + "\n")
        print(out)
    if args.results:
        res = read_results(args.results)
        out = Path(args.out) if args.out else Path(args.results).with_suffix(".html")
        print(write_report(res, out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
