"""``gaitflow progress STORE SUBJECT``: a subject's gait over the course of therapy.

Reads every session that ``gaitflow analyze SESSION --store STORE`` stored for the subject
(``gaitflow.patients``), prints a table with one column per visit and one row per figure
(speed, cadence, stride and step length, stance %, knee range of motion and peak flexion
per side, step symmetry) and the change from the first visit to the last, and writes
an HTML page with a chart per figure over the visits and links to every trial's report
(``STORE/SUBJECT/progress.html`` unless ``--html``), and with ``--csv PATH`` the table
for a spreadsheet (one row per visit). A session or trial file that cannot be
read is named on stderr, counted and left out; the rest is shown (exit 0).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def run(args: argparse.Namespace) -> int:
    from gaitflow.patients import (
        format_progress,
        load_subject,
        render_progress_html,
        write_progress_csv,
    )

    sessions, errors = load_subject(args.store, args.subject)
    print(format_progress(args.subject, sessions))
    for e in errors:
        print(f"warning: left out: {e}", file=sys.stderr)
    if errors:
        print(f"{len(errors)} file(s) left out", file=sys.stderr)
    out = args.html or Path(args.store) / args.subject / "progress.html"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(render_progress_html(args.subject, sessions, errors, out.parent.resolve()))
    print(f"progress page: {out}")
    if args.csv:
        print(f"progress table: {write_progress_csv(sessions, args.csv)}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "progress",
        help="a subject's gait figures over the stored sessions (table + HTML page)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Example:\n  gaitflow analyze sessions/S01-2026-11-21 --store clinic\n"
        "  gaitflow progress clinic S01",
    )
    p.add_argument("store", type=Path, help="the store given to gaitflow analyze --store")
    p.add_argument("subject", help="subject id (camera.json subject.id, or --subject)")
    p.add_argument("--html", type=Path, help="where to write the page")
    p.add_argument("--csv", type=Path, help="also write the table, one row per visit")
    p.set_defaults(func=run)
