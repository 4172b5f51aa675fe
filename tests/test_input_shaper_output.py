"""The printer's input shaper under a compensated file: switched off by the header, back on at the end."""

from dataclasses import replace

import pytest
from test_profile import KLIPPER

from ffcomp.errors import ProfileError
from ffcomp.pipeline.compensate_flow import compensate_file
from ffcomp.pipeline.header import SHAPER_OFF
from ffcomp.pipeline.options import CompensateOptions
from ffcomp.profile import InputShaper, load_profile, profile_from_dict, save_profile
from ffcomp.profile_import import from_klipper_cfg

SQUARE = ["G90", "M83", "SET_VELOCITY_LIMIT ACCEL=10000", "G1 X75 Y-25 Z30 F6000", "G4 P0"]
for _ in range(2):
    SQUARE += ["G1 X125 Y-25 F9000", "G1 X125 Y25", "G1 X75 Y25", "G1 X75 Y-25"]


def test_profile_section_round_trip_and_checks(tmp_path, profile):
    sh = InputShaper(shaper_type_x="ei", shaper_freq_x_hz=55.2, shaper_freq_y_hz=61.0, damping_ratio_y=0.07)
    p = tmp_path / "p.toml"
    save_profile(replace(profile, input_shaper=sh), p)
    assert load_profile(p).input_shaper == sh
    d = profile.to_dict()
    assert "input_shaper" not in d and profile.input_shaper is None
    for key, bad in (("shaper_type_x", "smooth"), ("shaper_freq_y_hz", -1.0), ("damping_ratio_x", 1.5),
                     ("shaper_frequency", 50.0)):
        with pytest.raises(ProfileError, match=f"input_shaper.{key}"):
            profile_from_dict({**d, "input_shaper": {key: bad}})


def test_klipper_import_reads_the_input_shaper(tmp_path, profile, capsys):
    from cli_util import run

    cfg = tmp_path / "printer.cfg"
    cfg.write_text(KLIPPER.replace("[stepper_a]", "[input_shaper]\nshaper_type: EI\nshaper_type_y: zv\n"
                                   "shaper_freq_x: 62.4\nshaper_freq_y: 58.8\ndamping_ratio_x: 0.05\n\n[stepper_a]"))
    want = InputShaper("ei", "zv", 62.4, 58.8, 0.05, 0.1, shaper_type_z="ei")  # z's type follows shaper_type
    assert from_klipper_cfg(cfg).input_shaper == want
    code, out, err = run(capsys, "profile", "import", "--klipper", cfg, "-o", tmp_path / "p.toml")
    assert code == 0, err
    assert "input shaper ei 62.4 Hz / zv 58.8 Hz" in " ".join(out.split())
    assert load_profile(tmp_path / "p.toml").input_shaper == want
    # recent Klipper's optional z shaper: read, and restored only where it is set
    cfg.write_text(KLIPPER.replace("[stepper_a]", "[input_shaper]\nshaper_freq_x: 60\nshaper_freq_y: 61\n"
                                   "shaper_type_z: zv\nshaper_freq_z: 35.5\n\n[stepper_a]"))
    sh = from_klipper_cfg(cfg).input_shaper
    assert (sh.shaper_type_z, sh.shaper_freq_z_hz, sh.damping_ratio_z) == ("zv", 35.5, 0.1)
    assert "SHAPER_TYPE_Z=zv SHAPER_FREQ_Z=35.5 DAMPING_RATIO_Z=0.1" in sh.klipper_command()
    assert "_Z=" not in InputShaper(shaper_freq_x_hz=60.0).klipper_command()
    cfg.write_text(KLIPPER)  # no section: Klipper does not shape, whatever the base profile said
    assert from_klipper_cfg(cfg, replace(profile, input_shaper=InputShaper())).input_shaper is None


def _run(tmp_path, prof, lines, name="out.gcode"):
    src = tmp_path / "in.gcode"
    src.write_text("\n".join(lines) + "\n")
    out = tmp_path / name
    s = compensate_file(str(src), str(out), prof, CompensateOptions(predict=False))
    return s, out.read_text().splitlines()


def test_header_switches_shaping_off_and_the_footer_back_on(tmp_path, profile):
    sh = InputShaper("mzv", "ei", 62.1, 60.4, 0.1, 0.08)
    s, out = _run(tmp_path, replace(profile, input_shaper=sh), SQUARE)
    assert s.input_shaper.startswith("off while the file runs, back on") and "62.1 Hz" in s.input_shaper
    first_move = next(i for i, ln in enumerate(out) if ln.startswith("G1 "))
    assert "SHAPER_FREQ_X=0 SHAPER_FREQ_Y=0 SHAPER_FREQ_Z=0" in SHAPER_OFF  # every axis Klipper may shape
    off = [i for i, ln in enumerate(out) if ln.startswith(SHAPER_OFF)]
    assert len(off) == 1 and off[0] < first_move
    last_move = max(i for i, ln in enumerate(out) if ln.startswith("G1 "))
    on = [ln for ln in out[last_move:] if ln.startswith("SET_INPUT_SHAPER ")]
    assert on == [f"{sh.klipper_command()} ; ffcomp: restore the profile's input shaper"]
    assert "SHAPER_FREQ_X=62.1" in on[0] and "SHAPER_TYPE_Y=ei" in on[0] and "DAMPING_RATIO_Y=0.08" in on[0]
    # without the section: off, and the footer says it cannot switch it back on
    s, out = _run(tmp_path, profile, SQUARE)
    assert "left off" in s.input_shaper and not any("shaper" in n for n in s.notes)  # a fact, not a warning
    assert sum(ln.startswith("SET_INPUT_SHAPER") for ln in out) == 1
    assert any("input shaping stays off" in ln for ln in out[-3:])
    # Marlin has no SET_INPUT_SHAPER
    marlin = replace(profile, limits=replace(profile.limits, planner="marlin"))
    s, out = _run(tmp_path, marlin, [ln for ln in SQUARE if not ln.startswith("SET_VELOCITY")])
    assert not any("SET_INPUT_SHAPER" in ln for ln in out) and s.input_shaper == ""


def test_a_source_shaper_line_is_a_stop_kept_as_a_comment(tmp_path, profile):
    """Klipper flushes its lookahead at SET_INPUT_SHAPER (a stop); switched on in the middle of the
    output it would smear the compensation, so the output keeps it as a comment."""
    lines = SQUARE[:6] + ["SET_INPUT_SHAPER SHAPER_FREQ_X=55 SHAPER_FREQ_Y=55"] + SQUARE[6:]
    s, out = _run(tmp_path, replace(profile, input_shaper=InputShaper(shaper_freq_x_hz=60.0)), lines)
    assert s.commands_stopped == 1 and s.commands_unknown == 0
    assert "; ffcomp (baked in): SET_INPUT_SHAPER SHAPER_FREQ_X=55 SHAPER_FREQ_Y=55" in out
    active = [ln for ln in out if ln.startswith("SET_INPUT_SHAPER")]
    assert active[0].startswith(SHAPER_OFF) and len(active) == 2 and "SHAPER_FREQ_X=60" in active[1]


def test_a_shaper_left_on_smears_the_compensation(tmp_path, profile):
    """Why the header switches it off (benchmarks/bench_shaper_stack.py prints the figures): on the
    simulator a shaper on top of the output leaves several times the output's own error, about what
    the shaper alone leaves."""
    from ffcomp.pipeline.output_check import check_gcode_output
    from ffcomp.sim.bench import shaper_tuning

    src = tmp_path / "sq.gcode"
    src.write_text("\n".join(SQUARE) + "\n")
    f_hz = shaper_tuning(profile).centre_hz
    c = check_gcode_output(profile, src, tmp_path / "sq_out.gcode", opts=CompensateOptions(predict=False),
                           shapers=(("mzv", f_hz), ("ei", f_hz)))
    ffc = c.gcode.lag.rms_norm_um
    for key, r in c.shaped.items():
        alone, stacked = r["none"].lag.rms_norm_um, r["gcode"].lag.rms_norm_um
        assert alone < 0.6 * c.none.lag.rms_norm_um, key  # the shaper works on the plain file
        assert ffc < 0.2 * alone, key  # the compensation alone does far better
        assert stacked > 5 * ffc, key  # but with the shaper left on most of that is gone
