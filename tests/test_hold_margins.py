"""Rest margins around retractions (``--hold-margin-ms``): where they go, what they cost, what they buy."""

import numpy as np
import pytest

from ffcomp.gcode.margins import hold_margins
from ffcomp.gcode.moves import DWELL, EXTRUDE, MOVE, PlannedMove
from ffcomp.pipeline.compensate_flow import CompensateOptions
from ffcomp.pipeline.output_check import check_gcode_output

OTHER = "samples/profiles/other_delta.toml"
OTHER_TRUTH = "samples/profiles/other_delta_truth.toml"


def _mv(index, kind, e0, e1, xyz0=(0.0, 0.0, 0.2), xyz1=(0.0, 0.0, 0.2)):
    return PlannedMove(index, index + 1, kind, 0.0, (*xyz0, e0), (*xyz1, e1), 1.0, (1.0, 0.0, 0.0, 0.0),
                       0.0, 1.0, 0.0, 1000.0, 0.0, 0.001, 0.0)


def test_margins_sit_before_retractions_after_moves_and_after_unretractions_before_moves():
    moves = {0: _mv(0, MOVE, 0.0, 1.0, (0, 0, 0.2), (10, 0, 0.2)),
             1: _mv(1, EXTRUDE, 1.0, 0.2),                           # retraction after a move: before
             2: _mv(2, MOVE, 0.2, 0.2, (10, 0, 0.2), (10, 0, 0.4)),  # z move after the retraction: none
             3: _mv(3, EXTRUDE, 0.2, 1.0),                           # unretraction before a move: after
             4: _mv(4, MOVE, 1.0, 2.0, (10, 0, 0.4), (0, 0, 0.4)),
             5: _mv(5, DWELL, 2.0, 2.0),                             # a dwell: none
             6: _mv(6, MOVE, 2.0, 3.0, (0, 0, 0.4), (5, 0, 0.4)),
             7: _mv(7, EXTRUDE, 3.0, 4.0),                           # E rises after a move: none
             8: _mv(8, EXTRUDE, 4.0, 3.0)}                           # retraction after an E move: none
    mi = np.repeat(np.arange(9), 3)
    assert hold_margins(mi, moves, None) == [(3, "before"), (12, "after")]
    # the same stream cut into blocks: a margin at a block's first sample needs the previous move
    assert hold_margins(mi[3:], moves, 0) == [(0, "before"), (9, "after")]
    assert hold_margins(mi[12:], moves, 3) == [(0, "after")]
    assert hold_margins(mi[12:], moves, None) == []  # a stream that starts here: nothing before it


def _layers(z_hop: bool) -> list[str]:
    sq = ["G90", "M83", "SET_VELOCITY_LIMIT ACCEL=10000", "G1 X-20 Y-20 Z0.2 F6000", "G4 P0"]
    for layer in range(2):
        if layer:
            sq += ["G1 E-0.8 F2100", f"G1 X-20 Y-20 Z{0.6 if z_hop else 0.4} F12000"]
            if z_hop:
                sq += ["G1 Z0.4 F12000"]
            sq += ["G1 E0.8 F2100"]
        sq += ["G1 X20 Y-20 E1.5 F9000", "G1 X20 Y20 E1.5", "G1 X-20 Y20 E1.5", "G1 X-20 Y-20 E1.5"]
    return sq


@pytest.mark.parametrize("which", ["default", "other"])
def test_margins_keep_the_gain_on_extruded_lines_after_a_layer_change(tmp_path, profile, which):
    """With 15 ms margins the G-code keeps >= 90 % of the exact commands' gain on the extruded lines
    of a layered file (without them ~75-80 %: the command cannot pre-actuate during the unretraction),
    on both printers; the margins add exactly their time, on the clock, and the output stays on it."""
    from ffcomp.profile import load_profile

    prof, plant = (profile, None) if which == "default" else (load_profile(OTHER), load_profile(OTHER_TRUTH))
    src = tmp_path / "layers.gcode"
    src.write_text("\n".join(_layers(z_hop=which == "other")) + "\n")
    base = check_gcode_output(prof, src, tmp_path / "plain.gcode", plant_profile=plant)
    chk = check_gcode_output(prof, src, tmp_path / "margins.gcode", plant_profile=plant,
                             opts=CompensateOptions(hold_margin_s=0.015))
    s = chk.summary
    # one before the retraction, one after the unretraction
    assert s.hold_margins == 2 and base.summary.hold_margins == 0
    assert s.hold_margin_time_s == pytest.approx(0.030)
    assert s.output_print_time_s - base.summary.output_print_time_s == pytest.approx(0.030, abs=1e-3)
    assert abs(s.self_check_drift_ms) < 0.3, s.self_check_drift_ms
    assert set(chk.extruding) == {"none", "exact", "gcode"}
    k_lag, k_con = chk.kept_extruding("lag"), chk.kept_extruding("contour")
    assert k_lag >= 0.9 and k_con >= 0.9, (k_lag, k_con)
    assert k_lag > base.kept_extruding("lag") + 0.05, (k_lag, base.kept_extruding("lag"))


def test_cli_and_hook_take_the_margin(tmp_path, capsys):
    from cli_util import run, run_json

    src = tmp_path / "layers.gcode"
    src.write_text("\n".join(_layers(z_hop=False)) + "\n")
    d = run_json(capsys, src, "-o", tmp_path / "out.gcode", "--hold-margin-ms", "15", "--no-progress")
    assert d["hold_margins"] == 2 and d["hold_margin_time_s"] == pytest.approx(0.030)
    assert "hold_margin=15ms" in (tmp_path / "out.gcode").read_text()
    code, _, err = run(capsys, "hook", src, "--hold-margin-ms", "15")
    assert code == 0, err
    assert "hold_margin=15ms" in src.read_text()
    for bad in (["--hold-margin-ms", "-1"], ["--hold-margin-ms", "15", "--format", "steps"]):
        code, _, err = run(capsys, tmp_path / "out.gcode", "-o", tmp_path / "x.ffsteps", *bad)
        assert code == 2 and "--hold-margin-ms" in err, err


def test_simulate_compare_puts_the_reference_on_the_margins_clock(tmp_path, profile):
    """``ffcomp simulate SRC --compare OUT`` reads the margin from OUT's header and adds the same rest
    to SRC's plan; aligned by one offset only, the output would drift 30 ms from the reference."""
    from ffcomp.gcode.margins import with_margins
    from ffcomp.pipeline.compensate_flow import compensate_file
    from ffcomp.pipeline.header import settings_hold_margin_s
    from ffcomp.pipeline.sim_flow import simulate_gcode
    from ffcomp.sim.moves import load_gcode_trajectory

    src, out = tmp_path / "layers.gcode", tmp_path / "out.gcode"
    src.write_text("\n".join(_layers(z_hop=False)) + "\n")
    compensate_file(str(src), str(out), profile, CompensateOptions(hold_margin_s=0.015, predict=False))
    assert settings_hold_margin_s(out) == pytest.approx(0.015) and settings_hold_margin_s(src) == 0.0
    plain = load_gcode_trajectory(profile, src)
    longer = load_gcode_trajectory(profile, src, hold_margin_s=0.015)
    assert len(longer.q_m) - len(plain.q_m) == 30
    assert with_margins((np.arange(5.0),), np.array([0, 0, 1, 1, 2]), {}, 3)[0].tolist() == list(range(5))
    rep = simulate_gcode(profile, src, compare=out)
    planned, comp = rep.runs[0].report, rep.runs[-1].report
    assert comp.lag.rms_norm_um < 0.4 * planned.lag.rms_norm_um, (comp.lag.rms_norm_um, planned.lag.rms_norm_um)
