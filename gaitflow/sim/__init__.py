"""Kinect v2 simulator driven by real walking trials (see docs/readme/simulator.md).

``simulate_session(trial, seed, config)`` builds a session (calibration, static, walks) whose
recordings yield ``(RawFrame, GroundTruth)`` pairs; ``list_trials()`` names the bundled
trials.
"""

from __future__ import annotations

from gaitflow.sim.body import list_trials
from gaitflow.sim.config import SimConfig

__all__ = ["SimConfig", "list_trials", "simulate_session"]


def simulate_session(*args, **kwargs):
    """See :func:`gaitflow.sim.session.simulate_session`."""
    from gaitflow.sim.session import simulate_session as _sim

    return _sim(*args, **kwargs)
