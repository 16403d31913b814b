"""``gaitflow demo``: simulate a session from a bundled real trial, analyse it, show the result.

The Kinect v2 simulator (``gaitflow.sim``) renders a short session from one of the bundled
real walking trials: a calibration, a static pose and a walk across the field of view and
back. Every recording goes through the whole pipeline (calibrate, clean, detect, locate,
model, label, gait) and the walk's results are written as ``walk-01.json`` (the results of
``shared/spec/results.md``) and ``walk-01.html`` (the report). A summary table per side is
printed with the path of the report.

By default the stages run in this process (``stages/inline.py``) while frames are rendered
by a small pool of worker processes, which keeps the demo around a minute on two cores.
``--bus`` instead writes the simulated session folder to ``OUT/session`` and runs
``gaitflow analyze`` on it with every stage as a process on a local Zenoh bus. Ground truth
is never given to the pipeline.
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

from gaitflow.progress import add_quiet_flag, progress

DEFAULT_TRIAL = "btk_PiG_Motion-FlatFoot-Full"
_WORKER: dict[str, Any] = {}


def _init_worker(trial: str, seed: int, config: Any) -> None:
    from gaitflow.sim import simulate_session

    _WORKER["ses"] = simulate_session(trial, seed, config)


def _render(job: tuple[str, int, bool]) -> Any:
    name, k, last = job
    raw, _truth = _WORKER["ses"].recordings[name].frame(k, last=last)
    return raw  # ground truth stays in the worker: the pipeline never sees it


def _render_with_truth(job: tuple[str, int, bool]) -> Any:
    name, k, last = job
    return _WORKER["ses"].recordings[name].frame(k, last=last)  # (raw, truth): for scoring


def rendered_frames(
    trial: str,
    seed: int,
    quick: bool,
    jobs: int,
    with_truth: bool = False,
    ses: Any = None,
) -> tuple[list[tuple[str, int]], Iterator[Any]]:
    """(recording, frame count) in protocol order, and the RawFrames of all of them in order.

    With ``jobs > 1`` frames are rendered by that many worker processes (the simulator is
    deterministic per seed, recording and frame, so the frames are identical). With
    ``with_truth`` the items are ``(RawFrame, GroundTruth)`` pairs (benchmarks only).
    ``ses`` is the session already simulated (any configuration, e.g. a variant of
    :mod:`gaitflow.sim.variants`; not built again here), else it is built from ``quick``;
    the workers build theirs from its configuration, so both render the same recordings.
    """
    from gaitflow.sim import simulate_session
    from gaitflow.sim.variants import sim_config

    if ses is None:
        ses = simulate_session(trial, seed, sim_config("base", quick))
    plan = [(name, len(rec)) for name, rec in ses.recordings.items()]
    work = [(name, k, k == n - 1) for name, n in plan for k in range(n)]

    def serial() -> Iterator[Any]:
        for name, k, last in work:
            pair = ses.recordings[name].frame(k, last=last)
            yield pair if with_truth else pair[0]

    def pooled() -> Iterator[Any]:
        with ProcessPoolExecutor(
            jobs, initializer=_init_worker, initargs=(trial, seed, ses.config)
        ) as ex:
            yield from ex.map(_render_with_truth if with_truth else _render, work, chunksize=4)

    return plan, (pooled() if jobs > 1 else serial())


def run(args: argparse.Namespace) -> int:
    from gaitflow.commands.analyze import TrialOutcome, analyze_session, summary_table
    from gaitflow.report import write_report
    from gaitflow.results import write_results

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    from gaitflow.sim import simulate_session
    from gaitflow.sim.variants import sim_config

    ses = simulate_session(args.trial, args.seed, sim_config("base", not args.full))
    if args.bus:
        from gaitflow.commands.simulate import write_session

        session_dir = out / "session"
        print(f"gaitflow demo: simulating {args.trial} into {session_dir}")
        write_session(ses, session_dir, None)
        outcomes = analyze_session(session_dir, out, inline=False, quiet=args.quiet)
    else:
        from gaitflow.stages.graph import load
        from gaitflow.stages.inline import InlinePipeline

        docs: dict[str, dict[str, Any]] = {}

        def sink(stream: str, msg: Any) -> None:
            if stream == "summary" and msg.results.get("scope") == "trial":
                docs[msg.header.trial] = msg.results

        from gaitflow.session import session_stage_params

        plan, frames = rendered_frames(args.trial, args.seed, not args.full, args.jobs, ses=ses)
        total = sum(n for _, n in plan)
        print(
            f"gaitflow demo: simulating {args.trial} (seed {args.seed}): "
            + ", ".join(f"{name} {n} frames" for name, n in plan)
        )
        pipe = InlinePipeline(load(), params=session_stage_params(ses.camera_json), sink=sink)
        with progress(total=total, desc="demo", unit="frame", quiet=args.quiet) as bar:
            for raw in frames:
                pipe.push(raw)
                bar.update(1)
            pipe.finish()
        outcomes = []
        for name, _ in plan:
            if not name.startswith("walk-"):
                continue
            doc = docs.get(name)
            if doc is None:
                from gaitflow.results import empty_results

                doc = empty_results("demo", name, 30.0, "no trial summary came out")
            doc = {**doc, "session": f"demo-{args.trial}"}
            jp = write_results(doc, out / f"{name}.json")
            hp = write_report(doc, out / f"{name}.html")
            outcomes.append(TrialOutcome(name, doc, jp, hp, list(doc.get("warnings", []))))
    dt = time.perf_counter() - t0
    print(summary_table(outcomes, f"gaitflow demo: {args.trial} ({dt:.0f} s)"))
    for o in outcomes:
        for w in o.warnings:
            print(f"warning: {o.trial}: {w}")
        print(f"report: {o.html_path.resolve() if o.html_path else '-'}")
        print(f"results: {o.json_path.resolve() if o.json_path else '-'}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    from gaitflow.sim import list_trials

    p = sub.add_parser(
        "demo",
        help="simulate a session from a bundled real trial, analyse it, print a summary",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Examples:\n  gaitflow demo\n  gaitflow demo --trial btk_PiG_Motion3_FF --bus",
    )
    trials = list_trials()
    p.add_argument(
        "--trial",
        default=DEFAULT_TRIAL,
        choices=trials,
        metavar="TRIAL",
        help=f"bundled trial (default {DEFAULT_TRIAL}; one of {', '.join(trials)})",
    )
    p.add_argument("--seed", type=int, default=0, help="simulator seed")
    p.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    p.add_argument("--bus", action="store_true", help="run the stages as processes on a bus")
    p.add_argument("--full", action="store_true", help="full-length calibration and static")
    p.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1), help="render processes")
    add_quiet_flag(p)
    p.set_defaults(func=run)
