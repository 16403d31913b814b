"""A session folder written by ``gaitflow simulate`` reads back byte-identical (issue 3).

The simulator's own frames are rendered again, independently, from the same seed; the
session folder is written by the same function the ``simulate`` command uses. Recordings
are cut to a few frames (dropped-frame gaps kept) so the test stays fast.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from gaitflow.schemas import RawFrame

from gaitflow.session import SessionReader, iter_raw_frames

sim_session = pytest.importorskip("gaitflow.sim.session")
simulate_cmd = pytest.importorskip("gaitflow.commands.simulate")

N = 3  # frames kept per recording


def _short_session(seed: int):
    from gaitflow.sim import list_trials
    from gaitflow.sim.config import SimConfig

    # Drops are frequent here so the kept frames include an index gap.
    ses = sim_session.simulate_session(list_trials()[0], seed, SimConfig.quick(drop_prob=0.3))
    for rec in ses.recordings.values():
        t = rec.times
        rec.times = type(t)(t.index[:N], t.time_s[:N])
    return ses


def test_simulate_output_reads_back_byte_identical(tmp_path: Path):
    out = tmp_path / "S01"
    simulate_cmd.write_session(_short_session(7), out, log=lambda *_: None)
    reader = SessionReader(out)
    assert reader.recordings() == ["calibration", "static", "walk-01"]
    assert (out / "truth").is_dir()  # ground truth beside the recordings, not in them
    reference = _short_session(7)  # rendered afresh: nothing shared with the writer
    assert reader.camera_doc == reference.camera_json
    gaps = 0
    for name, rec in reference.recordings.items():
        want = [raw for raw, _truth in rec]
        got = list(iter_raw_frames(reader, name, "cam0"))
        assert len(got) == len(want) == N
        for g, w in zip(got, want, strict=True):
            assert isinstance(g, RawFrame)
            assert (g.header.trial, g.header.frame, g.header.capture_ns) == (
                w.header.trial,
                w.header.frame,
                w.header.capture_ns,
            )
            assert g.ir.dtype == w.ir.dtype == np.uint16
            assert g.ir.tobytes() == w.ir.tobytes()
            assert g.depth.tobytes() == w.depth.tobytes()
        gaps += int(np.any(np.diff([g.header.frame for g in got]) > 1))
        assert got[-1].header.last and not any(g.header.last for g in got[:-1])
    assert gaps >= 1  # a dropped frame stayed a gap
    assert reader.skipped.total() == 0
