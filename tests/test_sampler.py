"""Sampler: exact evaluation on the global grid, blocks and overlap, mapping back to moves, IK."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ffcomp.errors import KinematicsError
from ffcomp.gcode import plan_gcode
from ffcomp.gcode.sampler import concat_blocks, sample_all, sample_blocks, sample_gcode
from ffcomp.kinematics import inverse
from ffcomp.profile import default_profile

BASE = default_profile()
GEOM = BASE.geometry_si()


def prof(**limits):
    return replace(BASE, limits=replace(BASE.limits, **limits))


def lines(text):
    return text.splitlines(keepends=True)


def test_single_move_samples_match_the_closed_form():
    p = prof(max_accel_mm_s2=1000.0)
    moves = list(plan_gcode(lines("G1 X100 F6000\n"), p))
    s = sample_all(moves, GEOM, fs_hz=1000.0)
    t = s.t_s
    assert t[0] == 0.0 and len(t) == math.ceil(1.1 * 1000) + 1
    assert np.array_equal(t, np.arange(len(t)) / 1000.0)
    a, v = 1000.0, 100.0
    x = np.where(t < 0.1, 0.5 * a * t ** 2,
                 np.where(t < 1.0, 5.0 + v * (t - 0.1), 95.0 + v * (t - 1.0) - 0.5 * a * (t - 1.0) ** 2))
    x = np.where(t >= 1.1, 100.0, x)
    vx = np.where(t < 0.1, a * t, np.where(t < 1.0, v, np.maximum(v - a * (t - 1.0), 0.0)))
    ax = np.where(t < 0.1, a, np.where(t < 1.0, 0.0, np.where(t < 1.1, -a, 0.0)))
    assert np.allclose(s.xyz_m[:, 0] * 1e3, x, atol=1e-9)
    assert np.allclose(s.v_m_s[:, 0] * 1e3, vx, atol=1e-9)
    assert np.allclose(s.a_m_s2[:, 0] * 1e3, ax, atol=1e-9)
    assert np.all(s.xyz_m[:, 1:] == 0.0)
    assert np.allclose(s.q_m, inverse(GEOM, s.xyz_m), atol=1e-15)
    assert tuple(s.xyz_m[-1] * 1e3) == (100.0, 0.0, 0.0)


def test_extruder_samples_and_move_mapping():
    text = "G1 X10 E1 F3000\n; comment\nG1 E0.2 F1800\nG4 P100\nG1 X0 E1\n"
    moves = list(plan_gcode(lines(text), BASE))
    s = sample_all(moves, GEOM, fs_hz=2000.0)
    assert set(np.unique(s.lineno)) == {1, 3, 4, 5}
    assert set(np.unique(s.move_index)) == {0, 1, 2, 3}
    for m in moves:
        sel = s.move_index == m.index
        assert np.all(s.lineno[sel] == m.lineno)
        assert np.all((s.t_s[sel] >= m.t_start_s - 1e-12) & (s.t_s[sel] <= m.t_end_s + 1e-12))
    assert s.e_mm[0] == 0.0 and s.e_mm[-1] == pytest.approx(1.0)
    retract = s.move_index == 1
    assert np.all(np.diff(s.e_mm[retract]) <= 1e-12)  # E goes back during the retraction
    dwell = s.move_index == 2
    assert np.all(s.v_m_s[dwell] == 0.0) and np.ptp(s.e_mm[dwell]) == 0.0


@settings(max_examples=25, deadline=None)
@given(block_len=st.integers(16, 700), overlap_frac=st.floats(0.0, 0.9),
       fs=st.sampled_from([500.0, 1000.0, 1234.5]))
def test_streamed_blocks_concatenate_to_sample_all(block_len, overlap_frac, fs):
    overlap = min(int(block_len * overlap_frac), block_len - 1)
    text = "G1 X10 Y5 E1 F3000\nG1 X-10 Y20 E2\nG4 P30\nG1 E1.5 F1800\nG1 X0 Y0 Z2 F6000\n"
    moves = list(plan_gcode(lines(text), BASE))
    whole = sample_all(moves, GEOM, fs_hz=fs)
    blocks = list(sample_blocks(iter(moves), GEOM, fs_hz=fs, block_len=block_len, overlap=overlap))
    assert blocks[-1].last and not any(b.last for b in blocks[:-1])
    for i, b in enumerate(blocks):
        assert b.overlap == (0 if i == 0 else overlap)
        assert b.k0 == i * (block_len - overlap)
        if i:
            prev = blocks[i - 1]
            assert np.array_equal(b.xyz_m[:overlap], prev.xyz_m[len(prev) - overlap:])
    cat = concat_blocks(blocks)
    for f in ("t_s", "xyz_m", "v_m_s", "a_m_s2", "e_mm", "q_m", "move_index", "lineno"):
        assert np.array_equal(getattr(cat, f), getattr(whole, f)), f


def test_streaming_pulls_moves_lazily():
    pulled = []
    text = "".join(f"G1 X{(i % 2) * 20} Y{i % 7} F6000\n" for i in range(400))
    moves = plan_gcode(lines(text), BASE)

    def counting():
        for m in moves:
            pulled.append(m.index)
            yield m

    it = sample_blocks(counting(), GEOM, fs_hz=1000.0, block_len=256, overlap=32)
    first = next(it)
    assert len(first) == 256
    assert len(pulled) < 100  # only the moves covering the first ~0.26 s


def test_sample_gcode_and_kinematics_error(tmp_path):
    f = tmp_path / "a.gcode"
    f.write_text("G1 X10 F600\nG1 Y10\n")
    blocks = list(sample_gcode(f, BASE, block_len=512, overlap=64))
    assert blocks[-1].fs_hz == BASE.limits.sample_rate_hz
    # Marlin does not check the workspace but clamps to the print radius; a short-armed geometry makes
    # the clamped point unreachable for the inverse kinematics
    g = replace(BASE.geometry, arm_length_mm=(200.0,) * 3)
    p = replace(BASE, geometry=g, limits=replace(BASE.limits, planner="marlin"))
    f.write_text("G1 X10 F600\nG1 X130 Y0\n")
    with pytest.raises(KinematicsError, match=r"a\.gcode:2: .*out of the arms' reach"):
        list(sample_gcode(f, p))


def test_empty_program_gives_one_sample():
    s = sample_all([], GEOM, fs_hz=1000.0)
    assert len(s) == 1 and s.last


def test_bad_arguments():
    with pytest.raises(ValueError):
        list(sample_blocks([], GEOM, fs_hz=1000.0, block_len=10, overlap=10))
    with pytest.raises(ValueError):
        list(sample_blocks([], GEOM, fs_hz=0.0))


def test_planned_move_helpers_agree_with_the_sampler():
    text = "G1 X10 Y5 E1 F3000\nG1 X-10 Y20 E2\nG1 Z3 F600\n"
    moves = list(plan_gcode(lines(text), BASE))
    s = sample_all(moves, GEOM, fs_hz=1000.0)
    for k in range(0, len(s), 37):
        m = moves[s.move_index[k]]
        t = s.t_s[k]
        assert np.allclose(np.array(m.position_at(t))[:3], s.xyz_m[k] * 1e3, atol=1e-9)
        assert m.position_at(t)[3] == pytest.approx(s.e_mm[k], abs=1e-9)
        assert m.speed_at(t) == pytest.approx(np.linalg.norm(s.v_m_s[k]) * 1e3, abs=1e-9)
