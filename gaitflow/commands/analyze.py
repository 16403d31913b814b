"""``gaitflow analyze SESSION_DIR --out DIR``: analyse every walking trial of a session folder.

Runs the calibration, the subject model and every walking trial (``walk-NN``) of a session
folder (``../shared/spec/session-folder.md``) through the pipeline of
``deploy/pipeline.yaml`` and writes, per walking trial, ``<trial>.json`` (the results of
``../shared/spec/results.md``, validated against ``gaitflow/data/results.schema.json``) and
``<trial>.html`` (the report, ``gaitflow.report``).

- Default: the stages run as processes on a Zenoh bus (a router on a free 127.0.0.1 port, the
  ``Launcher`` of ``stages/launcher.py``, the ``grab`` stage with ``source=session``), and
  the trial summaries are collected from the bus. Frames are published as fast as the stages
  take them (``rate=max``) with blocking queues, so no frame is dropped.
- ``--inline``: the same cores in one process (``stages/inline.py``), recordings in protocol
  order. Both give identical results (``tests/test_analyze_*.py``).

Bad input: a session without ``calibration/`` or ``static/`` stops with an error naming the
missing folder (no fallback: the floor plane and the subject model cannot be guessed
reliably from a walk, and a wrong floor would silently bias every event). A walking trial in
which the subject is never seen gets a valid, empty result with a warning.

``--store STORE`` files the results in a patient store instead of ``--out``:
``STORE/<subject>/<session>/`` with a ``session.json`` record (``gaitflow.patients``), the
subject being camera.json's ``subject.id`` (or ``--subject``) and the visit's date the
``YYYY-MM-DD`` in the session folder's name (or ``--date``). ``gaitflow progress STORE
SUBJECT`` then shows the subject's figures over the visits. Analysing a session again
replaces its folder's results.

``--export c3d,trc,mot,csv`` also writes each trial as C3D, OpenSim TRC (markers) and MOT
(knee flexion), and a CSV of its gait cycles, beside its JSON
(``gaitflow.exports``, as ``gaitflow convert``); a trial with no frame to export is named in
a warning.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import threading
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from gaitflow.benchutil import format_table
from gaitflow.errors import InputError, StageError
from gaitflow.exports import export_formats, write_exports
from gaitflow.markers import trial_kind
from gaitflow.params import parse_overrides
from gaitflow.progress import add_quiet_flag, progress
from gaitflow.report import side_summary, write_report
from gaitflow.results import empty_results, write_results

NO_SUMMARY = "no labelled frame reached the gait stage: the subject was never seen"


@dataclass
class TrialOutcome:
    """What analyze produced for one walking trial."""

    trial: str
    doc: dict[str, Any]
    json_path: Path | None = None
    html_path: Path | None = None
    warnings: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class StoreTarget:
    """Where ``analyze --store`` files a session: the store's root, and the subject id and
    visit date when not taken from camera.json and the session's name."""

    root: Path
    subject: str | None = None
    date: str | None = None


def _collect(
    summaries: Mapping[str, dict[str, Any]], walks: Iterable[str], session: str
) -> dict[str, dict[str, Any]]:
    """The final (scope == trial) document of every walk; empty ones where none came."""
    out = {}
    for w in walks:
        doc = summaries.get(w)
        if doc is None:
            doc = empty_results(session, w, 30.0, NO_SUMMARY)
        doc = dict(doc)
        doc["session"] = session
        out[w] = doc
    return out


def run_inline_session(
    root: Path, params: Mapping[str, Mapping[str, Any]] | None = None, quiet: bool = True
) -> dict[str, dict[str, Any]]:
    """Every recording of a session folder through the graph in this process.

    Returns trial -> the final results document of each walking trial seen.
    """
    from gaitflow.session import SessionReader, iter_raw_frames, session_stage_params
    from gaitflow.stages.graph import load
    from gaitflow.stages.inline import InlinePipeline

    reader = SessionReader(root)
    params = session_stage_params(reader.camera_doc, params)
    summaries: dict[str, dict[str, Any]] = {}

    def sink(stream: str, msg: Any) -> None:
        if stream == "summary" and msg.results.get("scope") == "trial":
            summaries[msg.header.trial] = msg.results

    pipe = InlinePipeline(load(), params=params, sink=sink)
    names = reader.recordings()
    total = sum(len(reader.rows(n)) for n in names)
    with progress(total=total, desc="analyze", unit="frame", quiet=quiet) as bar:
        for name in names:
            for raw in iter_raw_frames(reader, name):
                pipe.push(raw)
                bar.update(1)
        pipe.finish()
    return summaries


def run_bus_session(
    root: Path,
    params: Mapping[str, Mapping[str, Any]] | None = None,
    quiet: bool = True,
    timeout_s: float = 600.0,
    idle_s: float = 8.0,
) -> dict[str, dict[str, Any]]:
    """Every recording of a session folder through the pipeline as processes on the bus.

    A router and every stage but ``grab`` start first (``Launcher``); once all are ready
    and our subscriber is in place, ``grab`` starts with ``source=session`` and publishes at
    full speed. Returns trial -> the final results document, once every walk has one, the
    pipeline went quiet for ``idle_s`` after the source finished (no message on any per-frame
    stream: a walk in which nobody was seen may give no summary at all), or ``timeout_s``
    passed.
    """
    from gaitflow.bus import Bus
    from gaitflow.bus.keys import stream_selector
    from gaitflow.bus.router import client_config, local_endpoint
    from gaitflow.schemas import TrialSummary, decode
    from gaitflow.session import SessionReader, session_stage_params
    from gaitflow.stages.graph import load
    from gaitflow.stages.launcher import Launcher

    reader = SessionReader(root)
    walks = [n for n in reader.recordings() if trial_kind(n) == "walk"]
    total = sum(len(reader.rows(n)) for n in walks)
    graph = load()
    endpoint = local_endpoint()
    stage_params = session_stage_params(reader.camera_doc, params)
    stage_params.setdefault("grab", {}).update({"source": "session", "path": str(root.resolve())})
    summaries: dict[str, dict[str, Any]] = {}
    lock = threading.Lock()
    last_msg = [time.monotonic()]
    with tempfile.TemporaryDirectory(prefix="gaitflow-analyze-") as tmp:
        cfg = Path(tmp) / "analyze.yaml"
        cfg.write_text(
            yaml.safe_dump(
                {
                    "bus": {"connect": [endpoint], "site": graph.site},
                    "params": stage_params,
                    "runtime": {"queue_policy": "block", "rate": "max"},
                }
            )
        )
        others = [n.name for n in graph.nodes if n.inputs]
        sources = [n.name for n in graph.nodes if not n.inputs]
        la = Launcher(graph, stages=others, endpoint=endpoint, config=cfg, echo=False)
        src: Launcher | None = None
        bus = None
        bar = progress(total=total, desc="analyze (bus)", unit="frame", quiet=quiet)
        try:
            la.start()
            la.wait_ready(60.0)
            bus = Bus(client_config(endpoint, site=graph.site))

            def on_summary(key: str, payload: bytes) -> None:
                msg = decode(TrialSummary, payload)
                with lock:
                    last_msg[0] = time.monotonic()
                    if msg.results.get("scope") == "trial":
                        summaries[msg.header.trial] = msg.results

            def on_busy(key: str, payload: bytes) -> None:
                with lock:
                    last_msg[0] = time.monotonic()

            def on_gait(key: str, payload: bytes) -> None:
                with lock:
                    last_msg[0] = time.monotonic()
                bar.update(1)

            bus.subscribe(stream_selector(graph.site, "summary"), on_summary)
            bus.subscribe(stream_selector(graph.site, "gait"), on_gait)
            # small per-frame streams upstream of gait: they show the pipeline is still busy
            for stream in ("markers", "calstatus", "model", "labelled"):
                bus.subscribe(stream_selector(graph.site, stream), on_busy)
            time.sleep(0.3)  # let the subscriptions reach the router before frames flow
            src = Launcher(
                graph, stages=sources, endpoint=endpoint, router=False, config=cfg, echo=False
            )
            src.start()
            deadline = time.monotonic() + timeout_s
            while time.monotonic() < deadline:
                with lock:
                    if all(w in summaries for w in walks):
                        break
                    quiet_for = time.monotonic() - last_msg[0]
                if src.wait_sources(0.2) and quiet_for > idle_s:
                    break
                failed = [r for r in la.status() if r["state"] == "failed"]
                if failed:
                    raise StageError(failed[0]["name"], "stage failed during analyze")
        finally:
            bar.close()
            if bus is not None:
                bus.close()
            if src is not None:
                src.stop()
            la.stop()
    return summaries


def analyze_session(
    root: str | Path,
    out: str | Path | None,
    inline: bool = False,
    params: Mapping[str, Mapping[str, Any]] | None = None,
    quiet: bool = True,
    report: bool = True,
    store: StoreTarget | None = None,
) -> list[TrialOutcome]:
    """Analyse a session folder; write ``<trial>.json`` and ``<trial>.html`` into ``out``.

    With ``store``, ``out`` defaults to the session's folder in the patient store
    (``STORE/<subject>/<session>/``, :mod:`gaitflow.patients`), and a ``session.json``
    record is written beside the results. The subject and the session name are checked
    before anything is run.
    """
    from gaitflow.patients import session_date, session_dir, subject_of, write_manifest
    from gaitflow.session import SessionReader

    root = Path(root)
    reader = SessionReader(root)
    reader.require()  # InputError naming calibration/ or static/ if missing
    name = root.resolve().name
    if store is not None:
        subject = subject_of(reader.camera_doc, store.subject)
        visit = session_date(name, store.date)
        out = out if out is not None else session_dir(store.root, subject, name)
    if out is None:
        raise InputError("gaitflow analyze", "give --out DIR or --store STORE")
    walks = [n for n in reader.recordings() if trial_kind(n) == "walk"]
    if not walks:
        raise InputError(root, "no walking recording (walk-NN/) in the session folder")
    run = run_inline_session if inline else run_bus_session
    summaries = run(root, params, quiet)
    docs = _collect(summaries, walks, name)
    outdir = Path(out)
    outdir.mkdir(parents=True, exist_ok=True)
    outcomes = []
    for w in walks:
        doc = docs[w]
        jp = write_results(doc, outdir / f"{w}.json")
        hp = write_report(doc, outdir / f"{w}.html") if report else None
        outcomes.append(TrialOutcome(w, doc, jp, hp, list(doc.get("warnings", []))))
    if store is not None:
        write_manifest(outdir, subject, name, visit, walks)
    return outcomes


def summary_table(outcomes: Iterable[TrialOutcome], title: str = "gait summary") -> str:
    """Per trial and side: steps, stride length, cadence, speed, stance/swing %, knee ROM."""
    rows = []
    for o in outcomes:
        st = o.doc["spatiotemporal"]
        summ = side_summary(o.doc)
        for s in ("L", "R"):
            d = summ[s]
            rows.append(
                [
                    o.trial,
                    s,
                    int(d["steps"]),
                    d["stride_length_mm"],
                    st.get("cadence_steps_per_min") or float("nan"),
                    st.get("speed_m_s") or float("nan"),
                    d["stance_pct"],
                    d["swing_pct"],
                    d["knee_rom_deg"],
                    f"{int(d['cycles'])}"
                    + (f" ({int(d['rom_windows'])}w)" if d["rom_windows"] else ""),
                ]
            )
    cols = [
        "trial",
        "side",
        "steps",
        "stride mm",
        "cadence/min",
        "speed m/s",
        "stance %",
        "swing %",
        "knee ROM deg",
        "knee cycles",
    ]
    note = (
        "knee ROM: mean over the gait cycles whose knee angle is known over >= 90 % of the "
        "cycle ('knee cycles'); without one, over windows of one stride time known as well "
        "('(2w)': two windows); '-' = neither"
    )
    return format_table(title, cols, rows) + "\n" + note


def run(args: argparse.Namespace) -> int:
    store = StoreTarget(args.store, args.subject, args.date) if args.store else None
    if store is not None and args.out:
        raise InputError("--out/--store", "give one: --store files the results in the store")
    if store is None and (args.subject or args.date):
        raise InputError("--subject/--date", "they file a session in a store: give --store too")
    outcomes = analyze_session(
        args.session_dir,
        args.out,
        inline=args.inline,
        params=parse_overrides(args.param or []),
        quiet=args.quiet,
        store=store,
    )
    print(summary_table(outcomes, f"gaitflow analyze {args.session_dir}"))
    for o in outcomes:
        for w in o.warnings:
            print(f"warning: {o.trial}: {w}", file=sys.stderr)
        print(f"{o.trial}: {o.json_path}  {o.html_path}")
        if args.export:
            try:
                paths, _ = write_exports(
                    o.doc, o.json_path.parent, o.trial, args.export, source=o.json_path
                )
            except InputError as exc:
                # a trial without frames (the subject never in view) has nothing to export
                print(f"warning: {o.trial}: not exported: {exc}", file=sys.stderr)
                continue
            print(f"{o.trial}: " + "  ".join(str(p) for p in paths))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "analyze",
        help="analyse every walking trial of a session folder (JSON results + HTML report)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Examples:\n  gaitflow analyze sessions/S01 --out out/S01\n"
        "  gaitflow analyze sessions/S01-2026-11-21 --store clinic\n"
        "  gaitflow progress clinic S01\n"
        "  gaitflow analyze sessions/S01 --out out/S01 --inline --param gait.xi=0.33",
    )
    p.add_argument("session_dir", type=Path, help="session folder (camera.json, walk-01/, ...)")
    p.add_argument("--out", type=Path, help="output folder (required unless --store)")
    p.add_argument(
        "--store",
        type=Path,
        help="patient store: file the results under STORE/<subject>/<session>/ "
        "(see gaitflow progress)",
    )
    p.add_argument("--subject", help="with --store: subject id (default: camera.json subject.id)")
    p.add_argument(
        "--date", help="with --store: the visit's date YYYY-MM-DD (default: from the session name)"
    )
    p.add_argument("--inline", action="store_true", help="run the stages in this process")
    p.add_argument(
        "--export",
        type=export_formats,
        metavar="c3d,trc,mot,csv",
        help="also write each trial as C3D, OpenSim TRC / MOT and/or CSV (as gaitflow convert)",
    )
    p.add_argument(
        "--param",
        action="append",
        metavar="STAGE.NAME=VALUE",
        help="override a stage parameter (repeatable), e.g. gait.xi=0.33",
    )
    add_quiet_flag(p)
    p.set_defaults(func=run)
