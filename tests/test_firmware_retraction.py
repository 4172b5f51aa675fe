"""Firmware retraction (``G10``/``G11``): timed as the extruder moves Klipper's ``firmware_retraction``
makes of them when the profile has a ``[firmware_retraction]`` section, stops otherwise."""

import math

import pytest

from ffcomp.errors import ProfileError
from ffcomp.gcode.moves import FIRMWARE
from ffcomp.gcode.parser import parse_text
from ffcomp.gcode.planner import GcodePlan
from ffcomp.gcode.records import FirmwareMove, Stop
from ffcomp.pipeline.compensate_flow import CompensateOptions, compensate_file
from ffcomp.profile import FirmwareRetraction, load_profile, profile_from_dict, profile_to_toml

OTHER = "samples/profiles/other_delta.toml"
OTHER_TRUTH = "samples/profiles/other_delta_truth.toml"
FR = FirmwareRetraction(retract_length_mm=0.8, retract_speed_mm_s=35.0, unretract_extra_length_mm=0.05,
                        unretract_speed_mm_s=25.0)


def _ops(text, **kw):
    return [(ln.command, ln.op) for ln in parse_text(text, **kw)]


def test_g10_g11_are_klippers_extruder_moves_and_keep_the_files_e_coordinate():
    """Klipper's cmd_G10/G11: ``G1 E-<length> F<int(speed*60)>`` in G91 inside a saved state (so the
    file's absolute E goes on as if nothing happened), nothing while already (un)retracted, the
    unretraction adds the extra length; SET_RETRACTION changes the values and forgets the state."""
    ops = _ops("G1 X1 E1 F600\nG10\nG10\nG1 X5 F9000\nG11\nG11\nG1 X6 E2\n"
               "SET_RETRACTION RETRACT_LENGTH=2 RETRACT_SPEED=40.5\nG11\nG10\n", firmware_retraction=FR)
    cmds = [c for c, _ in ops]
    assert cmds == ["G1", "G10", "G10", "G1", "G11", "G11", "G1", "SET_RETRACTION", "G11", "G10"]
    g10, again, travel, g11, noop, line, setr, g11b, g10b = (op for _, op in ops[1:])
    assert isinstance(g10, FirmwareMove) and g10.start == (1.0, 0.0, 0.0, 1.0)
    assert g10.end[:3] == g10.start[:3] and g10.end[3] == pytest.approx(0.2)
    assert g10.speed_mm_s == 35.0
    assert again is None and noop is None and setr is None and g11b is None  # Klipper does nothing there
    assert travel.speed_mm_s == 150.0  # the file's modal feed is kept across G10 (RESTORE_GCODE_STATE)
    assert g11.end[3] - g11.start[3] == pytest.approx(0.85) and g11.speed_mm_s == 25.0
    # the file's E2 is 1 mm past its E1: the extra 0.05 mm stays in the machine's E, not the file's
    assert line.end[3] - line.start[3] == pytest.approx(1.0) and line.end[3] == pytest.approx(2.05)
    assert g10b.end[3] - g10b.start[3] == pytest.approx(-2.0)
    assert g10b.speed_mm_s == pytest.approx(int(40.5 * 60) / 60)  # Klipper's "F%d"


def test_without_settings_or_under_a_factor_they_are_stops_with_one_warning():
    from ffcomp.gcode.parser import GcodeParser

    par = GcodeParser("G1 X1 E1 F600\nG10\nG1 X2\nG11\nG10\n".splitlines(True))
    ops = [ln.op for ln in par]
    assert [type(ops[i]) for i in (1, 3, 4)] == [Stop, Stop, Stop]
    assert par.retraction_stops == 3 and par.warnings == 1
    assert "no [firmware_retraction] section" in par.warning_messages[0]
    assert "0.35 s" in par.warning_messages[0]
    # the M220/M221 factors apply to Klipper's retraction, and the move carries them for the writer
    par = GcodeParser("M221 S90\nM220 S150\nG10\nM221 S100\nM220 S100\nG10\nG11\n".splitlines(True),
                      firmware_retraction=FR)
    ops = [ln.op for ln in par]
    assert isinstance(ops[2], FirmwareMove) and ops[5] is None and isinstance(ops[6], FirmwareMove)
    assert ops[2].end[3] - ops[2].start[3] == pytest.approx(-0.8 * 0.9)
    assert ops[2].speed_mm_s == pytest.approx(35.0 * 1.5)
    assert (ops[2].speed_percent, ops[2].extrude_percent) == pytest.approx((150.0, 90.0))
    assert (ops[6].speed_percent, ops[6].extrude_percent) == (100.0, 100.0) and par.warnings == 0
    # Marlin: stops (its FWRETRACT is not modelled)
    par = GcodeParser(["G10\n"], dialect="marlin", firmware_retraction=FR)
    assert isinstance(next(iter(par)).op, Stop)
    with pytest.raises(Exception, match="RETRACT_SPEED"):
        parse_text("SET_RETRACTION RETRACT_SPEED=0.5\n", firmware_retraction=FR)


def _retraction_trapezoid_s(length, speed, accel):
    """An extruder-only move from rest to rest: accelerate, cruise, decelerate."""
    if speed * speed / accel >= length:
        return 2.0 * math.sqrt(length / accel)
    return length / speed + speed / accel


def test_the_planner_times_them_as_extruder_only_moves(profile):
    prof = profile.with_(firmware_retraction=FR)
    moves = list(GcodePlan("G1 X10 E1 F3000\nG10\nG1 X20 F9000\nG11\nG1 X30 E1\n".splitlines(True), prof))
    fw = [m for m in moves if m.kind == FIRMWARE]
    assert [m.lineno for m in fw] == [2, 4]
    lim = prof.limits
    for m, length, speed in ((fw[0], 0.8, 35.0), (fw[1], 0.85, 25.0)):
        v = min(speed, lim.max_extrude_only_velocity_mm_s)
        assert m.duration_s == pytest.approx(_retraction_trapezoid_s(length, v, lim.max_extrude_only_accel_mm_s2))
        assert m.start_v_mm_s == 0.0 and m.end_v_mm_s == 0.0
    # the same file with the file's own retraction lines plans to the same clock
    same = list(GcodePlan("M83\nG1 X10 E1 F3000\nG1 E-0.8 F2100\nG1 X20 F9000\nG1 E0.85 F1500\nG1 X30 E1 F9000\n"
                          .splitlines(True), prof))
    assert same[-1].t_end_s == pytest.approx(moves[-1].t_end_s, abs=1e-9)


def _layers(fw: bool) -> str:
    """Two layers of a 40 mm square with a retraction, z-hop and unretraction between them."""
    ret, unret = ("G10", "G11") if fw else ("G1 E-0.8 F2100", "G1 E0.85 F1500")
    sq = ["G90", "M83", "SET_VELOCITY_LIMIT ACCEL=10000", "G1 X-20 Y-20 Z0.2 F6000", "G4 P0"]
    for layer in range(2):
        if layer:
            sq += [ret, "G1 X-20 Y-20 Z0.6 F12000", "G1 Z0.4 F12000", unret]
        sq += ["G1 X20 Y-20 E1.5 F9000", "G1 X20 Y20 E1.5", "G1 X-20 Y20 E1.5", "G1 X-20 Y-20 E1.5"]
    return "\n".join(sq) + "\n"


@pytest.mark.parametrize("which", ["default", "other"])
def test_compensated_g10_g11_run_on_the_clock_like_the_files_own_retractions(tmp_path, profile, which):
    """G10/G11 pass through verbatim, once each, in place; the output runs on the absolute clock
    (the first segment after the firmware's move waited one sample on the plan: without that it
    left 0.5 ms late) and keeps the gain of the same file written with its own retraction lines;
    as stops they cost the inverse's settle and pre-roll each."""
    from ffcomp.pipeline.output_check import check_gcode_output

    base, plant = (profile, None) if which == "default" else (load_profile(OTHER), load_profile(OTHER_TRUTH))
    prof = base.with_(firmware_retraction=FR)
    (tmp_path / "fw.gcode").write_text(_layers(True))
    (tmp_path / "own.gcode").write_text(_layers(False))
    fw = check_gcode_output(prof, tmp_path / "fw.gcode", tmp_path / "fw_out.gcode", plant_profile=plant)
    own = check_gcode_output(prof, tmp_path / "own.gcode", tmp_path / "own_out.gcode", plant_profile=plant)
    out = (tmp_path / "fw_out.gcode").read_text().splitlines()
    body = [ln for ln in out if ln in ("G10", "G11")]
    assert body == ["G10", "G11"]
    assert any(ln.startswith("; G10/G11 timed for [firmware_retraction] retract_length = 0.8") for ln in out)
    s = fw.summary
    assert s.firmware_retractions == 2 and s.commands_stopped == 0
    assert s.output_print_time_s == pytest.approx(own.summary.output_print_time_s, abs=1e-6)
    assert abs(s.self_check_drift_ms) <= 0.2, s.self_check_drift_ms
    for metric in ("lag", "contour"):
        assert fw.kept(metric) >= own.kept(metric) - 0.05, (metric, fw.kept(metric), own.kept(metric))
    # the relative E written plus what the firmware moves adds up to the file's extrusion
    e_written = sum(float(w[1:]) for ln in out if ln.startswith("G1 ") for w in ln.split(";")[0].split()
                    if w.startswith("E"))
    assert e_written - 0.8 + 0.85 == pytest.approx(8 * 1.5 + 0.05, abs=1e-4)
    # as stops (no [firmware_retraction]): each ends the stream, 2 x (settle + pre-roll) longer
    stops = compensate_file(str(tmp_path / "fw.gcode"), str(tmp_path / "stops.gcode"), base,
                            CompensateOptions(predict=False))
    assert stops.commands_stopped == 2 and stops.firmware_retractions == 0
    assert stops.output_print_time_s - s.output_print_time_s > 0.5


def test_under_m220_m221_the_output_sets_the_factors_around_the_firmwares_line(tmp_path, profile):
    """The output bakes M220/M221 into its own moves; around a G10/G11 it sets the source's factors
    again, so the firmware retracts the source's length at the source's speed, on the clock."""
    prof = profile.with_(firmware_retraction=FR)
    src = _layers(True).replace("SET_VELOCITY_LIMIT ACCEL=10000", "SET_VELOCITY_LIMIT ACCEL=10000\nM221 S95\nM220 S80")
    (tmp_path / "f.gcode").write_text(src)
    s = compensate_file(str(tmp_path / "f.gcode"), str(tmp_path / "o.gcode"), prof, CompensateOptions(predict=False))
    out = (tmp_path / "o.gcode").read_text().splitlines()
    k = out.index("G10")
    assert [ln.split(" ;")[0] for ln in out[k - 2:k + 3]] == ["M220 S80", "M221 S95", "G10", "M220 S100", "M221 S100"]
    assert s.firmware_retractions == 2 and abs(s.self_check_drift_ms) <= 0.2, s.self_check_drift_ms
    # the re-planned output retracts what the source does: its extruder-only moves match the source's
    src_fw = [m for m in GcodePlan(str(tmp_path / "f.gcode"), prof) if m.kind == FIRMWARE]
    out_fw = [m for m in GcodePlan(str(tmp_path / "o.gcode"), prof) if m.kind == FIRMWARE]
    assert [round(m.end_mm[3] - m.start_mm[3], 6) for m in out_fw] == [round(-0.8 * 0.95, 6), round(0.85 * 0.95, 6)]
    for a, b in zip(src_fw, out_fw, strict=True):
        assert b.duration_s == pytest.approx(a.duration_s, abs=1e-12)
        assert b.cruise_v_mm_s == pytest.approx(min(35.0, 25.0) * 0.8 if a is src_fw[1] else 35.0 * 0.8)


def test_profile_section_round_trips_validates_and_imports(tmp_path, profile):
    prof = profile.with_(firmware_retraction=FR)
    import tomllib

    again = profile_from_dict(tomllib.loads(profile_to_toml(prof)))
    assert again.firmware_retraction == FR
    d = tomllib.loads(profile_to_toml(profile))
    assert "firmware_retraction" not in d
    d["firmware_retraction"] = {"retract_length_mm": 1.0}
    assert profile_from_dict(d).firmware_retraction == FirmwareRetraction(retract_length_mm=1.0)  # Klipper's defaults
    for key, bad in (("retract_speed_mm_s", 0.5), ("retract_length_mm", -1.0), ("retract_lenght_mm", 1.0)):
        d["firmware_retraction"] = {key: bad}
        with pytest.raises(ProfileError, match=key):
            profile_from_dict(d)
    from test_profile import KLIPPER

    from ffcomp.profile_import import from_klipper_cfg

    cfg = tmp_path / "printer.cfg"
    cfg.write_text(KLIPPER.replace("[stepper_a]", "[firmware_retraction]\nretract_length: 0.6\nretract_speed: 45\n\n"
                                   "[extruder]\nnozzle_diameter: 0.4\nfilament_diameter: 1.75\n\n[stepper_a]"))
    imp = from_klipper_cfg(cfg)
    assert imp.firmware_retraction == FirmwareRetraction(0.6, 45.0, 0.0, 10.0)
    # Klipper's extruder-only defaults: the toolhead's limits times 4 nozzle^2 / filament area
    ratio = 4 * 0.4 ** 2 / (math.pi * 0.875 ** 2)
    assert imp.limits.max_extrude_only_accel_mm_s2 == pytest.approx(3000 * ratio)
    assert imp.limits.max_extrude_only_velocity_mm_s == pytest.approx(imp.limits.max_velocity_mm_s * ratio)
    assert from_klipper_cfg(tmp_path / "printer.cfg").firmware_retraction is not None
    cfg.write_text(KLIPPER)
    assert from_klipper_cfg(cfg).firmware_retraction is None
    # a base profile's section does not outlive a printer.cfg without one (Klipper then has no G10)
    assert from_klipper_cfg(cfg, prof).firmware_retraction is None


def test_firmware_config_prints_the_section(profile):
    from ffcomp.pipeline.header import FirmwareNeeds, klipper_snippet

    lim = profile.limits
    needs = FirmwareNeeds(lim.max_accel_mm_s2, lim.max_z_accel_mm_s2, lim.max_velocity_mm_s,
                          lim.max_z_velocity_mm_s, 100000, 5, 0,
                          instantaneous_corner_velocity=lim.instantaneous_corner_velocity_mm_s,
                          max_extrude_only_velocity=lim.max_extrude_only_velocity_mm_s,
                          max_extrude_only_accel=lim.max_extrude_only_accel_mm_s2)
    assert "note:" not in klipper_snippet(needs, profile)  # the file's values are the profile's
    assert "[firmware_retraction]" not in klipper_snippet(needs, profile)
    snip = klipper_snippet(needs, profile.with_(firmware_retraction=FR))
    assert "[firmware_retraction]\nretract_length: 0.8\nretract_speed: 35\nunretract_extra_length: 0.05\n" \
           "unretract_speed: 25" in snip


@pytest.mark.parametrize("which", ["default", "other"])
def test_as_stops_the_command_stands_still_when_the_firmware_runs_them(tmp_path, profile, which):
    """Without [firmware_retraction] G10/G11 are stops: the stream ends at rest and the next starts
    from rest.  The stop's line is written where the command stands still (after the rest that
    ends the stream before, before the next stream's pre-roll), and the repair of the z-hop after
    the G10 stays in its own stream: it reached back into the rest before and moved the command by
    up to 16 um in its last 40 ms, so the firmware's flush at the G10 slowed that segment (0.13 ms,
    kept for the rest of the file) and the lift ran early (other_delta: -0.47 ms, 50 um)."""
    prof = profile if which == "default" else load_profile(OTHER)
    src = tmp_path / "stops.gcode"
    src.write_text("\n".join(["G28", "G90", "M83", "G1 Z0.25 F3000", "G1 X20 Y0 F6000", "G1 X30 Y10 E0.5 F1500",
                              "G10", "G1 Z.65 F15000", "G1 X-18.5 Y28.5", "G1 Z.25", "G11",
                              "G1 X-18.3 Y29.3 E.04 F1500", "G1 X-10 Y29.3 E.4"]) + "\n")
    s = compensate_file(str(src), str(tmp_path / "out.gcode"), prof, CompensateOptions(predict=False))
    assert s.commands_stopped == 2
    out = (tmp_path / "out.gcode").read_text().splitlines()
    for i in [i for i, ln in enumerate(out) if ln in ("G10", "G11")]:
        j = i - 1
        while out[j].startswith(";"):
            j -= 1
        w = out[j].split()
        assert w[0] == "G4" or (w[0] == "G1" and float(w[-1][1:]) < 6.0), (out[i], out[j])  # at rest
    assert abs(s.self_check_drift_ms) <= 0.3, s.self_check_drift_ms
    assert s.self_check_abs_max_um <= 10.0, s.self_check_abs_max_um


@pytest.mark.parametrize("which", ["default", "other"])
@pytest.mark.parametrize("name", ["lift", "checksums"])
def test_a_motor_off_that_ends_the_file_is_written_last_on_the_clock(tmp_path, profile, which, name):
    """An ``M84`` after the last move (a lift, as hand-written end G-code has it; the checksums
    sample) is a stop whose own samples are the firmware's dwells around it (Klipper's
    ``DISABLE_STALL_TIME``), written with that line.  The stream after it took the stop's next line
    for its pre-roll as a ``G10`` does, so the rests went out on both sides of the ``M84``: the
    self-check measured the file 200 ms off and wrote nothing (default profile), and where it passed
    (other_delta) the command crept 4 um after the motors were off.  Now nothing follows the ``M84``
    but the footer."""
    prof = profile if which == "default" else load_profile(OTHER)
    if name == "lift":
        src = tmp_path / "lift.gcode"
        src.write_text("\n".join(["G28", "G90", "M83", "G1 Z0.2 F3000", "G1 X-10 Y-10 F9000",
                                  "G1 X10 Y-10 E0.7 F3000", "G1 Z5 F3000", "M84"]) + "\n")
    else:
        src = "samples/gcode/checksums.gcode"
    s = compensate_file(str(src), str(tmp_path / "out.gcode"), prof, CompensateOptions(predict=False))
    assert abs(s.self_check_drift_ms) <= 0.1, s.self_check_drift_ms
    out = (tmp_path / "out.gcode").read_text().splitlines()
    i = max(k for k, ln in enumerate(out) if "M84" in ln and not ln.startswith(";"))
    after = [ln for ln in out[i + 1:] if ln.strip() and not ln.startswith(";")]
    assert all(ln.startswith("SET_VELOCITY_LIMIT") for ln in after), after
