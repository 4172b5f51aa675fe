"""Klipper planner: trapezoids, junctions, extruder and delta limits, limit commands, dwells, streaming."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from ffcomp.errors import GcodeError, KinematicsError
from ffcomp.gcode import klipper as kmod
from ffcomp.gcode import plan_gcode
from ffcomp.gcode.junction import klipper_corner_v2, klipper_junction_deviation
from ffcomp.profile import default_profile

BASE = default_profile()


def prof(geometry=None, **limits):
    p = replace(BASE, limits=replace(BASE.limits, **limits))
    if geometry:
        p = replace(p, geometry=replace(p.geometry, **geometry))
    return p


def plan(text, profile=None, **kw):
    pl = plan_gcode(text.splitlines(keepends=True), profile or BASE, **kw)
    out = list(pl)
    return out, pl


def trap_time(d, v0, vc, v1, a):
    """Closed-form duration of a trapezoid over d from v0 up to vc and down to v1."""
    da = (vc * vc - v0 * v0) / (2 * a)
    dd = (vc * vc - v1 * v1) / (2 * a)
    return (vc - v0) / a + (vc - v1) / a + (d - da - dd) / vc


# ---------------------------------------------------------------- single moves

def test_full_trapezoid_matches_closed_form():
    mv, _ = plan("G1 X100 F6000\n", prof(max_accel_mm_s2=1000.0))
    (m,) = mv
    assert (m.start_v_mm_s, m.cruise_v_mm_s, m.end_v_mm_s) == (0.0, 100.0, 0.0)
    assert m.accel_t_s == pytest.approx(0.1, rel=1e-12) and m.decel_t_s == pytest.approx(0.1, rel=1e-12)
    assert m.duration_s == pytest.approx(100 / 100 + 100 / 1000, rel=1e-12)


def test_accel_limited_triangle_without_cruise_ratio():
    mv, _ = plan("G1 X10 F12000\n", prof(max_accel_mm_s2=1000.0, minimum_cruise_ratio=0.0))
    (m,) = mv
    assert m.cruise_v_mm_s == pytest.approx(math.sqrt(10 * 1000), rel=1e-12)
    assert m.cruise_t_s == pytest.approx(0.0, abs=1e-12)
    assert m.duration_s == pytest.approx(2 * math.sqrt(10 / 1000), rel=1e-12)


def test_minimum_cruise_ratio_limits_the_peak_of_a_short_move():
    # Klipper: with minimum_cruise_ratio r a move from rest to rest peaks at v^2 = d a (1 - r)
    d, a, r = 10.0, 1000.0, 0.5
    mv, _ = plan("G1 X10 F12000\n", prof(max_accel_mm_s2=a, minimum_cruise_ratio=r))
    (m,) = mv
    vp = math.sqrt(d * a * (1 - r))
    assert m.cruise_v_mm_s == pytest.approx(vp, rel=1e-12)
    assert m.duration_s == pytest.approx(trap_time(d, 0, vp, 0, a), rel=1e-12)
    assert m.cruise_t_s == pytest.approx(r * d / vp, rel=1e-9)  # the cruise covers r of the distance


def test_velocity_is_capped_by_max_velocity():
    mv, _ = plan("G1 X100 F60000\n", prof(max_velocity_mm_s=150.0))
    assert mv[0].cruise_v_mm_s == 150.0


# ---------------------------------------------------------------- junctions

def _corner_plan(p2, profile, d=50.0):
    text = f"G1 X{d} Y0 F6000\nG1 X{p2[0]:.12f} Y{p2[1]:.12f}\n"
    mv, _ = plan(text, profile)
    return mv


def test_square_corner_runs_at_square_corner_velocity():
    p = prof(max_accel_mm_s2=1000.0, square_corner_velocity_mm_s=5.0)
    mv = _corner_plan((50.0, 50.0), p)
    assert mv[0].end_v_mm_s == pytest.approx(5.0, rel=1e-9)
    assert mv[1].start_v_mm_s == pytest.approx(5.0, rel=1e-9)
    total = trap_time(50, 0, 100, 5, 1000) + trap_time(50, 5, 100, 0, 1000)
    assert mv[-1].t_end_s == pytest.approx(total, rel=1e-12)


def test_135_degree_corner_follows_the_junction_deviation_formula():
    a, scv = 1000.0, 5.0
    p = prof(max_accel_mm_s2=a, square_corner_velocity_mm_s=scv)
    ang = math.radians(45.0)  # direction change 45 deg: the corner's interior angle is 135 deg
    mv = _corner_plan((50 + 50 * math.cos(ang), 50 * math.sin(ang)), p)
    jd = scv ** 2 * (math.sqrt(2) - 1) / a
    s = math.sin(math.radians(135.0) / 2)
    v = math.sqrt(a * jd * s / (1 - s))
    assert v == pytest.approx(11.21, abs=0.01)
    assert mv[1].start_v_mm_s == pytest.approx(v, rel=1e-9)


def test_junction_function_cases():
    a = 1000.0
    jd = klipper_junction_deviation(5.0, a)
    dv = 2 * 50 * a
    assert klipper_corner_v2(0.0, jd, a, dv, jd, a, dv) == pytest.approx(25.0)  # 90 deg
    assert klipper_corner_v2(1.0, jd, a, dv, jd, a, dv) == 0.0  # reversal
    assert klipper_corner_v2(-1.0, jd, a, dv, jd, a, dv) == math.inf  # straight on
    # short moves: the circle must touch each move before its middle (centripetal limit)
    short = 2 * 0.02 * a
    assert klipper_corner_v2(0.0, jd, a, short, jd, a, dv) == pytest.approx(0.25 * short * 1.0)


def test_centripetal_limit_in_a_plan():
    p = prof(max_accel_mm_s2=1000.0, square_corner_velocity_mm_s=5.0)
    mv, _ = plan("G1 X0.02 F6000\nG1 X0.02 Y0.02\n", p)
    assert mv[1].start_v_mm_s == pytest.approx(math.sqrt(0.5 * 0.02 * 1000.0), rel=1e-9)


def test_straight_continuation_keeps_speed_and_reversal_stops():
    mv, _ = plan("G1 X50 F6000\nG1 X100\n", prof(max_accel_mm_s2=1000.0))
    assert mv[0].end_v_mm_s == pytest.approx(100.0) and mv[1].start_v_mm_s == pytest.approx(100.0)
    mv, _ = plan("G1 X50 F6000\nG1 X0\n", prof(max_accel_mm_s2=1000.0))
    assert mv[0].end_v_mm_s == 0.0 and mv[1].start_v_mm_s == 0.0


def test_extruder_instantaneous_corner_velocity():
    p = prof(max_accel_mm_s2=1000.0, instantaneous_corner_velocity_mm_s=1.0)
    mv, _ = plan("G1 X50 E2.5 F6000\nG1 X100\n", p)  # extrusion ratio 0.05 -> 0
    assert mv[1].start_v_mm_s == pytest.approx(1.0 / 0.05, rel=1e-9)


def test_extrude_only_moves_use_their_own_limits_and_stop_the_neighbours():
    p = prof(max_extrude_only_velocity_mm_s=40.0, max_extrude_only_accel_mm_s2=800.0)
    mv, _ = plan("G1 X20 E1 F6000\nG1 E-2 F6000\nG1 X40 E3\n", p)
    assert [m.kind for m in mv] == ["move", "extrude", "move"]
    r = mv[1]
    assert r.cruise_v_mm_s == 40.0 and r.accel_mm_s2 == 800.0 and r.unit == (0.0, 0.0, 0.0, -1.0)
    assert r.distance_mm == 3.0
    assert r.duration_s == pytest.approx(trap_time(3.0, 0, 40, 0, 800), rel=1e-12)
    assert mv[0].end_v_mm_s == 0.0 and mv[2].start_v_mm_s == 0.0


def test_retraction_with_xy_travel_is_limited_by_the_extruder():
    p = prof(max_extrude_only_accel_mm_s2=500.0, max_extrude_only_velocity_mm_s=5.0)
    mv, _ = plan("G1 X10 E-1 F6000\n", p)  # axis ratio 0.1: v <= 50, a <= 5000
    assert mv[0].cruise_v_mm_s == pytest.approx(50.0) and mv[0].accel_mm_s2 == pytest.approx(5000.0)


def test_extrude_only_distance_limit():
    with pytest.raises(GcodeError, match="Extrude only move too long"):
        plan("G1 E60 F600\n")
    mv, _ = plan("G1 E60 F600\n", max_extrude_only_distance_mm=None)
    assert mv[0].distance_mm == 60.0


# ---------------------------------------------------------------- delta limits

def test_z_moves_are_limited_by_z_ratio():
    p = prof(max_z_velocity_mm_s=50.0, max_z_accel_mm_s2=500.0)
    mv, _ = plan("G1 Z10 F30000\n", p)
    assert mv[0].cruise_v_mm_s == 50.0 and mv[0].accel_mm_s2 == 500.0
    # 30 deg slope: d = 20, dz = 10, z_ratio = 2
    mv, _ = plan(f"G1 X{10 * math.sqrt(3):.15f} Z10 F30000\n", p)
    assert mv[0].distance_mm == pytest.approx(20.0)
    assert mv[0].cruise_v_mm_s == pytest.approx(100.0, rel=1e-9)
    assert mv[0].accel_mm_s2 == pytest.approx(1000.0, rel=1e-9)


def test_moves_far_out_are_slowed_like_klipper():
    geo = {"arm_length_mm": (250.0,) * 3, "delta_radius_mm": (150.0,) * 3, "print_radius_mm": 99.0}
    p = prof(geometry=geo, max_velocity_mm_s=300.0, max_accel_mm_s2=4000.0)
    from ffcomp.gcode.klipper import KlipperDelta

    kin = KlipperDelta(p, 300.0, 4000.0)
    slow, very_slow = math.sqrt(kin.slow_xy2), math.sqrt(kin.very_slow_xy2)
    h = 0.5 / p.limits.steps_per_mm
    assert slow == pytest.approx(3 * math.sqrt(250 ** 2 / 10 - h * h) + h - 150)
    assert very_slow == pytest.approx(6 * math.sqrt(250 ** 2 / 37 - h * h) + h - 150)
    assert slow < 89 < very_slow < 98
    mv, _ = plan("G1 X80 F18000\nG1 X89\nG1 X98\nG1 X0\n", p)
    assert mv[0].cruise_v_mm_s == 300.0 and mv[0].accel_mm_s2 == 4000.0
    assert mv[1].cruise_v_mm_s == 150.0 and mv[1].accel_mm_s2 == 2000.0
    assert mv[2].cruise_v_mm_s == 75.0 and mv[2].accel_mm_s2 == 1000.0
    assert mv[3].cruise_v_mm_s == 75.0  # starts far out


def test_out_of_range_moves_raise_naming_the_line():
    with pytest.raises(KinematicsError, match=r"x\.gcode:3: Move out of range: 110\.000 80\.000"):
        plan("G1 X10 F600\n; comment\nG1 X110 Y80\n", path="x.gcode")
    with pytest.raises(KinematicsError, match=":1: Move out of range"):
        plan("G1 Z-1\n")
    with pytest.raises(KinematicsError, match=":2:"):
        plan("G28\nG1 Z301\n")


# ---------------------------------------------------------------- limit commands and overrides

def test_set_velocity_limit_mid_file():
    text = """G1 X50 F6000
G1 X0
SET_VELOCITY_LIMIT ACCEL=2000
G1 X50
SET_VELOCITY_LIMIT VELOCITY=40
G1 X0
SET_VELOCITY_LIMIT VELOCITY=300 SQUARE_CORNER_VELOCITY=10
G1 X50
G1 X50 Y50
SET_VELOCITY_LIMIT MINIMUM_CRUISE_RATIO=0 ACCEL=1000
G1 X50 Y40 F60000
SET_VELOCITY_LIMIT ACCEL_TO_DECEL=250
G1 X50 Y50
"""
    mv, _ = plan(text, prof(max_accel_mm_s2=1000.0))
    assert mv[0].accel_mm_s2 == 1000.0 and mv[1].accel_mm_s2 == 1000.0
    assert mv[2].accel_mm_s2 == 2000.0
    assert mv[3].cruise_v_mm_s == 40.0
    jd = klipper_junction_deviation(10.0, 2000.0)
    assert mv[4].end_v_mm_s == pytest.approx(math.sqrt(jd * 2000.0 / (math.sqrt(2) - 1)), rel=1e-9)
    assert mv[4].end_v_mm_s == pytest.approx(10.0, rel=1e-9)
    assert mv[6].cruise_v_mm_s == pytest.approx(math.sqrt(10 * 1000.0), rel=1e-9)  # ratio 0: triangle
    # ACCEL_TO_DECEL=250 at ACCEL=1000 means a minimum cruise ratio of 0.75
    assert mv[7].cruise_v_mm_s == pytest.approx(math.sqrt(10 * 1000.0 * 0.25), rel=1e-9)


def test_m204_rules():
    mv, pl = plan("M204 S2500\nG1 X10 F600\nM204 P1000 T800\nG1 X20\nM204 P300\nG1 X30\n")
    assert [m.accel_mm_s2 for m in mv] == [2500.0, 800.0, 800.0]  # P alone is ignored by Klipper
    assert pl.planner.ignored_commands == 1
    mv, pl = plan("M201 X100\nM203 X1\nM205 J0.5\nG1 X10 F600\n")
    assert mv[0].accel_mm_s2 == BASE.limits.max_accel_mm_s2 and pl.planner.ignored_commands == 3


def test_speed_and_flow_overrides():
    mv, _ = plan("G1 X50 E1 F6000\nM220 S50\nM221 S150\nG1 X100 E2\n", prof(max_accel_mm_s2=1000.0))
    assert mv[0].cruise_v_mm_s == 100.0 and mv[1].cruise_v_mm_s == 50.0
    assert mv[1].end_mm[3] - mv[1].start_mm[3] == pytest.approx(1.5)


# ---------------------------------------------------------------- time line

def test_dwell_total_time_and_contiguity():
    text = "G1 X10 F3000\nG1 Y10\nG4 P750\nG1 X0\nM400\nG1 Y0\nM84\n"
    mv, pl = plan(text)
    kinds = [m.kind for m in mv]
    assert kinds == ["move", "move", "dwell", "move", "move", "dwell", "dwell"]
    for a, b in zip(mv, mv[1:], strict=False):
        assert b.t_start_s == pytest.approx(a.t_end_s, abs=1e-12)
        assert b.start_mm == a.end_mm
    assert mv[1].end_v_mm_s == 0.0  # the dwell flushes: the move before it stops
    assert mv[2].cruise_t_s == 0.75 and mv[2].lineno == 3
    assert sum(m.duration_s for m in mv) == pytest.approx(pl.planner.print_time, rel=1e-12)
    assert mv[-1].duration_s == pytest.approx(0.1)  # M84: Klipper dwells 2 x 0.1 s


def test_relative_moves_and_zero_length_moves():
    mv, _ = plan("G91\nG1 X10 F600\nG1 X0\nG1 Y5\nG1 E0\n")
    assert [m.end_mm[:2] for m in mv] == [(10.0, 0.0), (10.0, 5.0)]


def test_lookahead_memory_is_bounded_and_lazy_flush_matches_a_full_plan(monkeypatch, rng):
    pts = rng.uniform(-60, 60, size=(3000, 2))
    text = "".join(f"G1 X{x:.3f} Y{y:.3f} E{i * 0.01:.3f} F{rng.choice([1800, 6000, 12000])}\n"
                   for i, (x, y) in enumerate(pts))
    pl = plan_gcode(text.splitlines(keepends=True), BASE)
    longest = 0
    lazy = []
    for m in pl:
        longest = max(longest, len(pl.planner.queue))
        lazy.append(m)
    assert longest < 200
    # with flushing postponed to the end, the plan sees the whole file at once
    monkeypatch.setattr(kmod, "LOOKAHEAD_FLUSH_TIME", 1e9)
    monkeypatch.setattr(kmod, "BUFFER_TIME_HIGH", 1e9)
    full, _ = plan(text)
    assert len(full) == len(lazy)
    t_lazy = np.array([m.t_end_s for m in lazy])
    t_full = np.array([m.t_end_s for m in full])
    assert np.allclose(t_lazy, t_full, rtol=1e-12, atol=1e-9)


def test_marlin_dialect_is_picked_from_the_profile():
    _, pl = plan("G1 X10 F600\n", prof(planner="marlin"))
    assert pl.firmware == "marlin" and pl.planner.name == "marlin"


def test_unknown_planner_or_dialect_is_rejected():
    from ffcomp.gcode import GcodeParser, make_planner

    with pytest.raises(ValueError, match="unknown planner 'reprap'"):
        make_planner(BASE, firmware="reprap")
    with pytest.raises(ValueError, match="unknown planner"):
        plan_gcode([], BASE, firmware="reprap")
    with pytest.raises(ValueError, match="dialect"):
        GcodeParser([], dialect="reprap")
