"""Every line accounted for: known start, stops, unknown commands, guards, lenient skips, bytes, and
double-compensation marks (issue 10 items 2-4, issue 12 items 3 and 7)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from cli_util import run

from ffcomp.errors import GcodeError
from ffcomp.gcode import GcodePlan, Stop, parse_text
from ffcomp.gcode.commands import STOP, TABLE, classify
from ffcomp.gcode.parser import MAX_DWELL_S, MAX_MOVE_S, MIN_FEED_MM_S
from ffcomp.gcode.signature import SIGNATURE, scan_gcode
from ffcomp.pipeline.compensate_flow import CompensateOptions, compensate_file
from ffcomp.profile import default_profile, load_profile

ROOT = Path(__file__).resolve().parents[1]
OTHER = ROOT / "samples" / "profiles" / "other_delta.toml"
FAST = CompensateOptions(predict=False)

NO_HOME = """; sliced for a Klipper printer that homes in PRINT_START
G90
M83
G1 X0.002 Y0.002 Z0.3 F6000
G1 X20 Y0 Z0.3 E1 F3000
G1 X20 Y20 E1
G1 X0 Y20 E1
"""


@pytest.fixture(params=["default", "other"], scope="module")
def prof(request):
    return default_profile() if request.param == "default" else load_profile(OTHER)


def _motion(text: str) -> list[str]:
    return [ln for ln in text.splitlines() if ln.startswith("G1 ")]


def _xyz(line: str) -> np.ndarray:
    return np.array([float(re.search(a + r"(-?[\d.]+)", line).group(1)) for a in "XYZ"])


def _feed(line: str) -> float:
    return float(re.search(r"F([\d.]+)", line).group(1))


# ------------------------------------------------------------------ known start (issue 12 item 3)

def test_no_homing_warns_and_first_motion_is_a_travel_at_plan_speed(tmp_path, prof):
    src = tmp_path / "nohome.gcode"
    src.write_text(NO_HOME)
    out = tmp_path / "out.gcode"
    s = compensate_file(str(src), str(out), prof, FAST)
    assert s.homed_first is False and s.warnings >= 1
    assert any("moves before any G28" in n and ":4:" in n for n in s.notes)
    first = _motion(out.read_text())[0]
    # an ordinary travel at the speed the file asks (F6000), to the first move's target
    assert _feed(first) == pytest.approx(6000.0)
    assert np.allclose(_xyz(first), [0.002, 0.002, 0.3], atol=1e-4)
    # and never a creep: no motion line of the first 40 lasts longer than 0.5 s
    mot = _motion(out.read_text())[:40]
    for a, b in zip(mot, mot[1:]):
        d = np.linalg.norm(_xyz(b) - _xyz(a))
        assert d / (_feed(b) / 60.0) < 0.5, b
    assert s.self_check_max_um < 50


def test_start_option_is_honoured(tmp_path, profile):
    src = tmp_path / "nohome.gcode"
    src.write_text(NO_HOME)
    out = tmp_path / "out.gcode"
    s = compensate_file(str(src), str(out), profile, CompensateOptions(predict=False, start_mm=(5.0, -3.0, 10.0)))
    assert s.start_mm == [5.0, -3.0, 10.0] and any("--start" in n for n in s.notes)
    first = _motion(out.read_text())[0]
    assert np.allclose(_xyz(first), [5.0, -3.0, 10.0], atol=2e-4) and _feed(first) == pytest.approx(6000.0)
    # the plan itself starts there: the source's first move is a 10 mm descent, compensated
    plan = list(GcodePlan(str(src), profile, start_position_mm=(5.0, -3.0, 10.0, 0.0)))
    assert plan[0].start_mm[:3] == (5.0, -3.0, 10.0)
    assert s.print_time_s == pytest.approx(plan[-1].t_end_s, abs=2e-3)


def test_cli_start_option_and_bad_value(tmp_path, capsys):
    src = tmp_path / "nohome.gcode"
    src.write_text(NO_HOME)
    out = tmp_path / "o.gcode"
    code, _, err = run(capsys, src, "-o", out, "--no-progress", "--no-predict", "--start", "1,2,30")
    assert code == 0 and "warning" in err and "G28" in err
    assert np.allclose(_xyz(_motion(out.read_text())[0]), [1, 2, 30], atol=2e-4)
    code, _, err = run(capsys, src, "-o", tmp_path / "o2.gcode", "--no-progress", "--start", "1,2")
    assert code != 0 and "X,Y,Z" in err and not (tmp_path / "o2.gcode").exists()


def test_after_g28_the_start_is_home_and_output_unchanged(tmp_path, profile):
    src = tmp_path / "home.gcode"
    src.write_text(NO_HOME.replace("G90\n", "G28\nG90\n"))
    a, b = tmp_path / "a.gcode", tmp_path / "b.gcode"
    sa = compensate_file(str(src), str(a), profile, FAST)
    compensate_file(str(src), str(b), profile, CompensateOptions(predict=False, start_mm=(5.0, 5.0, 50.0)))
    assert sa.homed_first is True and a.read_text() == b.read_text()
    assert not any("before any G28" in n for n in sa.notes)  # no start warning (timing notes may remain)
    assert sa.start_mm == [0.0, 0.0, profile.geometry.z_max_mm]
    assert "travel to the start" not in a.read_text()
    first = _motion(a.read_text())[0]
    assert abs(_xyz(first)[2] - profile.geometry.z_max_mm) < 0.1  # starts from home


# ------------------------------------------------------------------ stops (issue 10 item 2)

STOPS = """G28
G90
M83
G1 X0 Y0 Z0.3 F6000
G1 X20 Y0 E1 F6000
{cmd}
G1 X20 Y20 E1
G1 X0 Y20 E1
"""


@pytest.mark.parametrize("cmd", ["M600", "T1", "G29", "G10", "PAUSE", "M0", "G42 I1 J1", "MY_PURGE_MACRO"])
def test_planner_comes_to_rest_at_a_stop(cmd, profile):
    for fw in ("klipper", "marlin"):
        text = STOPS.format(cmd=cmd)
        plan = GcodePlan(text.splitlines(keepends=True), profile, firmware=fw)
        moves = list(plan)
        before = [m for m in moves if m.lineno == 5][-1]
        assert before.end_v_mm_s == 0.0, (cmd, fw)
        assert plan.planner.stops == 1


@pytest.mark.parametrize("cmd", ["M600", "T1", "G10", "M109 S215", "M400", "MY_PURGE_MACRO"])
def test_stop_lines_run_where_the_compensated_command_rests(tmp_path, prof, cmd):
    src = tmp_path / "stop.gcode"
    src.write_text(STOPS.format(cmd=cmd))
    out = tmp_path / "out.gcode"
    s = compensate_file(str(src), str(out), prof, FAST)
    lines = out.read_text().splitlines()
    i = lines.index(cmd)
    before = [ln for ln in lines[:i] if ln.startswith("G1 X")][-3:]
    # the last three points before the stop line stand within 20 um of the planned rest point
    for ln in before:
        assert np.linalg.norm(_xyz(ln) - [20.0, 0.0, 0.3]) < 0.02, (ln, lines[i - 4:i + 1])
    assert s.commands_stopped + s.commands_unknown == (0 if cmd == "M400" else 1) and s.self_check_max_um < 50
    assert s.commands_synced == (1 if cmd == "M400" else 0)  # (said in the summary: the stream restarts there)
    if cmd == "MY_PURGE_MACRO":
        assert s.commands_unknown == 1 and s.warnings == len(s.notes)
        assert sum("MY_PURGE_MACRO" in n for n in s.notes) == 1


def test_unknown_command_policies(tmp_path, profile):
    src = tmp_path / "m.gcode"
    src.write_text(STOPS.format(cmd="MY_PURGE_MACRO LEN=3"))
    with pytest.raises(GcodeError, match=r":6: unknown command 'MY_PURGE_MACRO'"):
        compensate_file(str(src), str(tmp_path / "o.gcode"), profile, CompensateOptions(unknown_policy="refuse"))
    assert not (tmp_path / "o.gcode").exists()
    s = compensate_file(str(src), str(tmp_path / "p.gcode"), profile,
                        CompensateOptions(predict=False, unknown_policy="pass"))
    assert s.commands_unknown == 1 and s.commands_stopped == 0 and s.warnings == len(s.notes)
    assert sum("MY_PURGE_MACRO" in n for n in s.notes) == 1
    assert "MY_PURGE_MACRO LEN=3" in (tmp_path / "p.gcode").read_text()


def test_summary_counts_every_class(tmp_path, profile):
    text = ("G28\nM104 S200\nM106 S255\nG90\nM83\nSET_VELOCITY_LIMIT ACCEL=5000\nG1 X0 Y0 Z1 F6000\n"
            "G1 X10 E1\nM600\nT0\nG1 X10 Y10 E1\nMYSTERY\nG1 X0 Y10 E1\n")
    src = tmp_path / "c.gcode"
    src.write_text(text)
    s = compensate_file(str(src), str(tmp_path / "o.gcode"), profile, FAST)
    assert (s.commands_passed, s.commands_baked, s.commands_stopped, s.commands_unknown) == (2, 3, 2, 1)


def test_table_classes_and_firmware_doc():
    assert classify("T3") == STOP and classify("M600") == STOP and classify("G10") == STOP
    assert classify("M104") == "pass" and classify("M9999") == "pass" and classify("FOO_BAR") == "unknown"
    assert classify("G5") == "unknown" and classify("G90") == "state" and classify("G1") == "motion"
    doc = (ROOT / "ffcomp" / "gcode" / "FIRMWARE.md").read_text()
    missing = [w for w, c in TABLE.items() if c == STOP and f"`{w}`" not in doc]
    assert not missing, f"FIRMWARE.md does not list the stops {missing}"


# ------------------------------------------------------------------ guards (issue 10 item 3)

@pytest.mark.parametrize("line, what", [
    ("G1 X10 Y10 E2 F0.001", "below the minimum"),
    ("G1 X10 Y10 E2 F1", "below the minimum"),
    ("G1 X100 Y0 F6.5", "longer than the"),
    ("G4 P7200000", "dwell of 7200 s"),
    ("G2 X10 Y0 I5 J0 F1", "below the minimum"),
    ("G2 X10 Y0 I100000 J0 F3000", "arc of 6.283e"),
])
def test_pathological_input_is_a_clean_error_naming_the_line(tmp_path, profile, line, what):
    src = tmp_path / "bad.gcode"
    src.write_text(f"G28\nG1 X0 Y0 Z5 F6000\n{line}\n")
    with pytest.raises(GcodeError, match=rf"bad.gcode:3: .*{what}"):
        compensate_file(str(src), str(tmp_path / "o.gcode"), profile, FAST)
    assert not (tmp_path / "o.gcode").exists() and not list(tmp_path.glob(".ffcomp-*"))
    assert MIN_FEED_MM_S == 0.1 and MAX_MOVE_S == 900.0 and MAX_DWELL_S == 3600.0


@pytest.mark.parametrize("fw, limit", [("klipper", "SET_VELOCITY_LIMIT ACCEL=0.0001"), ("marlin", "M204 S0.0001")])
def test_a_move_the_limits_make_last_hours_is_an_error(profile, fw, limit):
    text = f"G28\nG1 X0 Y0 Z5 F6000\n{limit}\nG1 X100 Y0\nG1 X20 Y0\n"
    with pytest.raises(GcodeError, match=r"<string>:4: this move would last \d+ s"):
        list(GcodePlan(text.splitlines(keepends=True), profile, firmware=fw, path="<string>"))


def test_slow_but_sane_moves_still_pass(profile):
    # 1 mm/s probing-like move over 20 mm (20 s), a 10-minute heat soak, a 2 um settling move at F0.4
    recs = parse_text("G28\nG1 X0 Y0 Z20 F6000\nG1 Z0 F60\nG4 S600\nG4 P600000\nG1 X0.002 F0.4\n")
    assert recs[2].op is not None and recs[4].op.seconds == 600.0 and recs[5].op is not None


def test_compensated_output_passes_every_guard(compensated, profile):
    plan = GcodePlan(str(compensated), profile)  # not lenient: every line of ffcomp's own output is valid
    assert list(plan) and plan.parser.counts["skipped"] == 0 and plan.parser.warnings == 0


def test_a_huge_line_is_an_error_with_bounded_memory(tmp_path, profile):
    src = tmp_path / "huge.gcode"
    src.write_bytes(b"G28\nG1 X0 Y0 Z5 F6000\n; " + b"x" * (3 << 20) + b"\nG1 X10 Y0\n")
    with pytest.raises(GcodeError, match=r"huge.gcode:3: line longer than"):
        list(GcodePlan(str(src), profile))
    plan = GcodePlan(str(src), profile, lenient=True)
    moves = list(plan)
    assert plan.parser.lines_read == 4 and plan.parser.counts["skipped"] == 1 and moves[-1].end_mm[0] == 10.0


@pytest.mark.parametrize("text", ["", "\n\n", "; only\n; comments\n", "G28\nM104 S200\nG4 P100\n",
                                  "G90\nM83\nG1 E5 F300\n"])
def test_empty_or_motion_free_files_are_errors(tmp_path, profile, text, capsys):
    src = tmp_path / "empty.gcode"
    src.write_text(text)
    with pytest.raises(GcodeError, match="no XYZ motion"):
        compensate_file(str(src), str(tmp_path / "o.gcode"), profile, FAST)
    code, _, err = run(capsys, src, "-o", tmp_path / "o.gcode", "--no-progress")
    assert code == 3 and "no XYZ motion" in err and not (tmp_path / "o.gcode").exists()


def test_lenient_comments_out_what_it_skips(tmp_path, profile):
    src = tmp_path / "l.gcode"
    src.write_text("G28\nG90\nM82\nG1 X0 Y0 Z1 F6000\nG1 X10 E1\nG1 XNaN Y5 E2.5\nG1 X10 Y10 E2\nG1 X1O Y2\n")
    with pytest.raises(GcodeError, match=":6:"):
        compensate_file(str(src), str(tmp_path / "o.gcode"), profile, FAST)
    s = compensate_file(str(src), str(tmp_path / "o.gcode"), profile, CompensateOptions(predict=False, lenient=True))
    text = (tmp_path / "o.gcode").read_text()
    assert "; ffcomp (skipped): G1 XNaN Y5 E2.5\n" in text and "; ffcomp (skipped): G1 X1O Y2\n" in text
    assert not re.search(r"^G1 XNaN", text, re.M)
    assert s.lines_skipped == 2 and sum("skipped" in n.lower() or "malformed" in n.lower() for n in s.notes) >= 2
    assert s.warnings == len(s.notes)


# ------------------------------------------------------------------ bytes (issue 12 item 7)

def test_non_utf8_comments_and_passthrough_lines_round_trip(tmp_path, profile, capsys):
    odd = [b"; caf\xe9 (Latin-1)\n", b"M117 \xff\xfe stray bytes\n", b";\x00\x01\x7f\x80 binary\r\n",
           b"\xef\xbb\xbf; a BOM in the middle\n"]
    body = b"G28\nG90\nM83\n" + odd[0] + b"G1 X0 Y0 Z1 F6000\n" + odd[1] + b"G1 X10 E1\n" + odd[2] + \
        b"G1 X10 Y10 E1\n" + odd[3]
    src = tmp_path / "odd.gcode"
    src.write_bytes(body)
    out = tmp_path / "o.gcode"
    code, _, err = run(capsys, src, "-o", out, "--no-progress", "--no-predict")
    assert code == 0, err
    got = out.read_bytes()
    for ln in odd:
        assert ln in got


def test_undecodable_bytes_in_a_command_are_a_clean_error(tmp_path, capsys):
    src = tmp_path / "bad.gcode"
    src.write_bytes(b"G28\nG1 X0 Y0 Z5 F6000\nG1 X1\xff Y0\n")
    code, out, err = run(capsys, src, "-o", tmp_path / "o.gcode", "--no-progress")
    assert code == 3 and "bad.gcode:3:" in err and "not UTF-8" in err and "\\xff" in err
    assert "Traceback" not in err and not (tmp_path / "o.gcode").exists()
    src.write_bytes(b"G28\nG1 X0 Y0 Z5 F6000\nG1 X[/bold] Y0\n")  # rich markup in the echoed line
    code, out, err = run(capsys, src, "-o", tmp_path / "o.gcode", "--no-progress")
    assert code == 3 and "[/bold]" in err


# ------------------------------------------------------------------ double compensation (issue 10 item 4)

@pytest.fixture(scope="module")
def compensated(tmp_path_factory):
    d = tmp_path_factory.mktemp("dbl")
    out = d / "square.gcode"
    compensate_file(str(ROOT / "samples" / "gcode" / "stress_square.gcode"), str(out), default_profile(), FAST)
    return out


def test_signature_is_carried_by_the_body(compensated):
    text = compensated.read_text()
    lines = text.splitlines()
    sig = [i for i, ln in enumerate(lines) if ln.startswith(SIGNATURE)]
    assert len(sig) >= 2 and np.max(np.diff(sig)) <= 2000


@pytest.mark.parametrize("strip", ["header", "header_and_first_half", "all_comments"])
def test_double_compensation_is_refused_without_the_header(compensated, tmp_path, profile, strip):
    lines = compensated.read_text().splitlines(keepends=True)
    body_at = next(i for i, ln in enumerate(lines) if ln.startswith(SIGNATURE))
    if strip == "header":
        kept = lines[body_at:]
    elif strip == "header_and_first_half":
        kept = lines[len(lines) // 2:]
    else:
        kept = [ln for ln in lines if not ln.lstrip().startswith(";")]
    src = tmp_path / "again.gcode"
    src.write_text("; re-sliced\n" * 7 + "".join(kept))
    with pytest.raises(GcodeError, match="already compensated"):
        compensate_file(str(src), str(tmp_path / "o.gcode"), profile, FAST)
    assert not (tmp_path / "o.gcode").exists()


def test_signature_scan_finds_marks_anywhere_and_not_in_slicer_files(tmp_path):
    p = tmp_path / "a.gcode"  # 5.4 MB: the scan reads it in two chunks
    p.write_bytes(b"G1 X1\n" * 900000 + b"; ffcomp:sig compensated\n" + b"G1 X2")
    r = scan_gcode(str(p))
    assert r.mark_line == 900001 and r.compensated and r.mark_text == "; ffcomp:sig compensated"
    p.write_bytes(b"G1 X1\n" * 900000 + b"M117 ; ffcomp is not a mark here\nG1 X2")
    r = scan_gcode(str(p))
    assert not r.compensated and r.lines == 900001 and r.g1_lines == 900001
    for name in ("cube_prusa.gcode", "cube_cura.gcode", "stress_zigzag.gcode"):
        r = scan_gcode(str(ROOT / "samples" / "gcode" / name))
        assert not r.compensated and r.lines == (ROOT / "samples" / "gcode" / name).read_bytes().count(b"\n")


def test_stop_record_is_exported():
    assert parse_text("M600\n")[0].op == Stop("M600")


def test_profile_start_position_key(tmp_path):
    import tomllib

    from ffcomp.errors import ProfileError
    from ffcomp.profile import profile_from_dict, profile_to_toml

    base = tomllib.loads(profile_to_toml(default_profile()))
    prof = profile_from_dict({**base, "start_position_mm": [0, 10, 20]})
    assert prof.start_position_mm == (0.0, 10.0, 20.0)
    assert profile_from_dict(tomllib.loads(profile_to_toml(prof))).start_position_mm == (0.0, 10.0, 20.0)
    for bad in ([0, 0], [0, 0, "a"], [500, 0, 10], [0, 0, -5]):
        with pytest.raises(ProfileError, match="start_position_mm"):
            profile_from_dict({**base, "start_position_mm": bad})
    src = tmp_path / "nohome.gcode"
    src.write_text(NO_HOME)
    out = tmp_path / "o.gcode"
    s = compensate_file(str(src), str(out), prof, FAST)
    assert s.start_mm == [0.0, 10.0, 20.0] and any("profile's start_position_mm" in n for n in s.notes)
    assert np.allclose(_xyz(_motion(out.read_text())[0]), [0, 10, 20], atol=2e-4)
    # --start overrides the profile
    s = compensate_file(str(src), str(out), prof, CompensateOptions(predict=False, start_mm=(1.0, 1.0, 5.0)))
    assert s.start_mm == [1.0, 1.0, 5.0]


def test_first_motion_is_found_past_feed_only_lines_and_arcs(tmp_path, profile):
    from ffcomp.gcode.start import resolve_start

    src = tmp_path / "f.gcode"
    src.write_text("G1 F3000\nG1 X0 Y0 F1200\nG1 X5 Y5 Z2\n")  # G1 X0 Y0 does not move (from the origin)
    st = resolve_start(str(src), profile)
    assert st.position_mm[:3] == (5.0, 5.0, 2.0) and st.first_motion_line == 3 and st.travel_mm_s == 20.0
    src.write_text("G90\nG2 X10 Y0 I5 J0 F3000\n")  # an arc keeps the start (its centre is relative)
    st = resolve_start(str(src), profile)
    assert st.position_mm[:3] == (0.0, 0.0, 0.0) and st.origin == "default" and st.warning("f") is not None


def test_a_byte_order_mark_at_the_start_is_dropped(tmp_path, profile):
    src = tmp_path / "bom.gcode"
    src.write_bytes(b"\xef\xbb\xbfG28\nG1 X0 Y0 Z5 F6000\nG1 X10 Y0 Z5\n")
    recs = list(GcodePlan(str(src), profile).parser)
    assert recs[0].command == "G28" and recs[0].raw == "G28\n"
    out = tmp_path / "o.gcode"
    s = compensate_file(str(src), str(out), profile, FAST)
    assert s.homed_first and not any("before any G28" in n for n in s.notes)
    assert b"\xef\xbb\xbf" not in out.read_bytes()


def test_hook_shows_the_warnings(tmp_path, capsys):
    src = tmp_path / "nohome.gcode"
    src.write_text(NO_HOME + "MY_MACRO\nG1 X0 Y0 E1\n")
    code, _, err = run(capsys, "hook", src)
    assert code == 0 and "moves before any G28" in err and "MY_MACRO" in err


def test_a_refused_slow_line_changes_no_state():
    recs = parse_text("G1 X0 Y0 Z5 F6000\nG1 X50 F0.001\nG1 X10\n", lenient=True)
    assert recs[1].op is None and recs[1].error and recs[2].op.speed_mm_s == 100.0
    assert recs[2].op.start[0] == 0.0


def test_limit_commands_the_firmware_ignores_are_said(tmp_path):
    """Marlin-flavoured ``M204 P`` lines (PrusaSlicer's per-feature acceleration) are invalid to
    Klipper, which ignores them, as the plan does; the summary says so, once, with how many."""
    body = "G28\nG90\nM83\nG1 X0 Y0 Z0.3 F6000\n{m204}\nG1 X20 Y0 E1 F3000\nG1 X20 Y20 E1\n{m204}\nG1 X0 Y20 E1\n"
    src, out = tmp_path / "m204.gcode", tmp_path / "o.gcode"
    src.write_text(body.format(m204="M204 P2000"))
    s = compensate_file(str(src), str(out), default_profile(), FAST)
    notes = [n for n in s.notes if "Invalid M204" in n]
    assert len(notes) == 1 and notes[0].startswith("2 limit command(s) that klipper ignores (M204 without S or T: 2;")
    src.write_text(body.format(m204="M204 P2000 T3000"))  # valid to Klipper: min(P, T)
    s = compensate_file(str(src), str(out), default_profile(), FAST)
    assert not [n for n in s.notes if "ignores" in n]
