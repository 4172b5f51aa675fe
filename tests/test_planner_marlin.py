"""Marlin planner: junction deviation, small segments, buffer-limited lookahead, M201/M203/M204/M205."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest

from ffcomp.gcode import plan_gcode
from ffcomp.gcode.junction import marlin_corner_v2, marlin_fast_acos_neg
from ffcomp.profile import default_profile

BASE = default_profile()


def prof(**limits):
    limits.setdefault("planner", "marlin")
    return replace(BASE, limits=replace(BASE.limits, **limits))


def plan(text, profile=None, **kw):
    pl = plan_gcode(text.splitlines(keepends=True), profile or prof(), **kw)
    return list(pl), pl


def jd_speed(a, jd, theta_deg):
    s = math.sin(math.radians(theta_deg) / 2)
    return math.sqrt(a * jd * s / (1 - s))


def test_fast_acos_is_close_to_acos():
    for t in (-0.99, -0.9, -0.8, -0.72):
        assert marlin_fast_acos_neg(t) == pytest.approx(math.acos(-t), abs=0.035)


@pytest.mark.parametrize("theta_deg", [90.0, 135.0])
def test_corner_speed_follows_junction_deviation(theta_deg):
    a, jd = 2000.0, 0.05
    p = prof(max_accel_mm_s2=a, junction_deviation_mm=jd)
    turn = math.radians(180.0 - theta_deg)
    x2, y2 = 50 + 50 * math.cos(turn), 50 * math.sin(turn)
    mv, _ = plan(f"G1 X50 F6000\nG1 X{x2:.12f} Y{y2:.12f}\n", p)
    v = jd_speed(a, jd, theta_deg)
    assert mv[1].start_v_mm_s == pytest.approx(v, rel=1e-9)
    assert mv[0].end_v_mm_s == pytest.approx(v, rel=1e-9)
    c = -math.cos(turn)  # junction_cos_theta = -(u_prev . u)
    assert marlin_corner_v2(c, a, jd, 50.0) == pytest.approx(v * v, rel=1e-9)


def test_small_segments_use_the_arc_estimate():
    a, jd = 2000.0, 0.05
    theta = math.radians(170.0)
    c = math.cos(theta)  # a 10 deg turn between 0.5 mm segments
    jd_only = a * jd * math.sin(theta / 2) / (1 - math.sin(theta / 2))
    v2 = marlin_corner_v2(c, a, jd, 0.5)
    assert v2 == pytest.approx(0.5 * a / marlin_fast_acos_neg(c))
    assert v2 < jd_only
    assert marlin_corner_v2(c, a, jd, 0.5, small_segments=False) == pytest.approx(jd_only)
    assert marlin_corner_v2(0.9999999, a, jd, 10.0, min_planner_v2=3.0) == 3.0  # reversal


def test_single_move_trapezoid_and_minimum_planner_speed():
    p = prof(max_accel_mm_s2=1000.0, steps_per_mm=80.0)
    mv, _ = plan("G1 X100 F6000\n", p)
    (m,) = mv
    vmin = math.sqrt(0.5 * 1000.0 / 80.0)  # Marlin's minimum_planner_speed_sqr = 0.5 a / steps_per_mm
    assert m.start_v_mm_s == pytest.approx(vmin) and m.end_v_mm_s == 0.0
    assert m.cruise_v_mm_s == 100.0
    expect = (100 - vmin) / 1000 + 100 / 1000 + (100 - (100 ** 2 - vmin ** 2) / 2000 - 100 ** 2 / 2000) / 100
    assert m.duration_s == pytest.approx(expect, rel=1e-12)


def test_limit_commands():
    text = """M201 X500 Y500
M203 X40 Y40
G1 X50 F6000
G1 X0
M204 P800 T700 R300
G1 X50 E1
G1 X0
G1 E0
M205 J0.2
SET_VELOCITY_LIMIT ACCEL=100
G1 X50 E2
G1 X50 Y50 E3
"""
    mv, pl = plan(text, prof(max_accel_mm_s2=3000.0))
    assert mv[0].accel_mm_s2 == 500.0 and mv[0].cruise_v_mm_s == 40.0
    assert mv[2].accel_mm_s2 == 500.0  # print accel 800, limited by M201 X500
    assert mv[4].kind == "extrude" and mv[4].accel_mm_s2 == 300.0  # retract acceleration
    assert pl.planner.junction_deviation == 0.2 and pl.planner.ignored_commands == 1
    mv2, _ = plan("M204 P800 T700\nG1 X50 F6000\nG1 X0 E1\n", prof(max_accel_mm_s2=3000.0))
    assert mv2[0].accel_mm_s2 == 700.0 and mv2[1].accel_mm_s2 == 800.0


def test_lookahead_is_limited_to_the_block_buffer():
    # 1 mm collinear segments: a 16-block buffer sees only ~14 mm ahead, so the speed stays low
    p = prof(max_accel_mm_s2=1000.0)
    text = "".join(f"G1 X{i - 100}.0 F24000\n" for i in range(0, 201))
    mv, _ = plan(text, p)
    peak = max(m.cruise_v_mm_s for m in mv[1:])  # mv[0] is the 100 mm move to the start
    assert peak <= math.sqrt(2 * 1000.0 * 14) + 1e-6
    mv_big, _ = plan(text, p, block_buffer_size=512)
    assert max(m.cruise_v_mm_s for m in mv_big[1:]) == pytest.approx(300.0)
    assert mv_big[-1].t_end_s < mv[-1].t_end_s


def test_tiny_collinear_segments_are_slowed_by_the_small_segment_rule():
    # Marlin's JD_HANDLE_SMALL_SEGMENTS: v^2 <= L a / theta, and theta bottoms out at ~0.033 rad
    p = prof(max_accel_mm_s2=1000.0)
    text = "".join(f"G1 X{0.1 * i:.1f} F6000\n" for i in range(1, 401))
    mv, _ = plan(text, p, block_buffer_size=512)
    cap = math.sqrt(0.1 * 1000.0 / marlin_fast_acos_neg(-1.0))
    assert max(m.cruise_v_mm_s for m in mv) == pytest.approx(cap, rel=0.05)
    mv2, _ = plan(text, p, block_buffer_size=512, small_segments=False)
    assert max(m.cruise_v_mm_s for m in mv2) > 90.0


def test_profile_and_continuity():
    mv, pl = plan("G1 X10 Y10 E1 F3000\nG1 X20 Y0 E2\nG4 S1\nG1 X0 E3\nG1 X-10 Y5\n")
    for a, b in zip(mv, mv[1:], strict=False):
        assert b.t_start_s == pytest.approx(a.t_end_s, abs=1e-12)
        assert b.start_mm == a.end_mm
        assert b.start_v_mm_s == pytest.approx(a.end_v_mm_s, rel=1e-9, abs=1e-9) or a.kind == "dwell" \
            or b.kind == "dwell"
    assert [m.kind for m in mv].count("dwell") == 1
    assert sum(m.duration_s for m in mv) == pytest.approx(pl.planner.print_time)


def test_targets_outside_the_printable_radius_are_clamped():
    mv, pl = plan("G1 X200 Y0 F6000\n")
    assert mv[0].end_mm[0] == pytest.approx(BASE.geometry.print_radius_mm)
    assert pl.planner.clamped == 1
