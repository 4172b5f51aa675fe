"""Hypothesis properties on random polylines, for every planner variant: limits, continuity, end point."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from ffcomp.gcode import PLANNERS, LinearMove, parse_text, plan_gcode
from ffcomp.gcode.sampler import sample_all
from ffcomp.profile import default_profile

BASE = default_profile()
GEOM = BASE.geometry_si()
FS = 250.0

point = st.tuples(st.floats(-80, 80), st.floats(-80, 80), st.floats(0.2, 4.0))
feed = st.sampled_from([600.0, 1200.0, 3000.0, 6000.0, 12000.0, 30000.0])
step = st.tuples(point, feed, st.floats(-0.5, 2.0), st.booleans())
limits = st.fixed_dictionaries({
    "max_velocity_mm_s": st.floats(40.0, 400.0),
    "max_accel_mm_s2": st.floats(300.0, 20000.0),
    "max_z_velocity_mm_s": st.floats(5.0, 400.0),
    "max_z_accel_mm_s2": st.floats(100.0, 20000.0),
    "square_corner_velocity_mm_s": st.floats(0.0, 20.0),
    "minimum_cruise_ratio": st.floats(0.0, 0.9),
    "junction_deviation_mm": st.floats(0.005, 0.2),
    "max_extrude_only_velocity_mm_s": st.floats(10.0, 120.0),
    "max_extrude_only_accel_mm_s2": st.floats(300.0, 5000.0),
})


def _program(steps) -> str:
    out = ["G90\nM83\n"]
    for (x, y, z), f, de, wipe in steps:
        out.append(f"G1 X{x:.3f} Y{y:.3f} Z{z:.3f} E{de:.4f} F{f:.0f}\n")
        if wipe:
            out.append(f"G1 E{-abs(de):.4f} F2400\n")
    return "".join(out)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(step, min_size=1, max_size=12), limits, st.sampled_from(sorted(PLANNERS)))
@example(steps=[((0.0, 0.0, 1.0), 600.0, 0.0, False), ((0.0, 0.0, 1.0), 600.0, 0.0, False),
                ((0.0, 0.0, 0.25), 6000.0, 0.0, False)],
         lim={"max_velocity_mm_s": 40.0, "max_accel_mm_s2": 7894.0, "max_z_velocity_mm_s": 70.0,
              "max_z_accel_mm_s2": 7894.0, "square_corner_velocity_mm_s": 0.0, "minimum_cruise_ratio": 0.0,
              "junction_deviation_mm": 0.125, "max_extrude_only_velocity_mm_s": 10.0,
              "max_extrude_only_accel_mm_s2": 300.0},
         firmware="marlin")  # a Marlin z-only move at max_z_velocity > sqrt(3) max_velocity
def test_random_polylines_respect_limits_and_end_where_the_gcode_ends(steps, lim, firmware):
    prof = replace(BASE, limits=replace(BASE.limits, planner=firmware, **lim))
    text = _program(steps)
    recs = parse_text(text, dialect=firmware)
    last = [r.op for r in recs if isinstance(r.op, LinearMove)][-1].end
    moves = list(plan_gcode(text.splitlines(keepends=True), prof, max_extrude_only_distance_mm=None))
    assert moves, text

    if firmware == "klipper":  # Klipper limits the speed along the path
        vmax = max(lim["max_velocity_mm_s"], lim["max_extrude_only_velocity_mm_s"])
        amax = max(lim["max_accel_mm_s2"], lim["max_extrude_only_accel_mm_s2"])
    else:  # Marlin: per-axis limits on x and y, and z's own (a z-only move may outrun max_velocity)
        vmax = math.hypot(math.sqrt(2.0) * max(lim["max_velocity_mm_s"], lim["max_extrude_only_velocity_mm_s"]),
                          lim["max_z_velocity_mm_s"])
        amax = math.hypot(math.sqrt(2.0) * max(lim["max_accel_mm_s2"], lim["max_extrude_only_accel_mm_s2"]),
                          lim["max_z_accel_mm_s2"])
    # Marlin starts a block at no less than its minimum planner speed sqrt(a / 2 steps_per_mm), which
    # may exceed the previous block's exit ("rarely ... but that's ok" in planner.cpp)
    dv_ok = 1e-9 if firmware == "klipper" else math.sqrt(0.5 * amax / BASE.limits.steps_per_mm)
    for a, b in zip(moves, moves[1:], strict=False):
        assert b.t_start_s == a.t_end_s or math.isclose(b.t_start_s, a.t_end_s, abs_tol=1e-9)
        assert b.start_mm == a.end_mm
        assert abs(a.end_v_mm_s - b.start_v_mm_s) <= dv_ok * (1 + 1e-9) + 1e-9 * a.end_v_mm_s
    for m in moves:
        tol = 1e-9 * max(1.0, m.cruise_v_mm_s)
        assert m.start_v_mm_s <= m.cruise_v_mm_s + tol and m.end_v_mm_s <= m.cruise_v_mm_s + tol
        assert min(m.accel_t_s, m.cruise_t_s, m.decel_t_s) >= -1e-9
        if m.kind == "move":
            # Klipper limits the speed along the path; Marlin each axis component
            along = 1.0 if firmware == "klipper" else max(abs(u) for u in m.unit[:2])
            assert m.cruise_v_mm_s * along <= lim["max_velocity_mm_s"] * (1 + 1e-12)
            assert m.accel_mm_s2 * along <= lim["max_accel_mm_s2"] * (1 + 1e-12)
            dz = abs(m.end_mm[2] - m.start_mm[2])
            if dz > 1e-9 and firmware == "klipper":
                zr = dz / m.distance_mm  # the Z component obeys the Z limits
                vz = min(lim["max_z_velocity_mm_s"], lim["max_velocity_mm_s"])
                az = min(lim["max_z_accel_mm_s2"], lim["max_accel_mm_s2"])
                assert m.cruise_v_mm_s * zr <= vz * (1 + 1e-9)
                assert m.accel_mm_s2 * zr <= az * (1 + 1e-9)
        # the distance covered by the trapezoid is the move's length
        d = m.accel_d_mm + m.cruise_v_mm_s * m.cruise_t_s + m.decel_d_mm
        assert math.isclose(d, m.distance_mm, rel_tol=1e-9, abs_tol=1e-9)
    assert np.allclose(moves[-1].end_mm, last, atol=1e-9)

    s = sample_all(moves, GEOM, fs_hz=FS)
    speed = np.linalg.norm(s.v_m_s, axis=1) * 1e3
    acc = np.linalg.norm(s.a_m_s2, axis=1) * 1e3
    cruise = np.array([m.cruise_v_mm_s for m in moves])[s.move_index]
    accel = np.array([m.accel_mm_s2 for m in moves])[s.move_index]
    assert np.all(speed <= cruise * (1 + 1e-9) + 1e-9)
    assert np.all(speed <= vmax * (1 + 1e-9))
    assert np.all(acc <= accel * (1 + 1e-9) + 1e-9)
    assert np.all(acc <= amax * (1 + 1e-9))
    # continuity: no sample jumps further than the top speed allows in one period
    step_mm = np.linalg.norm(np.diff(s.xyz_m, axis=0), axis=1) * 1e3
    assert np.all(step_mm <= vmax / FS * (1 + 1e-6) + 1e-9)
    e_rate = max(abs(m.unit[3]) * m.cruise_v_mm_s for m in moves)
    assert np.all(np.abs(np.diff(s.e_mm)) <= e_rate / FS * (1 + 1e-6) + 1e-9)
    assert np.allclose(s.xyz_m[-1] * 1e3, last[:3], atol=1e-9)
    assert math.isclose(s.e_mm[-1], last[3], abs_tol=1e-9)
    assert s.t_s[-1] >= moves[-1].t_end_s - 1e-9
