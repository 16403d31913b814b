"""The patient record: every analysed session of a subject, and their progress over therapy.

``gaitflow analyze SESSION --store STORE`` writes a session's results into the store, one
folder per subject and one per session::

    STORE/<subject>/<session>/session.json     what was analysed, when, and the visit's date
    STORE/<subject>/<session>/walk-01.json     results JSON (shared/spec/results.md)
    STORE/<subject>/<session>/walk-01.html     the trial's report

``gaitflow progress STORE SUBJECT`` reads a subject's sessions back, pools each session's
walking trials into one row of figures (the same per-side figures as the trial report:
:func:`gaitflow.report.side_summary`), and prints and writes them as a table and an HTML page
with one chart per figure over the visits.

The subject is the session's ``camera.json`` ``subject.id`` (a pseudonym, never a name;
``session-folder.md``) unless given; the visit's date is ``--date``, else the first
``YYYY-MM-DD`` in the session folder's name, else unknown (sessions without a date are
shown after the dated ones, in the order they were analysed).

Conventions: lengths mm, times s, angles degrees, speed m/s; NaN = not measured.
"""

from __future__ import annotations

import csv
import html
import json
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, date, datetime
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from gaitflow import __version__
from gaitflow.errors import InputError
from gaitflow.results import read_results

MANIFEST = "session.json"
MANIFEST_FORMAT = "gaitflow.session-record"
MANIFEST_VERSION = 1
# A folder name: no separators, no leading dot (no "..", no hidden files).
SAFE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")
ISO_DATE = re.compile(r"(\d{4})-(\d{2})-(\d{2})")

# (key, label, unit, per side?, decimals): the figures of one session, in table order.
FIGURES: tuple[tuple[str, str, str, bool, int], ...] = (
    ("speed_m_s", "speed", "m/s", False, 2),
    ("cadence_steps_per_min", "cadence", "steps/min", False, 1),
    ("stride_length_mm", "stride length", "mm", True, 0),
    ("step_length_mm", "step length", "mm", True, 0),
    ("stance_pct", "stance", "% of stride", True, 1),
    ("knee_rom_deg", "knee ROM", "deg", True, 1),
    ("knee_peak_deg", "knee peak flexion", "deg", True, 1),
)


def safe_name(name: str, what: str) -> str:
    """``name`` if it can be a folder of the store, else an :class:`InputError` naming it."""
    if not SAFE_NAME.match(name):
        raise InputError(
            what, f"{name!r} cannot name a store folder (letters, digits, '.', '_', '-'; 1-64)"
        )
    return name


def subject_of(camera_json: Mapping[str, Any], override: str | None = None) -> str:
    """The subject id: ``override``, else camera.json's ``subject.id``."""
    if override:
        return safe_name(override, "--subject")
    subject = camera_json.get("subject")
    sid = subject.get("id") if isinstance(subject, Mapping) else None
    if not sid:
        raise InputError("camera.json", "no subject.id: pass --subject ID to store the session")
    return safe_name(str(sid), "camera.json subject.id")


def session_date(session: str, explicit: str | None = None) -> str | None:
    """The visit's date (ISO ``YYYY-MM-DD``): ``explicit``, else one in the session name."""
    if explicit:
        try:
            return date.fromisoformat(explicit).isoformat()
        except ValueError as exc:
            raise InputError("--date", f"{explicit!r} is not a date YYYY-MM-DD") from exc
    for m in ISO_DATE.finditer(session):
        try:
            return date(int(m[1]), int(m[2]), int(m[3])).isoformat()
        except ValueError:
            continue
    return None


def session_dir(store: str | Path, subject: str, session: str) -> Path:
    """Where one session of a subject lives in the store."""
    return Path(store) / safe_name(subject, "subject") / safe_name(session, "session")


def write_manifest(
    folder: str | Path, subject: str, session: str, visit: str | None, trials: Sequence[str]
) -> Path:
    """Write ``session.json``: subject, session, visit date, analysis time, trials."""
    doc = {
        "format": MANIFEST_FORMAT,
        "version": MANIFEST_VERSION,
        "subject": subject,
        "session": session,
        "date": visit,
        "analysed_at": datetime.now(UTC).isoformat(timespec="seconds"),
        "gaitflow": __version__,
        "trials": list(trials),
    }
    p = Path(folder) / MANIFEST
    p.write_text(json.dumps(doc, indent=1) + "\n")
    return p


@dataclass
class SessionRecord:
    """One stored session: its manifest fields and the trials that could be read."""

    session: str
    date: str | None
    analysed_at: str
    folder: Path
    docs: list[dict[str, Any]] = field(default_factory=list)
    reports: list[Path] = field(default_factory=list)

    @cached_property
    def figures(self) -> dict[str, Any]:
        """The session's figures (:func:`session_figures`), computed once for every view."""
        return session_figures(self.docs)


def _read_manifest(p: Path) -> dict[str, Any]:
    try:
        doc = json.loads(p.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(p, f"cannot read the session record: {exc}") from exc
    if not isinstance(doc, dict) or doc.get("format") != MANIFEST_FORMAT:
        raise InputError(p, f"not a gaitflow session record (format {MANIFEST_FORMAT!r})")
    if doc.get("version") != MANIFEST_VERSION:
        raise InputError(p, f"session record version {doc.get('version')!r} (this reads 1)")
    for key in ("session", "trials", "analysed_at"):
        if key not in doc:
            raise InputError(p, f"session record without {key!r}")
    trials = doc["trials"]
    if not isinstance(trials, list) or not all(
        isinstance(t, str) and SAFE_NAME.match(t) for t in trials
    ):
        raise InputError(p, f"session record 'trials' is not a list of trial names: {trials!r}")
    return doc


def load_subject(store: str | Path, subject: str) -> tuple[list[SessionRecord], list[InputError]]:
    """Every stored session of ``subject``, oldest visit first, and what could not be read.

    A session or trial file that cannot be read is reported in the second list (its error
    names the file) and left out; the others are returned.
    """
    root = Path(store) / safe_name(subject, "subject")
    if not root.is_dir():
        raise InputError(root, f"no stored sessions for subject {subject!r}")
    sessions: list[SessionRecord] = []
    errors: list[InputError] = []
    for mp in sorted(root.glob(f"*/{MANIFEST}")):
        try:
            man = _read_manifest(mp)
        except InputError as exc:
            errors.append(exc)
            continue
        rec = SessionRecord(
            str(man["session"]), man.get("date"), str(man["analysed_at"]), mp.parent
        )
        for trial in man["trials"]:
            jp = mp.parent / f"{trial}.json"
            try:
                rec.docs.append(read_results(jp))
            except InputError as exc:
                errors.append(exc)
                continue
            hp = jp.with_suffix(".html")
            if hp.exists():
                rec.reports.append(hp)
        sessions.append(rec)
    # dated visits first, by date; then the undated, in the order they were analysed
    sessions.sort(key=lambda r: (r.date is None, r.date or "", r.analysed_at, r.session))
    return sessions, errors


def _mean(xs: Sequence[float]) -> float:
    v = [x for x in xs if x is not None and math.isfinite(x)]
    return float(np.mean(v)) if v else float("nan")


def session_figures(docs: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """One session's figures from its walking trials' results documents.

    Step and stride lengths pool every step and stride of the session; stance % is the
    pooled mean stance time over the pooled mean stride time; knee ROM and peak are the mean
    of the trials' values (each from complete cycles or stride windows, as in the report);
    cadence and speed the mean over the trials that have one.

    Returns ``{key: float}`` for the session-wide figures and ``{key: {"L": .., "R": ..}}``
    for the per-side ones (:data:`FIGURES`), plus ``trials``, ``steps`` and the
    step-length symmetry index ``step_symmetry_pct`` (Robinson; 0 = symmetric).
    """
    from gaitflow.report import SIDES, side_summary, symmetry_index

    summaries = [side_summary(d) for d in docs]
    out: dict[str, Any] = {"trials": len(docs)}
    for key in ("speed_m_s", "cadence_steps_per_min"):
        out[key] = _mean([d["spatiotemporal"].get(key) for d in docs])
    out.update({key: {} for key, _, _, per_side, _ in FIGURES if per_side})
    steps = 0
    for s in SIDES:
        pooled = {
            k: [x for d in docs for x in d["spatiotemporal"][s][k] if x is not None]
            for k in ("step_length_mm", "stride_length_mm", "stance_s", "swing_s")
        }
        steps += len(pooled["step_length_mm"])
        out["step_length_mm"][s] = _mean(pooled["step_length_mm"])
        out["stride_length_mm"][s] = _mean(pooled["stride_length_mm"])
        stance, swing = _mean(pooled["stance_s"]), _mean(pooled["swing_s"])
        total = stance + swing
        out["stance_pct"][s] = 100.0 * stance / total if total > 0 else float("nan")
        out["knee_rom_deg"][s] = _mean([sm[s]["knee_rom_deg"] for sm in summaries])
        out["knee_peak_deg"][s] = _mean([sm[s]["knee_peak_deg"] for sm in summaries])
    out["steps"] = steps
    out["step_symmetry_pct"] = symmetry_index(
        out["step_length_mm"]["L"], out["step_length_mm"]["R"]
    )
    return out


def _figure_sides() -> list[tuple[str, str | None, str, int]]:
    """:data:`FIGURES` one column each: (key, side or None, label with unit, decimals)."""
    return [
        (key, s, f"{label}{' ' + s if s else ''}, {unit}", nd)
        for key, label, unit, per_side, nd in FIGURES
        for s in (("L", "R") if per_side else (None,))
    ]


def _value(fig: Mapping[str, Any], key: str, side: str | None) -> float:
    v = fig[key][side] if side else fig[key]
    return float(v) if v is not None else float("nan")


def progress_table(
    sessions: Sequence[SessionRecord],
) -> tuple[list[str], list[tuple[str, int, list[float], float]]]:
    """The progress table: one column per visit (its date, else its session name), one row
    per figure: (label with unit, decimals, value per visit, change from the first visit to
    the last, NaN where either is unknown). The first rows count trials and steps; the last
    is the step-length symmetry index."""
    figs = [r.figures for r in sessions]
    header = ["figure", *(r.date or r.session for r in sessions), "change"]
    rows: list[tuple[str, int, list[float], float]] = [
        ("walking trials", 0, [float(f["trials"]) for f in figs], float("nan")),
        ("steps measured", 0, [float(f["steps"]) for f in figs], float("nan")),
    ]
    for key, s, name, nd in _figure_sides():
        vals = [_value(f, key, s) for f in figs]
        rows.append((name, nd, vals, vals[-1] - vals[0] if vals else float("nan")))
    sym = [float(f["step_symmetry_pct"]) for f in figs]
    rows.append(("step symmetry (L vs R), %", 1, sym, float("nan")))
    return header, rows


def write_progress_csv(sessions: Sequence[SessionRecord], path: str | Path) -> Path:
    """The progress table for a spreadsheet: one row per visit (date, session, then one
    column per figure, the per-side ones as ``<key>_L`` / ``<key>_R``); empty = unknown."""
    keys = [("trials", None), ("steps", None), *((k, s) for k, s, _, _ in _figure_sides())]
    keys.append(("step_symmetry_pct", None))
    header = ["date", "session", *(f"{k}_{s}" if s else k for k, s in keys)]
    p = Path(path)
    with p.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        for rec in sessions:
            vals = [_value(rec.figures, k, s) for k, s in keys]
            w.writerow(
                [
                    rec.date or "",
                    rec.session,
                    *(f"{v:.6g}" if math.isfinite(v) else "" for v in vals),
                ]
            )
    return p


def _signed(v: float, nd: int) -> str:
    return f"{v:+.{nd}f}" if math.isfinite(v) else "–"


def format_progress(subject: str, sessions: Sequence[SessionRecord]) -> str:
    """The progress table as text, for the terminal."""
    from gaitflow.benchutil import format_table
    from gaitflow.report import fmt_value

    header, rows = progress_table(sessions)
    lines = [
        [name, *(fmt_value(v, nd) for v in vals), _signed(ch, nd)] for name, nd, vals, ch in rows
    ]
    sessions_row = ["session", *(r.session for r in sessions), ""]
    return format_table(f"gaitflow progress: subject {subject}", header, [sessions_row, *lines])


def _chart(key: str, label: str, unit: str, per_side: bool, figs: list[dict], x: list[str]) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from gaitflow.report import COLOURS, SIDE_NAME, svg_of

    fig, ax = plt.subplots(figsize=(3.4, 2.5))
    idx = np.arange(len(x))
    series = [(s, [_value(f, key, s) for f in figs]) for s in (("L", "R") if per_side else (None,))]
    for s, ys in series:
        colour = COLOURS[s] if s else "0.2"
        ax.plot(idx, ys, marker="o", color=colour, lw=1.5, label=SIDE_NAME[s] if s else None)
    ax.set_xticks(idx, x, rotation=30, ha="right", fontsize=8)
    ax.set_title(f"{label}, {unit}", fontsize=10)
    ax.grid(alpha=0.3)
    if per_side:
        ax.legend(fontsize=8, frameon=False)
    fig.tight_layout()
    out = svg_of(fig)
    plt.close(fig)
    return out


def _href(path: Path, base: Path) -> str:
    """A link to ``path`` from a page in ``base``: relative when below it, else a file URI."""
    path = path.resolve()
    return path.relative_to(base).as_posix() if path.is_relative_to(base) else path.as_uri()


def render_progress_html(
    subject: str, sessions: Sequence[SessionRecord], errors: Sequence[InputError], base: Path
) -> str:
    """The progress page as one HTML string (no external resource); trial reports are linked
    relative to ``base``, the folder the page is written to."""
    from gaitflow.report import CSS, fmt_value

    esc = html.escape
    figs = [r.figures for r in sessions]
    x = [r.date or r.session for r in sessions]
    parts = [
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>",
        f"<title>gaitflow progress: {esc(subject)}</title>",
        f"<style>{CSS}.charts{{display:flex;flex-wrap:wrap;gap:8px}}</style></head><body>",
        f"<h1>Progress: subject {esc(subject)}</h1>",
        f"<p class='meta'>{len(sessions)} session(s) · generated "
        f"{datetime.now(UTC).strftime('%Y-%m-%d %H:%M UTC')} by gaitflow {__version__}</p>",
    ]
    for e in errors:
        parts.append(f"<p class='warn'>left out: {esc(str(e))}</p>")
    header, rows = progress_table(sessions)
    parts.append("<h2>Figures per visit</h2><table><tr>")
    parts.append("".join(f"<th>{esc(h)}</th>" for h in header) + "</tr>")
    for name, nd, vals, change in rows:
        cells = [esc(name), *(fmt_value(v, nd) for v in vals), _signed(change, nd)]
        parts.append("<tr>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    links = [
        " ".join(f"<a href='{esc(_href(p, base))}'>{esc(p.stem)}</a>" for p in rec.reports)
        for rec in sessions
    ]
    parts.append(
        "<tr><td>trial reports</td>" + "".join(f"<td>{c}</td>" for c in links) + "<td></td></tr>"
    )
    parts.append("</table>")
    if sessions:
        parts.append("<h2>Over the visits</h2><div class='charts'>")
        for key, label, unit, per_side, _ in FIGURES:
            parts.append(_chart(key, label, unit, per_side, figs, x))
        parts.append("</div>")
    parts.append(
        "<p class='note'>Each session pools its walking trials: step and stride lengths over "
        "every step and stride; stance as the mean stance time over the mean stride time; "
        "knee ROM and peak flexion as the mean of the trials' (complete gait cycles, else "
        "windows of one stride time); step symmetry is Robinson's index of the left and "
        "right step lengths (0 = symmetric, positive = left longer). Heel strikes and toe "
        "offs are timed to half a frame (about ±17 ms at 30 fps): one stride's stance % is "
        "uncertain by about ±2 points (two events in a stride of about 1.1 s), a session's "
        "mean over many strides by less.</p>"
    )
    parts.append("</body></html>")
    return "\n".join(parts)
