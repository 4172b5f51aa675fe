"""The model and identification commands, end to end through the CLI."""

import numpy as np
import pytest
from cli_util import run, run_json

from ffcomp.measure.frf_file import save_frf
from ffcomp.measure.synthetic import identification_sweeps
from ffcomp.profile import load_profile


def test_model_show_json(capsys):
    d = run_json(capsys, "model", "show")
    assert d["dynamics"]["m"] == [0.177] * 3
    assert d["derived"][0]["w_n_rad_s"] == pytest.approx(730.3, abs=0.1)
    assert d["drive"][0]["rhp_zero_hz"] == pytest.approx(1.43e5 / 212.1 / (2 * np.pi))


def test_model_modes_table_behaviour(capsys):
    d = run_json(capsys, "model", "modes")
    poses = d["poses"]
    assert [p["position_mm"] for p in poses] == [[0, 0, 30], [-110, 0, 30], [0, -110, 30], [110, 0, 30]]
    f = [[m["freq_hz"] for m in p["modes"]] for p in poses]
    assert f[0][0] == pytest.approx(f[0][1], abs=1e-6)
    assert all(fp[1] - fp[0] > 5 for fp in f[1:])


def test_model_modes_map_and_plot(capsys, tmp_path):
    png = tmp_path / "map.png"
    d = run_json(capsys, "model", "modes", "--map", "--step", "30", "--plot", png)
    assert len(d["freq_hz"]) == len(d["xy_mm"]) > 50
    assert png.stat().st_size > 10_000


def test_model_frf(capsys, tmp_path):
    png, csv = tmp_path / "bode.png", tmp_path / "frf.csv"
    d = run_json(capsys, "model", "frf", "--at", "0,0,30", "--input", "z", "--output", "qA", "--plot", png,
                 "--csv", csv)
    assert abs(abs(complex(d["real"][0], d["imag"][0])) - 1) < 1e-3
    assert png.exists() and csv.exists()
    code, out, err = run(capsys, "model", "frf", "--input", "w")
    assert code != 0 and "input must be one of" in (out + err)


def test_model_frf_unreachable_pose_fails_cleanly(capsys):
    code, out, err = run(capsys, "model", "frf", "--at", "200,0,30")
    assert code == 3 and "unreachable" in err


def test_identify_end_to_end(capsys, tmp_path, profile):
    c, a = identification_sweeps(profile, noise=0.02, seed=11)
    save_frf(c, tmp_path / "carriage.csv")
    save_frf(a, tmp_path / "assembled.csv")
    out = tmp_path / "printer.toml"
    d = run_json(capsys, "identify", tmp_path / "carriage.csv", tmp_path / "assembled.csv", "--m-n", "0.156",
                 "--m-f", "0.032", "-o", out)
    assert d["k"] == pytest.approx(9.44e4, rel=0.03)
    prof = load_profile(out)
    assert prof.dynamics.b_nt == pytest.approx(27.9, rel=0.03)
    code, text, _ = run(capsys, "identify", tmp_path / "carriage.csv", tmp_path / "assembled.csv", "--m-n",
                        "0.156", "--m-f", "0.032")
    assert code == 0 and "identified parameters" in text


def test_identify_broken_file(capsys, tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("# ffcomp-frf 1\n# kind: carriage\nfreq_hz,real,imag\n1,x,2\n")
    code, _, err = run(capsys, "identify", bad, bad, "--m-n", "0.1", "--m-f", "0.01")
    assert code == 2 and "bad.csv:4" in err and "'x'" in err


def test_bad_profile_exit_code(capsys, tmp_path):
    p = tmp_path / "p.toml"
    p.write_text("[dynamics]\nm = -1\n")
    code, _, err = run(capsys, "model", "show", "--profile", p)
    assert code == 2 and "dynamics.m" in err and "-1" in err


def test_profile_import_and_dump(capsys, tmp_path):
    out = tmp_path / "m.toml"
    code, _, err = run(capsys, "profile", "import", "--m665", "M665 L330 R160 B120 H300", "-o", out)
    assert code == 0, err
    assert load_profile(out).geometry.tower_angles_deg == (210.0, 330.0, 90.0)
    code, text, _ = run(capsys, "profile", "dump")
    assert code == 0 and "[dynamics]" in text
