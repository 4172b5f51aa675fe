"""Two-sweep identification: synthetic sweeps from known parameters, recovered within tolerance."""

from dataclasses import replace

import numpy as np
import pytest

from ffcomp.errors import MeasurementError, SolverError
from ffcomp.loop.identify import fit_eq22, identify, sk_fit
from ffcomp.measure.synthetic import identification_sweeps

TRUE = {"m": 0.177, "c": 5.87, "b": 18.0, "k": 9.44e4, "b_nt": 27.9}


@pytest.mark.parametrize("seed", range(4))
def test_round_trip_table_one_with_two_percent_noise(profile, seed):
    carriage, assembled = identification_sweeps(profile, noise=0.02, seed=seed)
    r = identify(carriage, assembled, m_n=0.156, m_f=0.032)
    for k, v in TRUE.items():
        assert getattr(r, k) == pytest.approx(v, rel=0.03), k
    assert r.d0 == pytest.approx(1.43e5, rel=0.01)
    assert r.d1 == pytest.approx(-212.1, rel=0.02)
    assert r.d2 == pytest.approx(36.2, rel=0.02)
    # the fits leave only the noise: complex residual ~ 2 %, R^2 near one
    assert 0.015 < r.carriage_fit.residual < 0.025
    assert r.assembled_fit.r2_mag > 0.99 and r.assembled_fit.r2_phase > 0.99


def test_noise_free_recovery_is_exact(profile):
    c, a = identification_sweeps(profile, noise=0.0)
    r = identify(c, a, 0.156, 0.032)
    for k, v in TRUE.items():
        assert getattr(r, k) == pytest.approx(v, rel=1e-6), k


def test_other_printer_recovered(profile):
    """A held-out printer with other parameters (and d1 > 0: no right-half-plane zero)."""
    dyn = replace(profile.dynamics, m=(0.25,) * 3, c=(9.0,) * 3, b=(12.0,) * 3, k=(1.5e5,) * 3,
                  d0=(4.0e5,) * 3, d1=(150.0,) * 3, d2=(80.0,) * 3, m_n=0.3, m_f=0.05, b_nt=40.0)
    prof = replace(profile, dynamics=dyn)
    c, a = identification_sweeps(prof, noise=0.02, seed=7)
    r = identify(c, a, 0.3, 0.05)
    for k, v in {"m": 0.25, "c": 9.0, "b": 12.0, "k": 1.5e5, "b_nt": 40.0, "d1": 150.0}.items():
        assert getattr(r, k) == pytest.approx(v, rel=0.05), k


def test_sk_linear_fit_recovers_poles_exactly(profile):
    c, _ = identification_sweeps(profile, noise=0.0)
    num, den = sk_fit(c.freq_hz, c.H)
    w = np.sort(np.abs(np.roots(den)))
    np.testing.assert_allclose(w[::2], [np.sqrt(1.43e5), np.sqrt(9.44e4 / 0.177)], rtol=1e-6)


def test_single_sweep_fit(profile):
    c, _ = identification_sweeps(profile, noise=0.01, seed=3)
    f = fit_eq22(c)
    assert f.wn == pytest.approx(np.sqrt(9.44e4 / 0.177), rel=0.005)
    assert f.d0 == pytest.approx(1.43e5, rel=0.01)


def test_swapped_sweeps_are_refused(profile):
    c, a = identification_sweeps(profile, noise=0.0)
    with pytest.raises(SolverError, match="not below"):
        identify(a, c, 0.156, 0.032)


def test_off_centre_and_short_sweeps_are_refused(profile):
    c, a = identification_sweeps(profile, noise=0.0)
    with pytest.raises(MeasurementError, match="bed centre"):
        identify(c, replace(a, position_mm=np.array([50.0, 0, 30])), 0.156, 0.032)
    short = replace(c, freq_hz=c.freq_hz[:5], H=c.H[:5], coherence=c.coherence[:5])
    with pytest.raises(MeasurementError, match="at least 12"):
        identify(short, a, 0.156, 0.032)
    with pytest.raises(ValueError, match="m_n"):
        identify(c, a, -1.0, 0.032)


def test_linear_grid_and_log_density_weights():
    """A linear frequency grid (most points above the resonances) identifies as well as a log grid."""
    from ffcomp.loop.identify import log_density_weights
    from ffcomp.measure.synthetic import identification_sweeps
    from ffcomp.profile import load_profile

    w = log_density_weights(np.geomspace(5, 400, 50))
    assert np.allclose(w, 1.0)
    f = np.arange(5.0, 400.5, 2.0)
    w = log_density_weights(f)
    assert w[0] > 10 * w[-1] and np.mean(w) == pytest.approx(1.0)
    truth = load_profile("samples/profiles/other_delta_truth.toml")
    c, a = identification_sweeps(truth, f, noise=0.02, seed=4)
    res = identify(c, a, truth.dynamics.m_n, truth.dynamics.m_f)
    for key in ("m", "k", "c", "b"):
        assert getattr(res, key) == pytest.approx(getattr(truth.dynamics, key)[0], rel=0.05), key
