"""Quiet z moves next to holds (``--quiet-z``): the plan, what the moves leave ringing, what they cost,
and what the written G-code keeps with them."""

import numpy as np
import pytest

from ffcomp.gcode.klipper import quiet_accel, rest_to_rest_s
from ffcomp.gcode.planner import GcodePlan
from ffcomp.model.lpv import LpvModel
from ffcomp.model.modes import z_resonance_hz
from ffcomp.pipeline.compensate_flow import CompensateOptions
from ffcomp.pipeline.output_check import check_gcode_output

OTHER = "samples/profiles/other_delta.toml"
OTHER_TRUTH = "samples/profiles/other_delta_truth.toml"
HEAD = ["G90", "M83", "SET_VELOCITY_LIMIT ACCEL=10000"]


def _plan(profile, lines, period_s=None):
    kw = {} if period_s is None else {"quiet_z_period_s": period_s}
    plan = GcodePlan(lines, profile, start_position_mm=(0.0, 0.0, 0.2, 0.0), **kw)
    return list(plan), plan.planner


def test_quiet_accel_ramps_last_one_period():
    T = 1 / 60.0
    # a short move: a triangle whose two ramps last T each
    a = quiet_accel(0.2, 200.0, T)
    assert a == pytest.approx(0.2 / T ** 2)
    assert rest_to_rest_s(0.2, 200.0, a) == pytest.approx(2 * T)
    # a long one: ramps of T to the cruise speed
    a = quiet_accel(25.0, 100.0, T)
    assert a == pytest.approx(100.0 / T)
    assert rest_to_rest_s(25.0, 100.0, a) == pytest.approx(25.0 / 100.0 + T)
    assert rest_to_rest_s(25.0, 100.0, 1e9) == pytest.approx(0.25, abs=1e-6)


def test_z_resonance_is_the_peak_of_the_z_response(profile):
    """The z resonance is the drive pair's (the lightly damped 60 Hz pair dominates every FRF)."""
    f = z_resonance_hz(LpvModel.from_profile(profile))
    assert 55.0 < f < 65.0
    from ffcomp.model.modes import drive_modes

    assert f == pytest.approx(np.mean([m.freq_hz for m in drive_modes(LpvModel.from_profile(profile))]), rel=0.03)


def test_the_z_moves_next_to_holds_and_only_they_are_planned_quiet(profile):
    T = 1 / 60.0
    lines = HEAD + ["G1 X10 Y0 Z0.2 E1 F6000",       # 1 printed line
                    "G1 E-0.8 F2100",                # 2 retraction
                    "G1 Z0.6 F12000",                # 3 lift after a hold: quiet
                    "G1 X20 Y0 F12000",              # 4 travel: as planned
                    "G1 Z0.4 F12000",                # 5 move down before a hold: quiet (when the hold comes)
                    "G1 E0.8 F2100",                 # 6 unretraction
                    "G1 X30 Y0 E1 F6000",            # 7 printed line
                    "G1 X30 Y0 Z5 F6000",            # 8 z travel between moves: as planned
                    "G1 X30 Y0 Z0.4 F6000"]
    plain, _ = _plan(profile, lines)
    quiet, planner = _plan(profile, lines, T)
    assert planner.quiet_moves == 2
    assert len(plain) == len(quiet)
    quiet_i = {i for i, p in enumerate(plain) if p.kind == "move" and 0.1 < abs(p.end_mm[2] - p.start_mm[2]) < 1.0}
    assert len(quiet_i) == 2
    for i, (p, q) in enumerate(zip(plain, quiet)):
        if i in quiet_i:
            d = p.distance_mm
            assert q.accel_mm_s2 == pytest.approx(quiet_accel(d, q.cruise_v_mm_s if q.cruise_t_s > 0 else 1e9, T))
            assert q.accel_mm_s2 < 0.2 * p.accel_mm_s2
            # from rest to its peak in one period (the move down leaves the travel's corner at a few mm/s)
            assert q.cruise_v_mm_s / q.accel_mm_s2 == pytest.approx(T, rel=0.05)
        else:
            assert q.accel_mm_s2 == p.accel_mm_s2
            if i - 1 not in quiet_i and i + 1 not in quiet_i:  # (a neighbour's junction speed may change)
                assert q.duration_s == pytest.approx(p.duration_s)
    # the time the quiet moves add, rest to rest, is about what the plan grew by
    grown = (quiet[-1].t_end_s - plain[-1].t_end_s)
    assert planner.quiet_added_s == pytest.approx(grown, rel=0.1)  # (rest to rest; these have corners)
    assert grown > 0.02
    # the plan is continuous: each move starts where and when the last one ended
    for a, b in zip(quiet[:-1], quiet[1:]):
        assert b.t_start_s == pytest.approx(a.t_end_s, abs=1e-12)
        assert b.start_v_mm_s <= a.end_v_mm_s + 1e-9 or b.kind != "move" or a.kind != "move"


@pytest.mark.parametrize("which", ["default", "other"])
def test_a_quiet_layer_change_leaves_little_ringing(profile, which):
    """The uncompensated plan of a layer change's z move, simulated on the printer: planned quiet
    (ramps of one z period) it leaves a tenth of the ringing or less in the unretraction after it."""
    from ffcomp.profile import load_profile
    from ffcomp.sim.moves import load_gcode_trajectory
    from ffcomp.sim.plant import DeltaPlant

    prof, plant = (profile, profile) if which == "default" else (load_profile(OTHER), load_profile(OTHER_TRUTH))
    T = 1 / z_resonance_hz(LpvModel.from_profile(prof))
    import tempfile
    from pathlib import Path

    src = Path(tempfile.mkdtemp()) / "lc.gcode"
    src.write_text("\n".join(HEAD + ["G1 X0 Y0 Z0.2 F6000", "G4 P300", "G1 E-0.8 F2100", "G1 Z0.4 F12000",
                                     "G1 E0.8 F2100", "G4 P300"]) + "\n")
    ring = {}
    for name, qp in (("plain", None), ("quiet", T)):
        tr = load_gcode_trajectory(prof, src, split=False, quiet_z_period_s=qp)
        sim = DeltaPlant.from_profile(plant).simulate(tr.t_s, tr.q_m[None], hold="linear")
        z_err = sim.xyz_m[0][:, 2] - tr.xyz_m[:, 2]
        moving = np.nonzero(np.abs(np.diff(tr.xyz_m[:, 2])) > 0)[0]
        after = slice(moving[-1] + 2, moving[-1] + 2 + 60)  # the 60 ms after the z move
        ring[name] = float(np.max(np.abs(z_err[after])))
    assert ring["plain"] > 20e-6, ring
    assert ring["quiet"] < 0.1 * ring["plain"], ring


@pytest.mark.parametrize("which", ["default", "other"])
def test_quiet_z_moves_with_margins_keep_the_gain_over_the_whole_layered_file(tmp_path, profile, which):
    """With 15 ms margins and quiet z moves the written G-code keeps >= 90 % of the exact commands'
    lag-aligned and contour reduction over the whole layered file (margins alone: ~75 % on the default
    profile), on the clock; the reference has the same quiet z move (its time is in the plan)."""
    from test_hold_margins import _layers

    from ffcomp.profile import load_profile

    prof, plant = (profile, None) if which == "default" else (load_profile(OTHER), load_profile(OTHER_TRUTH))
    src = tmp_path / "layers.gcode"
    src.write_text("\n".join(_layers(z_hop=False)) + "\n")
    base = check_gcode_output(prof, src, tmp_path / "margins.gcode", plant_profile=plant,
                              opts=CompensateOptions(hold_margin_s=0.015, quiet_z=False, predict=False))
    chk = check_gcode_output(prof, src, tmp_path / "quiet.gcode", plant_profile=plant,
                             opts=CompensateOptions(hold_margin_s=0.015, quiet_z=True, predict=False))
    s = chk.summary
    assert s.quiet_z_moves == 1 and base.summary.quiet_z_moves == 0
    assert s.quiet_z_period_s == pytest.approx(1 / z_resonance_hz(LpvModel.from_profile(prof)))
    grown = s.output_print_time_s - base.summary.output_print_time_s
    assert grown == pytest.approx(s.quiet_z_time_s, abs=2e-3) and 0.005 < grown < 0.05
    assert abs(s.self_check_drift_ms) < 0.2, s.self_check_drift_ms
    assert chk.kept("lag") >= 0.9 and chk.kept("contour") >= 0.9, (chk.kept("lag"), chk.kept("contour"))
    assert chk.kept("lag") > base.kept("lag") + 0.03, (chk.kept("lag"), base.kept("lag"))
    # judged against the source's own plan (one lag for the whole file), the time they add is error:
    # why both stay off by default
    for c in (base, chk):
        n, g = c.source_clock["none"], c.source_clock["gcode"]
        assert g.lag.rms_norm_um > n.lag.rms_norm_um, (g.lag.rms_norm_um, n.lag.rms_norm_um)


@pytest.mark.parametrize("which", ["default", "other"])
def test_the_default_output_runs_on_the_source_clock(tmp_path, profile, which):
    """By default no quiet z move and no margin: the intended timeline is the source's own plan, the
    header carries no ``quiet_z``, and the output keeps that clock."""
    from test_hold_margins import _layers

    from ffcomp.gcode.start import resolve_start
    from ffcomp.pipeline.compensate_flow import compensate_file
    from ffcomp.profile import load_profile

    prof = profile if which == "default" else load_profile(OTHER)
    src, out = tmp_path / "layers.gcode", tmp_path / "out.gcode"
    src.write_text("\n".join(_layers(z_hop=True)) + "\n")
    s = compensate_file(str(src), str(out), prof, CompensateOptions(predict=False))
    assert s.quiet_z_moves == 0 and s.quiet_z_period_s is None and s.hold_margins == 0
    assert "quiet_z=" not in out.read_text()
    plain = list(GcodePlan(str(src), prof, start_position_mm=resolve_start(str(src), prof).position_mm))
    assert s.print_time_s == pytest.approx(plain[-1].t_end_s, abs=1.5e-3)  # (its last sample: a 1 ms grid)
    assert abs(s.self_check_drift_ms) < 0.2, s.self_check_drift_ms


def test_cli_header_and_simulate_take_quiet_z(tmp_path, capsys, profile):
    """Off by default (the output then runs on the source's own clock), on with --quiet-z; the header
    says the period and ``simulate --compare`` plans the source's z moves with it."""
    from cli_util import run, run_json
    from test_hold_margins import _layers

    from ffcomp.pipeline.header import settings_quiet_z_period_s
    from ffcomp.sim.moves import load_gcode_trajectory

    src, out = tmp_path / "layers.gcode", tmp_path / "out.gcode"
    src.write_text("\n".join(_layers(z_hop=False)) + "\n")
    d = run_json(capsys, src, "-o", out, "--quiet-z", "--no-progress")
    assert d["quiet_z_moves"] == 1 and d["quiet_z_time_s"] > 0.005
    off = run_json(capsys, src, "-o", tmp_path / "off.gcode", "--no-progress")  # (the default)
    assert off["quiet_z_moves"] == 0 and off["quiet_z_period_s"] is None
    assert "quiet_z=" not in (tmp_path / "off.gcode").read_text()
    assert run_json(capsys, src, "-o", tmp_path / "off2.gcode", "--no-quiet-z", "--no-progress")["quiet_z_moves"] == 0
    assert off["print_time_s"] == pytest.approx(d["print_time_s"] - d["quiet_z_time_s"], abs=1e-3)
    # with --jobs the workers plan and count; the period is the run's (it was None there)
    j2 = run_json(capsys, src, "-o", tmp_path / "j2.gcode", "--jobs", "2", "--quiet-z", "--no-progress")
    assert j2["quiet_z_period_s"] == pytest.approx(d["quiet_z_period_s"]) and j2["quiet_z_moves"] == 1
    T = settings_quiet_z_period_s(out)
    assert T == pytest.approx(d["quiet_z_period_s"], rel=1e-5) and settings_quiet_z_period_s(src) is None
    plain = load_gcode_trajectory(profile, src, split=False)
    quiet = load_gcode_trajectory(profile, src, split=False, quiet_z_period_s=T)
    assert len(quiet.q_m) - len(plain.q_m) == pytest.approx(d["quiet_z_time_s"] * 1000, abs=2)
    code, stdout, err = run(capsys, "simulate", src, "--compare", out)
    assert code == 0, err
    assert "quiet z moves next to retractions; the reference" in " ".join(stdout.split()), stdout
    code, stdout, err = run(capsys, "simulate", src, "--compare", tmp_path / "off.gcode")
    assert code == 0 and "the reference above has them" not in " ".join(stdout.split()), err
    code, _, err = run(capsys, "hook", src, "--quiet-z")
    assert code == 0, err
    assert "quiet_z=" in src.read_text()
    code, _, err = run(capsys, tmp_path / "out.gcode", "-o", tmp_path / "x.ffsteps", "--format", "steps",
                       "--quiet-z")
    assert code == 2 and "--quiet-z" in err, err


def test_quiet_z_is_refused_by_the_chain_planner(profile):
    from ffcomp.gcode.klipper_chains import KlipperChainPlanner

    with pytest.raises(ValueError, match="quiet_z_period_s"):
        KlipperChainPlanner(profile, quiet_z_period_s=0.0166)


def test_quiet_z_on_marlin_is_off_and_warns_only_when_asked(tmp_path, profile):
    """Marlin's plan is not ffcomp's Klipper planner: no quiet moves there; asked for explicitly, a
    counted warning says so."""
    from test_hold_margins import _layers

    from ffcomp.pipeline.compensate_flow import compensate_file

    src = tmp_path / "layers.gcode"
    src.write_text("\n".join(_layers(z_hop=False)) + "\n")
    marlin = _with_planner(profile, "marlin")
    s0 = compensate_file(str(src), str(tmp_path / "m0.gcode"), marlin, CompensateOptions(predict=False))
    s1 = compensate_file(str(src), str(tmp_path / "m1.gcode"), marlin, CompensateOptions(predict=False, quiet_z=True))
    assert s0.quiet_z_moves == s1.quiet_z_moves == 0 and s0.quiet_z_period_s is None
    assert s1.warnings == s0.warnings + 1 and any("--quiet-z" in n for n in s1.notes)


def _with_planner(profile, name):
    from dataclasses import replace

    return replace(profile, limits=replace(profile.limits, planner=name))


def test_the_slow_ends_of_a_quiet_ramp_are_merged_into_its_moving_segments():
    """Holds (sub-micrometre segments) at the start and the end of a quiet move's run go into the
    first / last moving segment of that run; other runs' holds stay."""
    from ffcomp.gcode.holds import merged_ramp_holds

    # two runs: run 0 quiet (hold, hold, move, move, hold), run 1 not quiet (hold, move)
    i = np.arange(7)
    j = i + 1
    srun = np.array([0, 0, 0, 0, 0, 1, 1])
    hold = np.array([True, True, False, False, True, True, False])
    ramp = srun == 0
    ii, jj = merged_ramp_holds(i, j, srun, hold, ramp)
    assert ii.tolist() == [0, 3, 5, 6] and jj.tolist() == [3, 5, 6, 7]
    assert merged_ramp_holds(i, j, srun, hold, np.zeros(7, bool)) is None
    assert merged_ramp_holds(i, j, srun, np.zeros(7, bool), ramp) is None


def test_a_quiet_z_hop_keeps_the_clock_where_max_z_accel_is_low(tmp_path):
    """other_delta (max_z_accel 3000): a z-hop's quiet lift leaves rest slowly (its first samples move
    the nozzle under a micrometre); written as holds and one quick segment, the firmware needed more
    than max_z_accel for it (a cube's z-hops ran 0.46 ms late).  The lift's segments keep the clock."""
    from ffcomp.pipeline.compensate_flow import compensate_file
    from ffcomp.profile import load_profile

    prof = load_profile(OTHER)
    lines = HEAD + ["G1 X-20 Y-20 Z0.2 F6000", "G4 P0", "G1 X20 Y-20 E1.5 F6000", "G1 E-0.8 F2100",
                    "G1 Z0.6 F6000", "G1 X20 Y20 F12000", "G1 Z0.2 F6000", "G1 E0.8 F2100", "G1 X-20 Y20 E1.5 F6000"]
    src = tmp_path / "hop.gcode"
    src.write_text("\n".join(lines) + "\n")
    s = compensate_file(str(src), str(tmp_path / "out.gcode"), prof, CompensateOptions(predict=False, quiet_z=True))
    assert s.quiet_z_moves == 2
    assert abs(s.self_check_drift_ms) < 0.2, s.self_check_drift_ms
