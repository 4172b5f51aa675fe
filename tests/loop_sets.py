"""Small hidden-effect data sets for the model-loop tests (paper-frame delta: arm 330, radius 155,
H_ez 25 mm; 2 % complex noise; coherence as from 50 averages with no ``averages`` header key)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ffcomp.loop.identify import identify
from ffcomp.measure.virtual import measurement_plan, virtual_measurements
from ffcomp.profile import load_profile

ROOT = Path(__file__).resolve().parents[1]
TRUTH = ROOT / "samples" / "profiles" / "other_delta_truth.toml"
PLUGIN = ROOT / "docs" / "effects_example_motor_mount.py"
NOISE = 0.02


def truth():
    return load_profile(TRUTH)


def make_set(effects=(), *, n_freq: int = 80, heights=(30.0, 130.0), seed: int = 1, averages: int = 50,
             fmax: float = 400.0):
    """Measurements of the truth profile with hidden ``effects`` (the default plan at ``heights``)."""
    p = truth()
    plan = measurement_plan(p, heights_mm=heights)
    return virtual_measurements(p, effects, freq_hz=np.geomspace(5.0, fmax, n_freq), noise=NOISE, seed=seed,
                                plan=plan, averages=averages, averages_key=False)


def identified(ms):
    """The truth's geometry with the dynamics from the two identification sweeps in ``ms``."""
    p = truth()
    c = next(m for m in ms if m.kind == "carriage")
    a = next(m for m in ms if m.kind == "assembled" and m.input == "z" and m.output == "qA")
    res = identify(c, a, p.dynamics.m_n, p.dynamics.m_f)
    return res, res.apply_to(p).with_(name="identified")
