"""``ffcomp plan`` and the summary function behind it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from cli_util import run, run_json

from ffcomp.gcode.summary import PlanSummary, summarize_gcode
from ffcomp.profile import default_profile

SQUARE = """; test square
G28
G90
M82
G92 E0
G1 Z0.3 F3000
G1 X-20 Y-20 F9000
G1 X20 Y-20 E1 F3000
G1 X20 Y20 E2
G1 X-20 Y20 E3
G1 X-20 Y-20 E4
G1 E3.2 F2100
G4 P200
G1 Z5 F3000
"""


@pytest.fixture
def square(tmp_path) -> Path:
    p = tmp_path / "square.gcode"
    p.write_text(SQUARE)
    return p


def test_summary_numbers(square):
    s = summarize_gcode(square, default_profile())
    assert isinstance(s, PlanSummary)
    assert s.lines == SQUARE.count("\n") and s.planner == "klipper" and s.warnings == 0
    assert s.moves == 7 and s.extrude_only_moves == 1 and s.dwells == 1
    assert s.dwell_time_s == pytest.approx(0.2)
    assert s.extruding_distance_mm == pytest.approx(160.0)
    assert s.extruded_mm == pytest.approx(4.0) and s.retracted_mm == pytest.approx(0.8)
    assert s.peak_speed_mm_s == pytest.approx(150.0)
    assert s.bbox_min_mm == pytest.approx((-20.0, -20.0, 0.3)) and s.bbox_max_mm[2] == 300.0
    d = s.to_dict()
    assert json.loads(json.dumps(d))["duration_s"] == pytest.approx(s.duration_s)


def test_plan_prints_a_summary(capsys, square):
    code, out, err = run(capsys, "plan", square)
    assert code == 0, err
    assert "klipper" in out and "duration" in out and "peak speed" in out


def test_plan_json_csv_and_plot(capsys, square, tmp_path):
    csv = tmp_path / "t.csv"
    png = tmp_path / "p.png"
    d = run_json(capsys, "plan", square, "--csv", csv, "--plot", png)
    assert d["moves"] == 7 and d["planner"] == "klipper"
    assert png.stat().st_size > 10_000 and png.read_bytes()[:4] == b"\x89PNG"
    data = np.loadtxt(csv, delimiter=",", skiprows=1)
    assert csv.read_text().splitlines()[0] == "t_s,x_mm,y_mm,z_mm,e_mm,qA_mm,qB_mm,qC_mm"
    assert data.shape == (d["csv"]["rows"], 8)
    assert np.allclose(np.diff(data[:, 0]), 1e-3, atol=2e-6)
    assert data[-1, 1:5] == pytest.approx([-20.0, -20.0, 5.0, 3.2], abs=1e-6)
    assert data[-1, 0] == pytest.approx(d["duration_s"], abs=1e-3)


def test_plan_errors_and_lenient(capsys, tmp_path):
    bad = tmp_path / "bad.gcode"
    bad.write_text("G1 X1 F600\nG1 X1O Y5\nG1 X2\n")
    code, out, err = run(capsys, "plan", bad)
    assert code == 3 and "bad.gcode:2" in err and "X1O" in err
    d = run_json(capsys, "plan", bad, "--lenient")
    assert d["warnings"] == 1 and d["moves"] == 1  # no G28: the plan starts at the first move's target
    far = tmp_path / "far.gcode"
    far.write_text("G1 X200 F600\n")
    code, out, err = run(capsys, "plan", far)
    assert code == 3 and "far.gcode:1" in err and "out of range" in err
    near = tmp_path / "near.gcode"
    near.write_text("G28\nG1 X20 F600\n")
    d = run_json(capsys, "plan", near, "--planner", "marlin")
    assert d["planner"] == "marlin"
    code, out, err = run(capsys, "plan", far, "--planner", "marlin")  # out of the print volume for Marlin too
    assert code == 3 and "far.gcode:1" in err
    code, out, err = run(capsys, "plan", far, "--planner", "reprap")
    assert code != 0


SAMPLES = Path(__file__).resolve().parents[1] / "samples" / "gcode"


@pytest.mark.parametrize("name", sorted(p.name for p in SAMPLES.glob("*.gcode")) if SAMPLES.exists() else [])
def test_sample_files_plan(name):
    from ffcomp.errors import GcodeError, KinematicsError

    prof = default_profile()
    path = SAMPLES / name
    if name.startswith("malformed"):
        with pytest.raises(GcodeError):
            summarize_gcode(path, prof)
        assert summarize_gcode(path, prof, lenient=True).warnings >= 1
        return
    if name.startswith("out_of_radius"):
        with pytest.raises(KinematicsError):
            summarize_gcode(path, prof)
        return
    for firmware in ("klipper", "marlin"):
        s = summarize_gcode(path, prof, firmware=firmware)
        assert s.duration_s > 0 and s.moves > 0
        if "fwr" in name:  # G10/G11 with a profile without [firmware_retraction]: planned as stops, said once
            assert s.warnings == 1 and "firmware retraction planned as a stop" in s.warning_messages[0]
        else:
            assert s.warnings == 0
