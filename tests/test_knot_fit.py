"""The writer's least-squares point values (ffcomp.gcode.knot_fit) against a dense least-squares solve."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from ffcomp.gcode.knot_fit import fit_knots


def _interp(k, V, n):
    return np.stack([np.interp(np.arange(n), k, V[:, c]) for c in range(V.shape[1])], 1)


def _dense_lstsq(P, k, fixed):
    """The same fit from the dense design matrix of the hat functions (an independent representation)."""
    m = len(k)
    s = np.arange(k[0], k[-1] + 1)
    B = np.stack([np.interp(s, k, np.eye(m)[i]) for i in range(m)], 1)  # hat function i at every sample
    fx = fixed.copy()
    fx[0] = fx[-1] = True
    free = ~fx
    rhs = P[s] - B[:, fx] @ P[k][fx]
    V = P[k].astype(float).copy()
    if free.any():
        V[free] = np.linalg.lstsq(B[:, free], rhs, rcond=None)[0]
    return V


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(2, 12), st.integers(20, 200))
def test_fit_equals_the_dense_least_squares(seed, m, n):
    rng = np.random.default_rng(seed)
    P = np.cumsum(rng.normal(size=(n, 3)), 0)
    k = np.unique(np.r_[0, n - 1, rng.choice(n, size=min(m, n), replace=False)])
    fixed = rng.random(len(k)) < 0.3
    V = fit_knots(P, k, fixed)
    ref = _dense_lstsq(P, k, fixed)
    np.testing.assert_allclose(V, ref, atol=1e-8 * (1 + np.abs(ref).max()))
    fx = fixed.copy()
    fx[0] = fx[-1] = True
    assert np.array_equal(V[fx], P[k][fx])  # fixed knots keep their samples exactly


def test_parabola_rms_error_falls_as_predicted():
    """On a parabola the chord's error is c s (1 - s): RMS sqrt(1/30) c; the fit's error is zero-mean,
    RMS about sqrt(1/180) c in the interior (the fixed ends add a little)."""
    n, step = 2001, 100
    t = np.linspace(0.0, 1.0, n)
    P = (t**2)[:, None]
    k = np.arange(0, n, step)
    c = (step / (n - 1)) ** 2  # second difference over one segment: the chord's bow is c s (1 - s)
    chord = _interp(k, P[k], n) - P
    fixed = np.zeros(len(k), bool)
    fit = _interp(k, fit_knots(P, k, fixed), n) - P
    assert abs(np.sqrt(np.mean(chord**2)) / c - np.sqrt(1 / 30)) < 2e-3
    inner = slice(3 * step, n - 3 * step)
    assert abs(np.sqrt(np.mean(fit[inner] ** 2)) / c - np.sqrt(1 / 180)) < 5e-3
    assert np.sqrt(np.mean(fit**2)) < 0.5 * np.sqrt(np.mean(chord**2))


def test_max_shift_bounds_every_knot():
    rng = np.random.default_rng(1)
    P = np.cumsum(rng.normal(size=(300, 2)), 0)
    k = np.arange(0, 300, 30)
    k = np.r_[k, 299]
    V = fit_knots(P, k, np.zeros(len(k), bool), max_shift=0.05)
    assert np.max(np.abs(V - P[k])) <= 0.05 + 1e-12
