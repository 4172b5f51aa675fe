"""The writer's times and points where the plan's stops fall between samples
(:mod:`ffcomp.gcode.plan_clock`), against a trapezoid computed by hand."""

import numpy as np
import pytest

from ffcomp.gcode.moves import PlannedMove
from ffcomp.gcode.plan_clock import (
    CORNER_LEAD_GAP_MM,
    REST_POINT_NEAR_MM,
    corner_lead,
    corner_lead_free,
    corner_segment_mm,
    corner_tail,
    free_corner,
    plan_speeds,
    rest_end,
    rest_start,
)

DT = 1e-3


def _z_move(t0=0.0046, dz=0.2, a=3000.0):
    """A z move from rest to rest at (0, 0, 1) -> (0, 0, 1 + dz), a triangle at ``a`` (mm/s^2)."""
    t = np.sqrt(dz / a)  # each ramp
    v = a * t
    return PlannedMove(0, 1, "move", t0, (0.0, 0.0, 1.0, 0.0), (0.0, 0.0, 1.0 + dz, 0.0), dz, (0.0, 0.0, 1.0, 0.0),
                       0.0, v, 0.0, a, t, 0.0, t)


def _z_at(mv, t):
    """The trapezoid's z at print time ``t`` (s), mm."""
    a, ta = mv.accel_mm_s2, mv.accel_t_s
    tau = np.clip(t - mv.t_start_s, 0.0, mv.duration_s)
    s = np.where(tau < ta, 0.5 * a * tau**2, mv.distance_mm - 0.5 * a * (mv.duration_s - tau) ** 2)
    return 1.0 + s


def test_a_run_ends_on_the_rest_point_at_the_plans_time():
    mv = _z_move()
    k = np.arange(0, 25)  # the plan's grid; the writer counts 100 samples more (a stream's pre-roll)
    X = np.zeros((len(k), 3))
    X[:, 2] = _z_at(mv, k * DT)
    b = int(np.ceil(mv.t_end_s / DT))  # samples 0 .. b-1 belong to the move
    on = np.ones(len(k), bool)
    # (this move's last sample is 1.3 um short of the rest point: within REST_POINT_NEAR_MM)
    assert 1e-3 < mv.end_mm[2] - X[b - 1, 2] < REST_POINT_NEAR_MM
    X3 = X.copy()
    X3[b - 1, 2] = mv.end_mm[2] - 3e-3  # a last sample 3 um short: the rest point is appended
    end = rest_end(DT, 100, b, X3, mv, k, on, None)
    assert end is not None
    pt, k_end, e, appended = end
    assert k_end == pytest.approx(mv.t_end_s / DT + 100, abs=1e-9) and appended == 1
    np.testing.assert_allclose(pt, mv.end_mm[:3])
    # a free command (not on the plan) turns elsewhere: no point of the plan's is put there
    off = on.copy()
    off[b - 1] = False
    assert rest_end(DT, 100, b, X3, mv, k, off, None) is None
    # the last sample within REST_POINT_NEAR_MM of the rest point (the plan's own, 1.3 um short, or
    # on it): the rest point takes that sample's place, at the plan's time (no micrometre segment)
    for X2 in (X, np.where(np.arange(len(k))[:, None] == b - 1, np.array(mv.end_mm[:3]), X)):
        pt, k_end, e, appended = rest_end(DT, 100, b, X2, mv, k, off, None)
        assert appended == 0 and k_end == pytest.approx(mv.t_end_s / DT + 100, abs=1e-9)
        np.testing.assert_allclose(pt, mv.end_mm[:3])


def test_a_rest_reached_before_the_runs_last_sample_takes_the_plans_time():
    """The plan comes to rest between the run's last two samples and the last sample stands on the
    rest point: that point takes the plan's rest time (the writer then drops the sample before it
    where it lies within a micrometre, instead of a hold that stopped the firmware a sample early)."""
    mv = _z_move()
    k = np.arange(0, 25)
    X = np.zeros((len(k), 3))
    X[:, 2] = _z_at(mv, k * DT)
    b = int(np.ceil(mv.t_end_s / DT)) + 1  # one sample past the rest: the last sample is the rest point
    on = np.ones(len(k), bool)
    pt, k_end, e, appended = rest_end(DT, 100, b, X, mv, k, on, None)
    assert k_end == pytest.approx(mv.t_end_s / DT + 100, abs=1e-9) and k_end < 100 + b - 1 and appended == 0
    np.testing.assert_allclose(pt, mv.end_mm[:3])
    off = on.copy()
    off[b - 1] = False
    assert rest_end(DT, 100, b, X, mv, k, off, None) is None  # a free command: not the plan's point
    assert rest_end(DT, 100, b + 1, X, mv, k, on, None) is None  # the rest two samples back: none


def test_a_run_leaves_rest_at_the_plans_time():
    mv = _z_move(t0=0.0046)
    k = np.arange(0, 25)
    a = int(np.ceil(mv.t_start_s / DT))  # the move's first sample
    on = np.ones(len(k), bool)
    lead = np.round(np.array(mv.start_mm[:3]), 4)
    assert rest_start(DT, 100, a, mv, k, on, lead, 100 + a - 1) == pytest.approx(100 + mv.t_start_s / DT)
    # elsewhere than the start, or not on the plan: from the previous point, as before
    assert rest_start(DT, 100, a, mv, k, on, lead + 0.01, 100 + a - 1) == 100 + a - 1
    assert rest_start(DT, 100, a, mv, k, ~on, lead, 100 + a - 1) == 100 + a - 1
    # a move that leaves rest exactly on a sample (the first move after a homing: t = 0) leaves it
    # at that sample, not a sample earlier (the writer would stretch its first segment over two)
    mv0 = _z_move(t0=0.005)
    a0 = int(round(mv0.t_start_s / DT))
    assert rest_start(DT, 100, a0, mv0, k, on, lead, 100 + a0 - 1) == pytest.approx(100 + a0)


def test_plan_speeds_are_the_trapezoids_peak_along_each_segment():
    mv = _z_move(t0=0.0)
    n = int(np.ceil(mv.t_end_s / DT))
    K = np.arange(n + 1, dtype=float)
    K[-1] = mv.t_end_s / DT
    i, j = np.arange(n), np.arange(1, n + 1)
    src = np.minimum(np.arange(n + 1), n - 1)
    v, acc = plan_speeds(DT, 0, [mv], [0], np.array([0]), src, K, i, j, np.zeros(n, int), [True],
                         np.ones(n, bool), np.arange(n))
    t_mid = mv.accel_t_s
    speed = lambda t: np.where(t < t_mid, mv.accel_mm_s2 * t, mv.accel_mm_s2 * (mv.duration_s - t))  # noqa: E731
    want = np.maximum(speed(K[i] * DT), speed(K[j] * DT))
    peak = (K[i] * DT < t_mid) & (K[j] * DT > t_mid)
    want[peak] = mv.cruise_v_mm_s
    np.testing.assert_allclose(v, want, rtol=1e-9, atol=1e-3)
    assert np.all(acc == mv.accel_mm_s2)


def _corner_down(v_j=2.739, a=3000.0, t0=0.0103, dz=0.4):
    """A z move down from (0, 0, 1) that leaves the corner after an X travel at ``v_j`` (mm/s) and
    accelerates at ``a`` (mm/s^2) to the end (enough for the test), and that travel."""
    t = (np.sqrt(v_j * v_j + 2.0 * a * dz) - v_j) / a
    down = PlannedMove(1, 2, "move", t0, (0.0, 0.0, 1.0, 0.0), (0.0, 0.0, 1.0 - dz, 0.0), dz,
                       (0.0, 0.0, -1.0, 0.0), v_j, v_j + a * t, v_j + a * t, a, t, 0.0, 0.0)
    travel = PlannedMove(0, 1, "move", 0.0, (-10.0, 0.0, 1.0, 0.0), (0.0, 0.0, 1.0, 0.0), 10.0,
                         (1.0, 0.0, 0.0, 0.0), 0.0, 100.0, v_j, 3000.0, 0.01, 0.0, 0.0003)
    return down, travel


@pytest.mark.parametrize("t0", [0.0103, 0.0108, 0.0101])
def test_a_run_leaves_a_corner_with_a_first_segment_the_junction_allows(t0):
    """A run following the plan out of a right-angled corner it passes at v_j: Klipper caps the
    junction at sqrt(d a tan(45 deg) / 2) for a first segment of length d, so the first point is
    the plan's, 2 v_j^2 / a along the move, at the plan's time there; or, where a sample lies just
    beyond that point, that sample (the ones before it go)."""
    down, travel = _corner_down(t0=t0)
    k = np.arange(0, 40)
    a = int(np.ceil(t0 / DT))  # the move's first sample
    X = np.zeros((len(k), 3))
    X[:, 2] = 1.0 - np.array([down.distance_at(t) for t in k * DT])
    on = np.ones(len(k), bool)
    lead = np.array([0.0, 0.0, 1.0])
    reach = 2.0 * down.start_v_mm_s**2 / down.accel_mm_s2
    got = corner_lead(DT, 100, a, len(k), X, down, k, on, lead, travel)
    d = 1.0 - X[a:, 2]
    m = int(np.argmax(d >= reach))
    assert m >= 1 and got is not None
    n_drop, pt, k_pt = got
    if d[m] < reach + CORNER_LEAD_GAP_MM:
        assert n_drop == m and pt is None
    else:
        assert n_drop == m - 1
        np.testing.assert_allclose(pt, [0.0, 0.0, 1.0 - reach], atol=1e-12)
        t_pt = (k_pt - 100) * DT  # back on the plan's clock
        assert down.distance_at(t_pt) == pytest.approx(reach, abs=1e-9)
        assert 100 + a - 1 + m - 1 < k_pt < 100 + a + m
    # no rule on a straight line, nor off the plan, nor away from the corner, nor from rest
    straight = travel._replace(unit=(0.0, 0.0, -1.0, 0.0))
    assert corner_lead(DT, 100, a, len(k), X, down, k, on, lead, straight) is None
    assert corner_lead(DT, 100, a, len(k), X, down, k, ~on, lead, travel) is None
    assert corner_lead(DT, 100, a, len(k), X, down, k, on, lead + 0.01, travel) is None
    assert corner_lead(DT, 100, a, len(k), X, down._replace(start_v_mm_s=0.0), k, on, lead, travel) is None
    # a sharper turn (135 degrees between the directions) reaches further: tan(22.5 deg) < 1
    back = travel._replace(unit=(np.sqrt(0.5), 0.0, np.sqrt(0.5), 0.0))
    far = corner_lead(DT, 100, a, len(k), X, down, k, on, lead, back)
    assert far is not None and far[0] >= n_drop


def test_a_free_run_leaving_the_plans_corner_drops_the_samples_within_its_reach():
    """The mirror of :func:`corner_lead` for a command off the plan after the corner (a correction
    of a few micrometres in x): the samples closer to the corner than Klipper's centripetal rule
    needs at the plan's ``v_j`` go, the next one stays where it is.  On a straight plan, a turn of
    0.7 deg in the command just past the corner gets the same rule (3.2 um chords cap a junction at
    27 mm/s in a lift at 55 mm/s)."""
    down, travel = _corner_down(v_j=5.0, t0=0.0103)
    k = np.arange(0, 40)
    a = int(np.ceil(0.0103 / DT))
    X = np.zeros((len(k), 3))
    X[:, 2] = 1.0 - np.array([down.distance_at(t) for t in k * DT])
    X[a:, 0] = 2e-4 * np.arange(len(k) - a) ** 0.5  # the correction, off the plan (0.2 um and more)
    on = np.zeros(len(k), bool)
    lead = np.array([0.0, 0.0, 1.0])
    reach = corner_segment_mm(travel.unit, down.unit, 5.0, 3000.0)
    got = corner_lead_free(a, len(k), X, down, on, lead, travel, 3000.0, 5e-3)
    d = np.linalg.norm(X[a:] - lead, axis=1)
    assert got == (int(np.argmax(d >= reach)), None, None) and got[0] >= 1
    # on the plan it is corner_lead's; elsewhere, or beyond the tolerance, nothing
    assert corner_lead_free(a, len(k), X, down, np.ones(len(k), bool), lead, travel, 3000.0, 5e-3) is None
    assert corner_lead_free(a, len(k), X, down, on, lead + 0.01, travel, 3000.0, 5e-3) is None
    assert corner_lead_free(a, len(k), X, down, on, lead, travel, 3000.0, 1e-7) is None
    # a straight plan: the command turns 0.7 deg 3.2 um past the corner
    up = PlannedMove(1, 2, "move", 0.0, (0.0, 0.0, 1.0, 0.0), (0.0, 0.0, 2.0, 0.0), 1.0, (0.0, 0.0, 1.0, 0.0),
                     55.0, 55.0, 55.0, 3000.0, 0.0, 1.0 / 55.0, 0.0)
    below = up._replace(index=0, start_mm=(0.0, 0.0, 0.0, 0.0), end_mm=(0.0, 0.0, 1.0, 0.0))
    S = np.zeros((12, 3))
    S[:, 2] = 1.0 + 0.0032 + 0.055 * np.arange(12)
    S[1:, 0] = 7e-4 * np.arange(1, 12)  # 0.7 um per 55 um: 0.73 deg
    jc = -np.dot(S[0] - lead, S[1] - S[0]) / np.linalg.norm(S[0] - lead) / np.linalg.norm(S[1] - S[0])
    tan_half = np.sqrt(0.5 * (1 - jc)) / np.sqrt(0.5 * (1 + jc))
    assert np.sqrt(0.5 * 0.0032 * 3000.0 * tan_half) < 30.0  # Klipper's cap there: the case
    assert corner_lead_free(0, 12, S, up, np.ones(12, bool), lead, below, 3000.0, 5e-3) == (1, None, None)
    # a command on the line: nothing to drop
    S[:, 0] = 0.0
    assert corner_lead_free(0, 12, S, up, np.ones(12, bool), lead, below, 3000.0, 5e-3) is None


def test_a_slow_lifts_first_point_may_lie_in_its_cruise():
    """A lift that leaves the corner at 5 mm/s and cruises at 10 mm/s within 1.7 ms (Cura's layer
    change, ``G1 Z.. F600``, on other_delta): the junction wants a first segment of 16.7 um, which
    the plan covers in its cruise.  The first point is the plan's there, at the plan's time (it was
    left at the first sample, 3.6 um up, and the firmware took the corner 0.4 ms off the clock)."""
    v_j, vc, a, t0, dz = 5.0, 10.0, 3000.0, 0.0103, 0.3
    ta = (vc - v_j) / a
    s_acc = v_j * ta + 0.5 * a * ta * ta
    tc = (dz - s_acc) / vc
    up = PlannedMove(1, 2, "move", t0, (0.0, 0.0, 1.0, 0.0), (0.0, 0.0, 1.0 + dz, 0.0), dz, (0.0, 0.0, 1.0, 0.0),
                     v_j, vc, vc, a, ta, tc, 0.0)
    travel = PlannedMove(0, 1, "move", 0.0, (-10.0, 0.0, 1.0, 0.0), (0.0, 0.0, 1.0, 0.0), 10.0,
                         (1.0, 0.0, 0.0, 0.0), 0.0, 100.0, v_j, 3000.0, 0.01, 0.0, 0.0003)
    k = np.arange(0, 40)
    i0 = int(np.ceil(t0 / DT))
    X = np.zeros((len(k), 3))
    X[:, 2] = 1.0 + np.array([up.distance_at(t) for t in k * DT])
    reach = 2.0 * v_j**2 / a
    assert reach > s_acc  # the case: the point lies in the cruise
    got = corner_lead(DT, 100, i0, len(k), X, up, k, np.ones(len(k), bool), np.array([0.0, 0.0, 1.0]), travel)
    assert got is not None
    n_drop, pt, k_pt = got
    d = X[i0:, 2] - 1.0
    m = int(np.argmax(d >= reach))
    if pt is None:
        assert d[m] < reach + CORNER_LEAD_GAP_MM and n_drop == m
    else:
        np.testing.assert_allclose(pt, [0.0, 0.0, 1.0 + reach], atol=1e-12)
        assert up.distance_at((k_pt - 100) * DT) == pytest.approx(reach, abs=1e-9)
    # beyond the cruise (a move that brakes within the reach) there is no rule to follow
    short = up._replace(cruise_t_s=0.0, decel_t_s=tc)
    assert corner_lead(DT, 100, i0, len(k), X, short, k, np.ones(len(k), bool), np.array([0.0, 0.0, 1.0]),
                       travel) is None


def _corner_up(v_j=2.739, a=3000.0, t0=0.0103, dz=0.2, cruise_v=None):
    """A z move up from (0, 0, 1) that brakes at ``a`` (mm/s^2) into the corner with an X travel it
    passes at ``v_j`` (mm/s), and that travel; with ``cruise_v``, the move cruises at that speed
    before it brakes."""
    if cruise_v is None:
        t = (np.sqrt(v_j * v_j + 2.0 * a * dz) - v_j) / a
        up = PlannedMove(1, 2, "move", t0, (0.0, 0.0, 1.0, 0.0), (0.0, 0.0, 1.0 + dz, 0.0), dz,
                         (0.0, 0.0, 1.0, 0.0), v_j + a * t, v_j + a * t, v_j, a, 0.0, 0.0, t)
    else:
        td = (cruise_v - v_j) / a
        tc = (dz - 0.5 * (cruise_v + v_j) * td) / cruise_v
        t = tc + td
        up = PlannedMove(1, 2, "move", t0, (0.0, 0.0, 1.0, 0.0), (0.0, 0.0, 1.0 + dz, 0.0), dz,
                         (0.0, 0.0, 1.0, 0.0), cruise_v, cruise_v, v_j, a, 0.0, tc, td)
    travel = PlannedMove(2, 3, "move", t0 + t, (0.0, 0.0, 1.0 + dz, 0.0), (10.0, 0.0, 1.0 + dz, 0.0), 10.0,
                         (1.0, 0.0, 0.0, 0.0), v_j, 100.0, 0.0, 3000.0, 0.03, 0.07, 0.03)
    return up, travel


@pytest.mark.parametrize("v_j, cruise_v", [(2.739, None), (5.0, None), (5.0, 10.0)])
@pytest.mark.parametrize("t0", [0.0103, 0.0108, 0.0101, 0.0106, 0.0109])
def test_a_run_comes_into_a_corner_with_a_last_segment_the_junction_allows(t0, v_j, cruise_v):
    """The mirror of the corner lead: a run following the plan into a right-angled corner it passes
    at v_j (a z-hop into its travel).  Klipper caps the junction by the segment before it too, at
    sqrt(d a tan(45 deg) / 2), so the segment into the corner is 2 v_j^2 / a long: from the plan's
    point there at the plan's time, or from a sample just before that point; the samples after it
    go.  With a cruise before the braking (10 mm/s into a 5 mm/s corner: the braking covers 12.5 um
    of the 16.7 um segment), the point lies in the cruise."""
    up, travel = _corner_up(t0=t0, v_j=v_j, cruise_v=cruise_v)
    k = np.arange(0, 40)
    a = int(np.ceil(t0 / DT))  # the move's first sample
    b = int(np.ceil(up.t_end_s / DT))  # samples before the corner: a .. b - 1
    X = np.zeros((len(k), 3))
    X[:, 2] = 1.0 + np.array([up.distance_at(t) for t in k * DT])
    on = np.ones(len(k), bool)
    end = rest_end(DT, 100, b, X, up, k, on, travel)
    assert end is not None
    corner = np.array([0.0, 0.0, 1.2])
    np.testing.assert_allclose(end[0], corner, atol=1e-12)
    reach = 2.0 * up.end_v_mm_s**2 / up.accel_mm_s2
    got = corner_tail(DT, 100, a, b, X, up, on, travel, end, 3000.0)
    last = b - 1 if end[3] else b - 2  # the last sample before the corner point
    d = corner[2] - X[:last + 1, 2]
    within = np.nonzero(d < reach)[0]
    if got is None:  # the last sample already starts a segment just longer than the point's
        assert not within.size and d[last] < reach + CORNER_LEAD_GAP_MM
        return
    n_drop, pt, k_pt = got
    first = int(within[0]) if within.size else last  # none within: the last sample moves out
    if d[first - 1] < reach + CORNER_LEAD_GAP_MM:
        assert n_drop == last - first + 1 and pt is None
    else:
        assert n_drop == last - first + 1
        np.testing.assert_allclose(pt, corner - [0.0, 0.0, reach], atol=1e-12)
        t_pt = (k_pt - 100) * DT  # back on the plan's clock
        assert up.distance_at(t_pt) == pytest.approx(up.distance_mm - reach, abs=1e-9)
        assert 100 + first - 1 < k_pt < end[1]
    # the segment into the corner now lets the firmware pass it at v_j, and no faster
    seg = reach if pt is not None else d[first - 1]
    assert 0.5 * seg * 1.0 * 3000.0 >= up.end_v_mm_s**2 * (1 - 1e-9)
    # no rule on a straight line, off the plan, from rest, or before an extruder-only move
    straight = travel._replace(unit=(0.0, 0.0, 1.0, 0.0))
    assert corner_tail(DT, 100, a, b, X, up, on, straight, end, 3000.0) is None
    assert corner_tail(DT, 100, a, b, X, up, ~on, travel, end, 3000.0) is None
    assert corner_tail(DT, 100, a, b, X, up._replace(end_v_mm_s=0.0), on, travel, end, 3000.0) is None
    assert corner_tail(DT, 100, a, b, X, up, on, travel._replace(kind="extrude"), end, 3000.0) is None
    # a sharper turn (135 degrees between the directions) reaches further: tan(22.5 deg) < 1
    back = travel._replace(unit=(np.sqrt(0.5), 0.0, -np.sqrt(0.5), 0.0))
    far = corner_tail(DT, 100, a, b, X, up, on, back, end, 3000.0)
    assert far is not None and far[0] >= n_drop


def _travel_into_lift(t_corner=0.01037, v_j=5.0, a=3000.0, out=(0.0, 0.0, 1.0)):
    """A travel along +x (cruise 20 mm/s, braking at ``a`` to ``v_j``) into a lift up z (or along
    ``out``) from ``v_j`` at ``a``, the corner at (0, 0, 1) at ``t_corner`` (s), between two
    samples."""
    vc = 20.0
    td = (vc - v_j) / a
    L = 0.5 * (vc + v_j) * td + vc * 0.02
    A = PlannedMove(0, 1, "move", t_corner - 0.02 - td, (-L, 0.0, 1.0, 0.0), (0.0, 0.0, 1.0, 0.0), L,
                    (1.0, 0.0, 0.0, 0.0), vc, vc, v_j, a, 0.0, 0.02, td)
    dz = 0.5
    ta = (np.sqrt(v_j * v_j + 2 * a * dz) - v_j) / a
    u = np.array(out) / np.linalg.norm(out)
    B = PlannedMove(1, 2, "move", t_corner, (0.0, 0.0, 1.0, 0.0), (*(np.array([0.0, 0.0, 1.0]) + dz * u), 0.0), dz,
                    (*u, 0.0), v_j, v_j + a * ta, v_j + a * ta, a, ta, 0.0, 0.0)
    return A, B


def _klipper_corner_v(lim, pts):
    """Klipper's junction speed limits (mm/s) at the inner points of the chain ``pts`` (n, 3)."""
    from ffcomp.gcode.chain_plan import junction_v2, segment_limits

    d = np.diff(pts, axis=0)
    ln = np.linalg.norm(d, axis=1)
    acc = segment_limits(lim, pts[:-1], pts[1:], np.zeros(len(d)))[1]
    return np.sqrt(junction_v2(lim, d / ln[:, None], np.zeros(len(d)), acc, 2.0 * ln * acc))


def _sampled(A, B, wobble_mm=25e-3):
    """The plan of ``A`` then ``B`` on 40 samples and a command: the plan plus a 60 Hz wobble along
    x + z; returns (k, plan, command, correction function)."""
    k = np.arange(0, 40)
    t = k * DT

    def corr(t):
        w = 2 * np.pi * 60.0
        return wobble_mm * np.sin(w * (t - A.t_end_s) + 0.3)[:, None] * np.array([1.0, 0.0, 1.0]) / np.sqrt(2)

    plan = np.array([np.array(mv.start_mm[:3]) + np.array(mv.unit[:3]) * mv.distance_at(ti)
                     for ti in t for mv in [A if ti < A.t_end_s else B]])
    return k, plan, plan + corr(t), corr


def test_a_free_corner_is_written_with_segments_klipper_lets_through_at_the_commands_speed():
    """A travel into a steep move (a 73 deg turn) that the plan takes at 5 mm/s, with a correction
    (a 60 Hz wobble of 25 um along x + z) that carries the command through the turn at 14-16 mm/s.
    Sampled, the chords either side of the corner are 14-16 um: Klipper's centripetal rule of such
    short segments (``max_z_accel * d / |dz|`` on the steep ones) caps a junction there at
    12.2 mm/s, 0.84 of the command's speed.  ``free_corner`` ends the run on the command's corner
    (the plan's corner moved by the correction interpolated at the plan's time) and drops the
    samples within reach; the chords that replace them hold the dropped samples within the
    tolerance, and Klipper's limits at the new corner let the command through (15.4 mm/s)."""
    from pathlib import Path

    from ffcomp.gcode.chain_plan import ChainLimits
    from ffcomp.profile import load_profile

    prof = load_profile(Path(__file__).resolve().parents[1] / "samples" / "profiles" / "other_delta.toml")
    lim = ChainLimits(prof, 1e5, 100.0)
    A, B = _travel_into_lift(out=(0.3, 0.0, 1.0))
    k, plan, X, corr = _sampled(A, B)
    b = int(np.ceil(A.t_end_s / DT))  # the first sample of the steep move
    a, tol = 0, 5e-3
    # the case: as sampled, Klipper caps the junctions by the corner below the command's speed
    v_cmd = np.linalg.norm(np.diff(X, axis=0), axis=1) / DT
    v = min(v_cmd[b - 2], v_cmd[b])
    jv = _klipper_corner_v(lim, X[b - 2:b + 2])
    need = 0.5 * (v_cmd[b - 2:b] + v_cmd[b - 1:b + 1])  # the command's speed at those junctions
    assert np.min(jv / need) < 0.85
    got = free_corner(DT, 100, a, b, len(k), X, A, B, k, lim, tol)
    assert got is not None
    (pc, k_end, e, appended), n, m = got
    assert appended == 1 and n >= 1 and m >= 1 and k_end == pytest.approx(A.t_end_s / DT + 100, abs=1e-9)
    # the command's corner: the plan's corner plus the correction there (to its curvature, < 1 um)
    np.testing.assert_allclose(pc, np.array(A.end_mm[:3]) + corr(np.array([A.t_end_s]))[0], atol=1e-3)
    # the chords that replace the dropped samples hold them within the tolerance
    p_in, p_out = X[b - 1 - n], X[b + m]
    for seg0, seg1, pts in ((p_in, pc, X[b - n:b]), (pc, p_out, X[b:b + m])):
        dd = seg1 - seg0
        s_ = np.clip((pts - seg0) @ dd / (dd @ dd), 0, 1)
        assert np.max(np.linalg.norm(pts - (seg0 + s_[:, None] * dd), axis=1)) <= tol
    # and Klipper lets the command through the new corner much faster
    jv_new = _klipper_corner_v(lim, np.array([p_in, pc, p_out]))[0]
    assert jv_new >= 1.15 * np.min(jv) and jv_new >= 0.85 * v
    # none on a straight line (the sampled chords let the command through), or without three of the
    # next run's samples past the dropped ones
    A2, B2 = _travel_into_lift(out=(1.0, 0.0, 0.0))
    k2, _, X2, _ = _sampled(A2, B2)
    assert free_corner(DT, 100, a, b, len(k2), X2, A2, B2, k2, lim, tol) is None
    assert free_corner(DT, 100, a, b, b + 2, X, A, B, k, lim, tol) is None


def test_the_corner_gate_equals_klippers_rules():
    """``free_corner`` first asks whether the sampled chords already let the command through, for
    every run end of a writer's chunk at once (``sampled_corners_ok``; a call per corner cost 2.7 s
    of 17 on the plate's first 40,000 lines).  It must answer as :func:`junction_v2` with
    :func:`segment_limits` (the delta cap, the slow zones near the print radius) do, chain by
    chain."""
    from pathlib import Path

    from ffcomp.gcode.chain_plan import ChainLimits
    from ffcomp.gcode.plan_clock import FREE_CORNER_SHARE, _junction_speeds, sampled_corners_ok
    from ffcomp.profile import load_profile

    lim = ChainLimits(load_profile(Path(__file__).resolve().parents[1] / "samples/profiles/other_delta.toml"),
                      1e5, 100.0)
    rng = np.random.default_rng(3)
    answers, chains = [], []
    for _ in range(3000):
        start = rng.uniform(-125, 125, 3) * np.array([1, 1, 0.2]) + np.array([0, 0, 30])
        u = rng.normal(size=3) * np.array([1, 1, rng.uniform(0, 3)])
        L = rng.uniform(0.002, 0.03)
        d = u / np.linalg.norm(u) * L + rng.normal(size=(3, 3)) * L * rng.uniform(0.0, 0.6)
        P = np.vstack([start, start + np.cumsum(d, 0)])
        ln = np.linalg.norm(d, axis=1)
        answers.append(bool(np.all(_junction_speeds(lim, P) >= FREE_CORNER_SHARE * 0.5 * (ln[:-1] + ln[1:]) / DT)))
        chains.append(P)
    assert 0.1 < np.mean(answers) < 0.9  # both answers occur
    X = np.concatenate(chains)
    assert sampled_corners_ok(lim, X, np.arange(len(chains)) * 4 + 2, DT).tolist() == answers
