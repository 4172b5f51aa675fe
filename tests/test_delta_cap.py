"""Klipper's delta caps on the written command (:mod:`ffcomp.compensate.delta_cap`): the caps against
Klipper's own junction formula, the cheap screen against the exact check, the smallest change that
keeps them, and the written G-code's clock on the fidelity bench's z travel."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ffcomp.compensate.delta_cap import EDGE_ACROSS_SHARE, DeltaCap, cap_breaks, cap_window, jacobian_table
from ffcomp.compensate.pin_repair import PulseResponses
from ffcomp.gcode.junction import klipper_corner_v2, klipper_junction_deviation
from ffcomp.kinematics import forward, inverse, jacobian
from ffcomp.model.lpv import LpvModel
from ffcomp.profile import default_profile

DT = 1e-3


@pytest.fixture(scope="module")
def model():
    return LpvModel.from_profile(default_profile())


def _cap(scv_mm_s: float = 100.0, mza: float = 3.0, geom=None) -> DeltaCap:
    jd_mm = klipper_junction_deviation(scv_mm_s, 1e5)
    return DeltaCap(mza, 100.0, jd_mm * 1e-3, DT, jacobian_table(geom) if geom is not None else None)


@pytest.mark.parametrize("scv", [5.0, 100.0])
def test_the_cap_across_the_path_is_klippers_junction_rule_on_dense_segments(scv):
    """Two segments of one sample each at speed ``v``, turning by a small angle: Klipper's corner limit
    (:func:`~ffcomp.gcode.junction.klipper_corner_v2`, its square-corner and centripetal terms with
    the segments' acceleration ``max_z_accel / |u_z|``) allows ``v`` up to where the turn's
    acceleration ``v phi / dt`` reaches :meth:`DeltaCap.limits`'s cap across (``sqrt(8 jd a) / dt``
    at SQUARE_CORNER_VELOCITY 5, ``a`` itself at the 100 the output sets)."""
    cap = _cap(scv)
    u_z = 0.6
    along, across = cap.limits(np.array([u_z]))
    a_mm = float(along[0]) * 1e3
    assert a_mm == pytest.approx(3000.0 / u_z)
    jd = klipper_junction_deviation(scv, 1e5)
    for phi in np.deg2rad([0.3, 1.0, 3.0]):
        def corner_v(v, phi=phi):  # Klipper's v limit for segments of v dt each
            d = v * DT
            return math.sqrt(klipper_corner_v2(-math.cos(phi), jd, a_mm, 2 * d * a_mm, jd, a_mm, 2 * d * a_mm))
        lo, hi = 1e-3, 1e5
        for _ in range(200):  # the fixed point v = corner_v(v)
            mid = math.sqrt(lo * hi)
            lo, hi = (mid, hi) if corner_v(mid) > mid else (lo, mid)
        a_n = lo * phi / DT * 1e-3  # m/s^2
        assert a_n == pytest.approx(float(across[0]), rel=0.03), (np.rad2deg(phi), a_n, across)
    assert (float(across[0]) < float(along[0])) == (scv == 5.0)  # both branches of the cap


def test_the_jacobian_table_bounds_the_jacobian(model):
    """:func:`jacobian_table` (the screen's bounds) is above the Jacobian's norm and its z row's
    deviation from the carriages' mean at random points of the print disc."""
    geom = model.geometry
    r_tab, sig, zdev = jacobian_table(geom)
    rng = np.random.default_rng(3)
    r = geom.print_radius_m * np.sqrt(rng.random(2000))
    ang = 2 * np.pi * rng.random(2000)
    xyz = np.c_[r * np.cos(ang), r * np.sin(ang), 0.02 * rng.random(2000)]
    J = jacobian(geom, xyz)
    k = np.minimum(np.searchsorted(r_tab, r), len(r_tab) - 1)
    assert np.all(np.linalg.norm(J, ord=2, axis=(1, 2)) <= sig[k])
    assert np.all(np.linalg.norm(J[:, 2, :] - 1 / 3, axis=1) <= zdev[k])


def _braking_line(n: int = 80, u_z: float = 0.4, bump_m: float = 30e-6):
    """A plan braking at 6 m/s^2 along a line rising at ``u_z`` (its cap 3 / 0.4 = 7.5 m/s^2), and a
    command with an x correction (ahead, then back: braking harder at its peak)."""
    t = np.arange(n) * DT
    u = np.array([np.sqrt(1 - u_z**2), 0.0, u_z])
    s = 0.5 * t - 0.5 * 6.0 * t**2  # 500 mm/s braking at 6 m/s^2
    xp = np.array([-0.02, 0.0, 0.01]) + s[:, None] * u
    xc = xp.copy()
    xc[:, 0] += bump_m * np.exp(-((t - 0.04) / 0.004) ** 2)
    return t, u, xp, xc


def test_a_free_command_past_the_delta_cap_is_brought_within_it(model):
    """Klipper caps a segment's acceleration at ``max_z_accel * d/|dz|``, along the segment and (its
    centripetal junction rule) across it.  The plan keeps its cap; the correction passes it (the
    fidelity bench's z travel on other_delta: the command into an XZ reversal ran 0.93 ms off the
    clock).  :func:`cap_breaks` flags those samples (none of the plan's); :func:`cap_window` brings
    them within the cap by a few micrometres (9.3 -> 7.2 m/s^2 along, 3 um), and changes nothing
    where the cap does not bind."""
    geom = model.geometry
    cap = _cap(geom=geom)
    t, u, xp, xc = _braking_line()
    qp, c = inverse(geom, xp), inverse(geom, xc)
    assert not cap_breaks(geom, qp, xp, cap).any()
    br = cap_breaks(geom, c, xp, cap)
    assert br.sum() >= 3  # the case
    pose = xp[len(t) // 2]
    H = PulseResponses(model, DT).at(pose)
    J = jacobian(geom, pose)
    out = cap_window(H, c, J, jacobian(geom, xp), xp, cap)
    assert not cap_breaks(geom, out, xp, cap).any()
    assert 0.0 < float(np.max(np.abs(out - c))) < 10e-6
    a_t = np.abs((np.diff(forward(geom, out), 2, axis=0) / DT**2) @ u)
    assert float(np.max(a_t)) <= 3.0 / 0.4 * 1.01
    assert float(np.max(np.abs((np.diff(forward(geom, c), 2, axis=0) / DT**2) @ u))) > 3.0 / 0.4 * 1.1
    loose = DeltaCap(30.0, 100.0, cap.junction_deviation_m, DT)  # a cap that does not bind
    np.testing.assert_array_equal(cap_window(H, c, J, jacobian(geom, xp), xp, loose), c)


def test_a_bend_off_a_pinned_run_is_judged_at_the_writers_short_segment(model):
    """The writer ends a pinned run on the plan's corner at its time, so a short segment meets the
    first free one: Klipper's centripetal rule takes the shorter length.  A free command that bends
    off the end of a pinned z move (at 84 mm/s: a random file, 2 um, 1.4 degrees, braked from 84
    to 76 mm/s by the firmware) is flagged with the pins given (the cap across at
    :data:`EDGE_ACROSS_SHARE`), not without."""
    geom = model.geometry
    cap = _cap(geom=geom)
    n = 60
    t = np.arange(n) * DT
    xp = np.c_[np.full(n, 0.02), np.zeros(n), 0.005 + 0.084 * t]  # straight up at 84 mm/s
    pin = t < 0.030
    xc = xp.copy()
    k = np.arange(n) - 29
    xc[:, 0] -= np.where(k > 0, 1e-6 * k * 1.5, 0.0)  # bending off from the last pinned sample
    qp, c = inverse(geom, xp), inverse(geom, xc)
    a_n = np.abs(np.diff(xc[:, 0], 2) / DT**2)[28]  # across, at the last pinned sample
    assert EDGE_ACROSS_SHARE * 3.0 < a_n < 3.0  # within the cap, past its share at the edge
    assert not cap_breaks(geom, c, xp, cap).any()
    assert cap_breaks(geom, c, xp, cap, pin)[29]
    assert not cap_breaks(geom, qp, xp, cap, pin).any()


@settings(max_examples=25, deadline=None)
@given(st.floats(0.05, 0.95), st.floats(1e-6, 80e-6), st.floats(-0.05, 0.05), st.floats(0.0, 2 * np.pi))
def test_the_screen_never_hides_a_break(u_z, bump, x0, ang):
    """:func:`cap_breaks` with the plan's carriage heights (the cheap screen first) flags exactly the
    samples the exact check flags, on random steep lines with random corrections."""
    geom = LpvModel.from_profile(default_profile()).geometry
    cap = _cap(geom=geom)
    n = 80
    t = np.arange(n) * DT
    u = np.array([np.sqrt(1 - u_z**2) * np.cos(ang), np.sqrt(1 - u_z**2) * np.sin(ang), u_z])
    s = 0.1 * t - 0.5 * 1.0 * t**2
    xp = np.array([x0, -x0, 0.01]) + s[:, None] * u
    xc = xp.copy()
    xc += bump * np.exp(-((t - 0.04) / 0.003) ** 2)[:, None] * np.array([1.0, -0.5, 0.3])
    qp, c = inverse(geom, xp), inverse(geom, xc)
    exact = cap_breaks(geom, c, xp, DeltaCap(cap.max_z_accel_m_s2, cap.accel_m_s2, cap.junction_deviation_m, DT))
    np.testing.assert_array_equal(cap_breaks(geom, c, xp, cap, q_plan=qp), exact)
