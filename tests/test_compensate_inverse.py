"""The inverse on synthetic paths, judged by the LPV model (the nonlinear simulator judges in test_bench)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from trajectories import square, trapezoid_path

from ffcomp.compensate.inverse import InverseConfig, _derivatives, invert
from ffcomp.compensate.predict import predict_lpv
from ffcomp.compensate.stream_inverse import StreamingInverse
from ffcomp.kinematics import inverse, jacobian


def _rms_um(model, X, q, q_cmd):
    y = predict_lpv(model, q_cmd, X, 1e-3)
    e = np.einsum("nij,nj->ni", jacobian(model.geometry, X), y - q)
    return float(np.sqrt(np.mean(np.sum(e**2, 1)))) * 1e6


@pytest.fixture(scope="module")
def paths(model):
    out = {}
    for name, pts in (("centre", square(0, 0)), ("off100", square(100, 0, side=50))):
        X = trapezoid_path(pts)
        out[name] = (X, inverse(model.geometry, X))
    return out


@pytest.mark.parametrize("where", ["centre", "off100"])
def test_lpv_removes_over_95_percent(model, paths, where):
    X, q = paths[where]
    before = _rms_um(model, X, q, q)
    r = invert(model, q, X, 1e-3)
    after = _rms_um(model, X, q, r.q_cmd)
    assert before > 200  # 10,000 mm/s^2 corners ring and lag by hundreds of micrometres
    assert after < 0.05 * before, (before, after)
    # bounded and smooth: the correction stays below a millimetre, changes no more abruptly than the
    # plan itself (second differences), and dies out when the plan comes to rest (no seam ringing)
    d = r.q_cmd - q
    assert np.max(np.abs(d)) < 1e-3
    assert np.max(np.abs(np.diff(d, 2, axis=0))) < np.max(np.abs(np.diff(q, 2, axis=0)))
    assert np.max(np.abs(d[-20:])) < 0.01 * np.max(np.abs(d))


def test_lpv_beats_centre_frozen_lti_far_from_centre(model, paths):
    X, q = paths["off100"]
    lpv = _rms_um(model, X, q, invert(model, q, X, 1e-3).q_cmd)
    lti = _rms_um(model, X, q, invert(model, q, X, 1e-3, InverseConfig(method="lti-centre")).q_cmd)
    assert lpv < 0.2 * lti, (lpv, lti)


@pytest.mark.parametrize("method", ["lpv-basis", "window-centre", "lpv-exact"])
def test_variants_all_compensate(model, paths, method):
    X, q = paths["off100"]
    before = _rms_um(model, X, q, q)
    after = _rms_um(model, X, q, invert(model, q, X, 1e-3, InverseConfig(method=method)).q_cmd)
    assert after < 0.05 * before, (method, after)


@pytest.mark.parametrize("chunk", [10**6, 333, 47])
def test_streaming_equals_in_memory(model, paths, chunk):
    X, q = paths["off100"]
    ref = invert(model, q, X, 1e-3).q_cmd
    qd, qdd = _derivatives(q, 1e-3)
    si = StreamingInverse(model, 1e-3)
    out = [si.push(q[a:a + chunk], X[a:a + chunk], qd[a:a + chunk], qdd[a:a + chunk]) for a in range(0, len(q), chunk)]
    out.append(si.finish())
    o = np.concatenate(out)
    assert o.shape == q.shape
    np.testing.assert_allclose(o, ref, atol=1e-9)


def test_bounds_are_enforced_with_osqp(model, paths):
    """Tight bounds on the correction and the carriage acceleration: OSQP keeps the command inside."""
    X, q = paths["off100"]
    qd, qdd = _derivatives(q, 1e-3)
    D, V, A = 0.12e-3, 0.9, 25.0  # m, m/s, m/s^2 (the free solution needs ~0.3 mm and more acceleration)
    si = StreamingInverse(model, 1e-3, InverseConfig(bounds=(D, V, A)))
    out = np.concatenate([si.push(q, X, qd, qdd), si.finish()])
    assert si.drive[0].qp_windows > 0  # the bounds did bind
    dev = out - q
    assert np.max(np.abs(dev)) < D * 1.02
    acc = np.diff(out, 2, axis=0) / 1e-6
    ref_acc = np.abs(qdd[1:-1])
    assert np.all(np.abs(acc) <= np.maximum(A, ref_acc) * 1.1 + 0.5)
    before = _rms_um(model, X, q, q)
    free = _rms_um(model, X, q, invert(model, q, X, 1e-3).q_cmd)
    bounded = _rms_um(model, X, q, out)
    assert free < bounded < 0.5 * before  # less correction allowed, still far better than none


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**31 - 1), st.floats(0.2, 5.0))
def test_convex_hull_pretest_never_hides_a_violation(seed, scale):
    """``_surely_within`` may say "check exactly" too often, never "fine" when a bound breaks:
    value, velocity and acceleration of the spline stay within the bounds whenever it passes."""
    from types import SimpleNamespace

    from ffcomp.compensate.bspline import UniformBasis
    from ffcomp.compensate.stream import FbsStream

    rng = np.random.default_rng(seed)
    basis = UniformBasis(5, 4, 1e-3)
    coef = np.cumsum(rng.normal(0, 2e-6 * scale, (60, 1)), axis=0)
    n = 60 * basis.m + basis.support
    bounds = (1e-4, 0.02, 8.0)  # m, m/s, m/s^2: near what such coefficients reach
    fake = SimpleNamespace(bounds=bounds, m=basis.m, basis=basis, rvel=np.zeros((n, 1)), racc=np.zeros((n, 1)))
    ok = FbsStream._surely_within(fake, coef[:20], coef[20:], 0, n)
    s0, s1, s2 = (basis.evaluate(coef, n, deriv=k) for k in (0, 1, 2))
    inside = (np.max(np.abs(s0)) <= bounds[0] and np.max(np.abs(s1)) <= bounds[1]
              and np.max(np.abs(s2)) <= bounds[2])
    assert inside or not ok


def test_convex_hull_pretest_passes_small_and_flags_large_corrections():
    from types import SimpleNamespace

    from ffcomp.compensate.bspline import UniformBasis
    from ffcomp.compensate.stream import FbsStream

    basis = UniformBasis(5, 4, 1e-3)
    n = 400
    fake = SimpleNamespace(bounds=(1e-4, 0.02, 8.0), m=basis.m, basis=basis, rvel=np.zeros((n, 1)),
                           racc=np.zeros((n, 1)))
    smooth = 1e-6 * np.sin(np.arange(60) / 9.0)[:, None]
    assert FbsStream._surely_within(fake, smooth[:20], smooth[20:], 0, n)
    assert not FbsStream._surely_within(fake, smooth[:20] * 200, smooth[20:] * 200, 0, n)
