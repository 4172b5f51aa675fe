"""The physical limit, the reference's derivatives from its samples and the inertia split.

Ground truths: scipy's natural cubic spline for the derivatives, the plain ``H0[g]`` for the
inertia split on a smooth signal, and the nonlinear plant for the limit and the corner fix.
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.interpolate import CubicSpline

from ffcomp.compensate.bspline import UniformBasis
from ffcomp.compensate.differ import SplineDerivatives, spline_derivatives
from ffcomp.compensate.inverse import InverseConfig, inertia_split, invert, mech_target
from ffcomp.compensate.kernels import mech_arrays
from ffcomp.compensate.limit import limit_commands
from ffcomp.compensate.ltv import simulate_lti
from ffcomp.compensate.stream import _command_shapes
from ffcomp.compensate.stream_inverse import StreamingInverse
from ffcomp.kinematics import carriage_rates, inverse
from ffcomp.linalg3 import matvec3
from ffcomp.sim import metrics
from ffcomp.sim.moves import pattern, polygon_path
from ffcomp.sim.plant import DeltaPlant


def _rest_padded(rng, n=220, pad=40):
    q = np.cumsum(rng.normal(size=(n, 3)), 0) * 1e-4
    return np.vstack([np.repeat(q[:1], pad, 0), q, np.repeat(q[-1:], pad, 0)])


def test_derivatives_are_the_natural_cubic_interpolant(rng):
    q = _rest_padded(rng)
    dt = 1e-3
    qd, qdd = spline_derivatives(q, dt)
    t = np.arange(len(q)) * dt
    cs = CubicSpline(t, q, bc_type="natural")
    np.testing.assert_allclose(qd, cs(t, 1), atol=1e-10 * np.abs(qd).max())
    np.testing.assert_allclose(qdd, cs(t, 2), atol=1e-10 * np.abs(qdd).max())


@settings(max_examples=25, deadline=None)
@given(st.lists(st.integers(1, 90), min_size=1, max_size=12))
def test_streamed_derivatives_do_not_depend_on_the_chunks(chunks):
    q = _rest_padded(np.random.default_rng(7), n=150)
    ref = spline_derivatives(q, 1e-3)
    s = SplineDerivatives(q[0], 1e-3)
    out, a = [], 0
    for c in chunks * (len(q) // max(1, sum(chunks)) + 1):
        if a >= len(q):
            break
        out.append(s.push(q[a:a + c], np.arange(a, min(a + c, len(q)))))
        a += c
    out.append(s.finish())
    idx = np.concatenate([o[3] for o in out])
    np.testing.assert_array_equal(idx, np.arange(len(q)))  # every row once, in order, extras aligned
    np.testing.assert_array_equal(np.concatenate([o[1] for o in out]), ref[0])
    np.testing.assert_array_equal(np.concatenate([o[2] for o in out]), ref[1])


def test_inertia_split_equals_plain_weighting_on_a_smooth_path(model):
    """``H0[g - dh] + d/dt H0[h]`` is ``H0[g]`` when the samples resolve the motion."""
    dt = 1e-3
    t = np.arange(1500) * dt
    X = np.column_stack([0.03 * np.sin(2 * np.pi * 3 * t) * np.sin(np.pi * t / t[-1]) ** 2,
                         0.02 * (1 - np.cos(2 * np.pi * 2 * t)) * np.sin(np.pi * t / t[-1]) ** 2,
                         np.full_like(t, 0.03)])
    q = inverse(model.geometry, X)
    qd, qdd = spline_derivatives(q, dt)
    mats = model.matrices(X, check=False)
    x0 = np.array([[0.0, 0.0, 0.03]])
    A0, _ = mech_arrays(model.matrices(x0))
    Bf = np.zeros((6, 3))
    Bf[3:] = np.linalg.inv(model.matrices(x0).M[0])
    g = matvec3(mats.M, qdd) + 0.1 * qd
    h, dh = inertia_split(mats, qd, qdd, dt)
    plain = simulate_lti(A0[0], Bf, g, dt)[0][:, :3]
    split = mech_target(A0[0], Bf, g, h, dh, dt)
    assert np.abs(split - plain).max() < 2e-3 * np.abs(plain).max()


def test_linear_spline_command_shapes_are_sample_differences():
    b = UniformBasis(1, 1, 1e-3)
    s, v, a = _command_shapes(b)
    np.testing.assert_allclose(s, [0.0, 1.0, 0.0])  # a hat on one sample, zero one sample either side
    np.testing.assert_allclose(v, [0.5e3, 0.0, -0.5e3])
    np.testing.assert_allclose(a, np.array([1.0, -2.0, 1.0]) / 1e-6)
    c = UniformBasis(5, 4, 1e-3)
    for x, d in zip(_command_shapes(c), range(3)):
        np.testing.assert_allclose(x, c.shape(d))


@pytest.fixture(scope="module")
def polygon_case(geom):
    tr = pattern("polygon", geom, (0.0, 0.0, 30.0), loops=1)
    return tr


def test_polygon_pattern_is_a_sliced_circle_at_250_hz(geom, polygon_case):
    v = polygon_path(np.zeros(3), loops=1)
    chords = np.linalg.norm(np.diff(v, axis=0), axis=1)
    assert len(v) == 65 and np.allclose(chords, 0.8e-3)
    speed = np.linalg.norm(np.diff(polygon_case.xyz_m, axis=0), axis=1).max() / 1e-3
    assert speed == pytest.approx(0.2, rel=1e-6)  # cruises at 200 mm/s: 250 segments a second


def _planned_window(profile, name, n=1500, pad=300):
    """A window of a stress sample as the G-code planner samples it: positions and the planner's
    exact velocities and accelerations, from a standstill near the bed, then held at rest."""
    from pathlib import Path

    from ffcomp.gcode.sampler import concat_blocks, sample_gcode

    src = Path(__file__).resolve().parents[1] / "samples" / "gcode" / name
    ref = concat_blocks(sample_gcode(str(src), profile, overlap=0))
    x = ref.xyz_m
    step = np.linalg.norm(np.diff(x, axis=0), axis=1)
    cuts = np.concatenate([[0], np.flatnonzero(step > 0.45e-3) + 1, [len(x)]])  # homing jumps
    k = int(np.argmax(np.diff(cuts)))
    a0, a1 = cuts[k], cuts[k + 1]
    still = np.flatnonzero((step[a0:a1 - 1] == 0) & (x[a0 + 1:a1, 2] < 0.005)) + a0 + 1
    sl = slice(still[0], min(a1, still[0] + n))
    hold = lambda a, zero=False: np.vstack([a[sl], np.repeat(0 * a[sl][-1:] if zero else a[sl][-1:], pad, 0)])  # noqa: E731
    X, v, a = hold(x), hold(ref.v_m_s, True), hold(ref.a_m_s2, True)
    return X, inverse(profile.geometry_si(), X), v, a


def test_corners_reach_the_inverse_whatever_derivatives_the_planner_gives(model, profile, geom):
    """The planner's exact derivatives leave out the velocity jumps at corners; the samples' own
    derivatives (the default) do not, and the stream ignores the derivatives it is given."""
    dt = 1e-3
    X, q, v, a = _planned_window(profile, "stress_square.gcode")
    qd, qdd = carriage_rates(geom, X, v, a)
    si = StreamingInverse(model, dt)
    got = np.concatenate([si.push(q, X, qd, qdd), si.finish()])
    np.testing.assert_allclose(got, invert(model, q, X, dt).q_cmd, atol=1e-9)
    given_ = invert(model, q, X, dt, InverseConfig(derivatives="given"), qd_ref=qd, qdd_ref=qdd).q_cmd
    t = np.arange(len(q)) * dt
    res = DeltaPlant(model).simulate(t, np.stack([q, got, given_]), hold="linear")
    e = [metrics.evaluate(t, X, res.xyz_m[k]).lag.rms_norm_um for k in range(3)]
    assert e[1] < 0.03 * e[0], e
    assert e[1] < 0.6 * e[2], e  # measured: 2.0 um against 4.0 um


def test_limit_beats_the_default_on_the_models_own_plant(model, geom):
    tr = pattern("square", geom, (50.0, 0.0, 30.0), loops=1, side_m=0.03)
    dt = 1e-3
    lim = limit_commands(model, tr.q_m, tr.xyz_m, dt, iterations=1)
    assert lim.rms_um[1] < 0.3 * lim.rms_um[0] and lim.best == 1  # the Newton step converges
    default = invert(model, tr.q_m, tr.xyz_m, dt).q_cmd
    res = DeltaPlant(model).simulate(tr.t_s, np.stack([tr.q_m, default, lim.q_cmd]), hold="linear")
    e = [metrics.evaluate(tr.t_s, tr.xyz_m, res.xyz_m[k]).lag.rms_norm_um for k in range(3)]
    assert e[2] < e[1] < 0.02 * e[0], e
    assert e[2] < 0.3 * e[1], e
