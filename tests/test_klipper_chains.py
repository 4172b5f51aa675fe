"""The chain planner (runs of straight moves planned vectorised) against the move-by-move planner."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ffcomp.errors import GcodeError, KinematicsError
from ffcomp.gcode import klipper_chains
from ffcomp.gcode.klipper_chains import MoveBlock
from ffcomp.gcode.planner import GcodePlan
from ffcomp.profile import load_profile

OTHER = "samples/profiles/other_delta.toml"


def _flat(lines, profile, chains):
    """Every planned item as rows (line, kind, start time, duration, start / cruise / end speed,
    acceleration, start x y z e), blocks unrolled; and the planner."""
    plan = GcodePlan(lines, profile, path="t.gcode", chains=chains, start_position_mm=(0.0, 0.0, 5.0, 0.0))
    rows = []
    for m in plan:
        if isinstance(m, MoveBlock):
            dur = m.accel_t + m.cruise_t + m.decel_t
            for i in range(len(m)):
                rows.append((m.lineno[i], "move", m.t_start[i], dur[i], m.start_v[i], m.cruise_v[i], m.end_v[i],
                             m.accel[i], *m.start[i]))
        else:
            rows.append((m.lineno, m.kind, m.t_start_s, m.duration_s, m.start_v_mm_s, m.cruise_v_mm_s,
                         m.end_v_mm_s, m.accel_mm_s2 if m.kind != "dwell" else 0.0, *m.start_mm))
    return rows, plan.planner


def _assert_same(lines, profile):
    want, _ = _flat(lines, profile, False)
    got, planner = _flat(lines, profile, True)
    assert [r[:2] for r in got] == [r[:2] for r in want]
    if want:
        a = np.array([r[2:] for r in want], float)
        b = np.array([r[2:] for r in got], float)
        np.testing.assert_allclose(b, a, rtol=1e-9, atol=1e-8)
    return planner


#: the other lines of a random file: (share of all lines, maker(rng, position))
_OTHER_LINES = [
    (0.08, lambda rng, p: f"G1 E{rng.choice([-0.8, 0.8, 0.05]):.5f} F{rng.choice([1800, 2400]):d}"),
    (0.05, lambda rng, p: f"G4 P{rng.choice([0, 1, 20]):d}"),
    (0.04, lambda rng, p: f"SET_VELOCITY_LIMIT ACCEL={rng.choice([2000, 5000, 20000]):d}"),
    (0.02, lambda rng, p: f"SET_VELOCITY_LIMIT MINIMUM_CRUISE_RATIO={rng.choice([0, 0, 0.5]):g}"),
    (0.02, lambda rng, p: f"M204 S{rng.choice([1500, 8000]):d}"),
    (0.02, lambda rng, p: "M400"),
    (0.02, lambda rng, p: f"G1 X{p[0]:.4f} Y{p[1]:.4f} Z{p[2]:.4f} F6000"),  # a zero-length move
    (0.02, lambda rng, p: "G92 E0"),
    (0.03, lambda rng, p: "; a comment"),
]


def _random_file(rng, n, radius, mcr, z_share):
    """A file of the kinds of lines a compensated output holds (and some it does not): 70 % moves."""
    lines = [f"SET_VELOCITY_LIMIT ACCEL={rng.choice([3000, 10000, 1e5]):g} MINIMUM_CRUISE_RATIO={mcr:g} "
             f"SQUARE_CORNER_VELOCITY={rng.choice([5, 20, 100]):g}", "M83"]
    p = np.array([0.0, 0.0, 5.0])
    edges = 0.70 + np.cumsum([share for share, _ in _OTHER_LINES])
    for _ in range(n):
        u = rng.random()
        if u >= 0.70:
            k = min(int(np.searchsorted(edges, u, side="right")), len(_OTHER_LINES) - 1)
            lines.append(_OTHER_LINES[k][1](rng, p))
            continue
        step = rng.normal(size=3) * rng.uniform(0.01, 3.0)
        step[2] *= z_share
        p = np.round(p + step, 4)
        p[:2] = np.clip(p[:2], -0.6 * radius, 0.6 * radius)
        p[2] = np.clip(p[2], 0.3, 150.0)
        e = f" E{rng.uniform(-0.05, 0.2):.5f}" if rng.random() < 0.7 else ""
        lines.append(f"G1 X{p[0]:.4f} Y{p[1]:.4f} Z{p[2]:.4f}{e} F{rng.uniform(3, 300) * 60:.3f}")
    return lines


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 120), mcr=st.sampled_from([0.0, 0.0, 0.5]),
       z_share=st.sampled_from([0.0, 0.05, 1.0]), other=st.booleans())
def test_the_chain_planner_plans_as_the_klipper_planner(seed, n, mcr, z_share, other, profile):
    prof = load_profile(OTHER) if other else profile
    lines = _random_file(np.random.default_rng(seed), n, prof.geometry.print_radius_mm, mcr, z_share)
    _assert_same(lines, prof)


def test_long_chains_and_limit_changes_go_move_by_move_and_agree(profile, monkeypatch):
    rng = np.random.default_rng(7)
    pts = np.round(np.cumsum(rng.normal(size=(400, 3)) * [1.0, 1.0, 0.02], 0) + [0, 0, 20], 4)
    body = [f"G1 X{x:.4f} Y{y:.4f} Z{z:.4f} E0.01 F{6000 + 30 * i}" for i, (x, y, z) in enumerate(pts)]
    head = ["SET_VELOCITY_LIMIT ACCEL=5000 MINIMUM_CRUISE_RATIO=0 SQUARE_CORNER_VELOCITY=5", "M83"]
    planner = _assert_same(head + body, profile)
    assert planner.chains == 1 and planner.chain_moves == 400  # one chain, vectorised
    # a limit change inside the chain: the moves before keep the old limits, the rest follow
    lines = head + body[:150] + ["SET_VELOCITY_LIMIT ACCEL=2000"] + body[150:]
    planner = _assert_same(lines, profile)
    assert planner.chain_moves == 0
    # a chain longer than MAX_CHAIN is handed over whole
    monkeypatch.setattr(klipper_chains, "MAX_CHAIN", 100)
    planner = _assert_same(head + body, profile)
    assert planner.chain_moves == 0


@pytest.mark.parametrize("bad, exc, text", [
    ("G1 X0 Y0 Z900 F6000", KinematicsError, "Move out of range"),
    ("G1 X500 Y0 Z5 F6000", KinematicsError, "Move out of range"),
    ("G1 X1 Y1 Z5 E-80 F6000", GcodeError, "Extrude only move too long"),
])
def test_errors_in_a_chain_are_the_klipper_planners(bad, exc, text, profile):
    lines = ["SET_VELOCITY_LIMIT MINIMUM_CRUISE_RATIO=0", "G1 X1 Y2 Z5 F6000", "G1 X3 Y2 Z5", bad, "G1 X3 Y3 Z5"]
    for chains in (False, True):
        with pytest.raises(exc, match=text) as e:
            _flat(lines, profile, chains)
        assert ":4" in str(e.value) or "line 4" in str(e.value)


@pytest.mark.parametrize("prof_path", [None, OTHER])
def test_the_self_check_measures_the_same_either_way(prof_path, profile, tmp_path, monkeypatch):
    """The self-check on the chain planner gives the move-by-move planner's numbers (a real sample:
    retractions, z-hops, layer changes)."""
    from ffcomp.pipeline import self_check as sc
    from ffcomp.pipeline.compensate_flow import compensate_file

    prof = load_profile(prof_path) if prof_path else profile
    seen = {}
    orig = sc.measure

    def spy(*a, **k):
        seen["chains"] = orig(*a, **k, chains=True)
        return orig(*a, **k, chains=False)

    monkeypatch.setattr(sc, "measure", spy)
    summ = compensate_file("samples/gcode/stress_square.gcode", str(tmp_path / "o.gcode"), prof)
    r = seen["chains"]
    assert summ.self_check_max_um == pytest.approx(r["worst"] * 1e6, abs=1e-3)
    assert summ.self_check_abs_max_um == pytest.approx(r["worst_abs"] * 1e6, abs=1e-3)
    assert summ.self_check_drift_ms == pytest.approx(r["drift_max"] * 1e3, abs=1e-5)
    assert summ.output_print_time_s == pytest.approx(r["t_end"], abs=1e-8)
    assert r["cnt"] > 1000


def test_blocks_carry_the_klipper_fields(profile):
    lines = ["SET_VELOCITY_LIMIT MINIMUM_CRUISE_RATIO=0", "G1 X10 Y0 Z5 F6000", "G1 X10 Y10 Z5"]
    items = list(GcodePlan(lines, profile, chains=True, start_position_mm=(0.0, 0.0, 5.0, 0.0)))
    assert len(items) == 1 and isinstance(items[0], MoveBlock)
    b = items[0]
    assert b.lineno.tolist() == [2, 3]
    assert b.t_start_s == 0.0 and b.t_end_s == pytest.approx(b.t_start[1] + b.accel_t[1] + b.cruise_t[1]
                                                             + b.decel_t[1])
    np.testing.assert_allclose(b.unit[:, :3], [[1, 0, 0], [0, 1, 0]])
    # a plain run gives the same durations
    plain = list(GcodePlan(lines, profile, start_position_mm=(0.0, 0.0, 5.0, 0.0)))
    np.testing.assert_allclose(b.accel_t + b.cruise_t + b.decel_t, [m.duration_s for m in plain], rtol=1e-12)
    assert all(m.kind == "move" for m in plain)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 80))
def test_runs_of_g1_lines_parse_as_the_line_by_line_path(seed, n):
    """MoveRun arrays carry the same positions and speeds, bit for bit, as the line records, under
    the state commands that change the arithmetic (G92 offsets, M82/M83, M220/M221, G91, G20)."""
    from ffcomp.gcode.move_runs import MoveRun
    from ffcomp.gcode.parser import parse_gcode
    from ffcomp.gcode.records import LinearMove

    rng = np.random.default_rng(seed)
    lines = ["G28", "G1 X0 Y0 Z10 F3000"]
    state = ["G92 X1.5 E0", "G92 E3", "M82", "M83", "M220 S150", "M221 S90", "G91", "G90", "G20", "G21",
             "G1 F300", "G92 Z-0.25"]
    for _ in range(n):
        if rng.random() < 0.15:
            lines.append(str(rng.choice(state)))
            continue
        x, y, z = rng.uniform(-20, 20, 3)
        e = f" E{rng.uniform(-1, 2):.5f}" if rng.random() < 0.7 else ""
        f = rng.choice([f"{rng.uniform(1, 300) * 60:.3f}", "6000", "0.5", "12.", "0", "0.001"])
        lines.append(f"G1 X{x:.4f} Y{y:.4f} Z{z + 20:.4f}{e} F{f}")
    text = [ln + "\n" for ln in lines]

    def moves(records):
        out = []
        for r in records:
            if isinstance(r, MoveRun):
                out += [(int(ln), tuple(e.tolist()), float(v)) for ln, e, v in zip(r.lineno, r.ends, r.speeds)]
            elif isinstance(r.op, LinearMove):
                out.append((r.lineno, tuple(r.op.end), r.op.speed_mm_s))
            elif r.error is not None:  # (lenient: a refused line, e.g. too slow to finish)
                out.append((r.lineno, r.error))
        return out

    want = moves(parse_gcode(text, lenient=True))
    got = moves(parse_gcode(text, lenient=True).runs())
    assert got == want
