"""Virtual FRF measurements through the nonlinear simulator agree with the LPV model."""

import numpy as np
import pytest

from ffcomp.measure.frf_file import load_frf, save_frf
from ffcomp.model.lpv import AXES, frequency_response
from ffcomp.model.submodels import g_qd
from ffcomp.pipeline.model_flow import frame_for
from ffcomp.sim.measure import SweepSpec, h1_estimate, periodic_chirp, virtual_frf
from ffcomp.sim.plant import DeltaPlant

SPEC = SweepSpec(f_lo_hz=10.0, f_hi_hz=200.0, periods=2)


@pytest.fixture(scope="module")
def plant(model):
    return DeltaPlant(model)


def _near_peak(H_model, freq_hz, width=0.25):
    k = int(np.argmax(np.abs(H_model)))
    return np.abs(freq_hz - freq_hz[k]) <= width * freq_hz[k]


@pytest.mark.parametrize("at,inp,out", [((0, 0, 30), "z", "qA"), ((-100, 0, 30), "x", "x"),
                                        ((0, -100, 30), "y", "y")])
def test_h1_matches_model_near_resonance(plant, at, inp, out):
    meas = virtual_frf(plant, at, inp, out, spec=SPEC)
    H = frequency_response(plant.model, np.array([at]) * 1e-3, meas.freq_hz,
                           frame=frame_for(inp, out))[0, AXES[out], AXES[inp]]
    rel = np.abs(meas.H - H) / np.abs(H)
    near = _near_peak(H, meas.freq_hz)
    assert rel[near].max() < 0.02  # within 2 % around the resonance
    assert np.median(rel) < 0.02
    assert meas.coherence.min() > 0.99
    assert meas.kind == "assembled" and meas.input == inp and meas.output == out


def test_carriage_sweep_is_g_qd(plant, profile, tmp_path):
    meas = virtual_frf(plant, (0, 0, 30), "qA", "qA", kind="carriage", spec=SPEC)
    d = profile.dynamics
    H = g_qd(2j * np.pi * meas.freq_hz, d.m[0], d.c[0], d.b[0], d.k[0], d.d0[0], d.d1[0], d.d2[0])
    assert (np.abs(meas.H - H) / np.abs(H)).max() < 0.01
    path = tmp_path / "carriage.csv"
    save_frf(meas, path)
    back = load_frf(path)
    assert back.kind == "carriage" and back.input == "qA"
    assert np.allclose(back.H, meas.H, rtol=1e-8)
    with pytest.raises(ValueError):
        virtual_frf(plant, (0, 0, 30), "z", "qA", kind="carriage", spec=SPEC)


def test_noise_lowers_coherence(plant):
    spec = SweepSpec(f_lo_hz=10.0, f_hi_hz=200.0, periods=3, noise_um=0.5, seed=3)
    meas = virtual_frf(plant, (0, 0, 30), "z", "z", spec=spec)
    assert meas.coherence.min() < 0.9  # weak bins
    assert meas.coherence.max() > 0.99  # the resonance stands out


def test_periodic_chirp_and_h1_estimator():
    spec = SweepSpec(f_lo_hz=5.0, f_hi_hz=100.0, period_s=0.5, periods=2, rate_hz=1000.0)
    t, x = periodic_chirp(spec)
    n = int(spec.period_s * spec.rate_hz)
    assert np.allclose(x[:n], x[n:2 * n], atol=1e-9)  # periodic
    assert abs(x[0]) < 1e-12
    # a pure 3-sample delay has H = exp(-j w 3 / fs) exactly at the bins
    y = np.roll(x, 3)
    f, H, coh = h1_estimate(x[n:], y[n:], spec.rate_hz, n)
    band = (f >= 5) & (f <= 100)
    assert np.allclose(H[band], np.exp(-2j * np.pi * f[band] * 3 / spec.rate_hz), atol=1e-9)
    assert coh[band].min() > 1 - 1e-9
