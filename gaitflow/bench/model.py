"""``gaitflow bench model``: the subject model against the simulator's static truth.

For each bundled trial (or ``--trials``) the calibration and static parts of a simulated
session (quick protocol) run through calibrate, clean, detect, locate and model, with the
detector's three splitters of merged blobs off and on (``detect.SPLITTERS``, on by
default). Each marker of the published model is compared with
the truth's median position over the static frames, in the forward (a) and height (h)
floor axes only: a marker's measured depth is noisy by 50-100 mm, so (a, h) tells a wrong
blob from a right one. Truth is read here only, never by a stage.

Figures per trial and setting: near-side markers within ``OK_MM`` of their truth (of 10),
far-side ones, markers on a wrong blob (further than ``OK_MM``), and the worst error of the
right ones (mm).
"""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np

from gaitflow.benchutil import add_json_flag, emit, format_table
from gaitflow.markers import MARKER_NAMES

OK_MM = 30.0


def check_trial(trial: str, seed: int, split: bool, variant: str = "base") -> dict[str, Any]:
    """Run calibration + static of one simulated trial (simulator set-up ``variant``), with
    every splitter of merged blobs on (``split``) or off; score the model (see module doc)."""
    from gaitflow.sim import simulate_session
    from gaitflow.sim.variants import sim_config
    from gaitflow.stages.detect import SPLITTERS
    from gaitflow.stages.graph import load
    from gaitflow.stages.inline import InlinePipeline
    from gaitflow.stages.model import FloorFrame

    ses = simulate_session(trial, seed, sim_config(variant))
    got: dict[str, list[Any]] = {"model": [], "calibration": []}

    def sink(stream: str, msg: Any) -> None:
        if stream in got:
            got[stream].append(msg)

    stages = ["calibrate", "clean", "detect", "locate", "model"]
    pipe = InlinePipeline(load(), stages, {"detect": dict.fromkeys(SPLITTERS, split)}, sink)
    truth = []
    for rec in ses.recordings.values():
        if rec.kind not in ("calibration", "static"):
            continue
        for k in range(len(rec)):
            raw, tr = rec.frame(k, last=k == len(rec) - 1)
            if rec.kind == "static":
                truth.append(np.asarray(tr.position, dtype=np.float64))
            pipe.push(raw)
    pipe.finish()
    if not got["model"] or not truth:
        raise RuntimeError(f"bench model: no subject model for {trial}")
    m = got["model"][-1]
    ff = FloorFrame.from_record(got["calibration"][-1] if got["calibration"] else None, 800.0)
    ref = ff.to_floor(np.asarray(m.reference, dtype=np.float64))
    tru = ff.to_floor(np.median(np.stack(truth), axis=0))
    err = np.hypot(ref[:, 0] - tru[:, 0], ref[:, 2] - tru[:, 2])
    found = np.isfinite(err)
    right = found & (err <= OK_MM)
    near = np.array([n.startswith(m.near_side) for n in MARKER_NAMES])
    return {
        "near_ok": int((right & near).sum()),
        "far_ok": int((right & ~near).sum()),
        "wrong": [MARKER_NAMES[i] for i in np.flatnonzero(found & ~right)],
        "worst_ok_mm": float(err[right].max()) if right.any() else float("nan"),
    }


def run(args: argparse.Namespace) -> int:
    from gaitflow.sim import list_trials
    from gaitflow.sim.variants import variant_changes

    variant_changes(args.variant)  # an unknown name fails before any trial runs
    rows = []
    per: dict[str, Any] = {}
    for trial in args.trials or list_trials():
        for split in (False, True):
            r = check_trial(trial, args.seed, split, args.variant)
            per[f"{trial}|splitters={split}"] = r
            rows.append(
                [trial, split, r["near_ok"], r["far_ok"], len(r["wrong"]), r["worst_ok_mm"]]
            )
    cols = ["trial", "splitters", "near ok /10", "far ok", "wrong", "worst ok mm"]
    title = f"subject model, variant {args.variant}"
    figures = {"seed": args.seed, "variant": args.variant, "trials": per}
    emit(args, figures, [format_table(title, cols, rows)])
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "model",
        help="subject model vs the simulator's static truth, detect's splitters off and on",
        description=__doc__,
        epilog="Example: gaitflow bench model --trials bz_HC002D_straight_HC002D06 --json",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--trials", nargs="*", default=None, help="bundled trial ids (default: all)")
    p.add_argument("--seed", type=int, default=0, help="simulator seed")
    p.add_argument(
        "--variant",
        default="base",
        metavar="NAME[+NAME...]",
        help="simulated set-up, as for `gaitflow bench gait --variant` (default base)",
    )
    add_json_flag(p)
    p.set_defaults(func=run)
