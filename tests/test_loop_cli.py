"""The model loop from the command line: identify's warnings and refinement, valid JSON, real
paths in the advice, profile set, import frames, plug-ins."""

import json

import numpy as np
import pytest
from cli_util import run, run_json
from loop_sets import PLUGIN, TRUTH, make_set, truth

from ffcomp.measure.frf_file import save_frf
from ffcomp.measure.virtual import PlanItem, virtual_measurements
from ffcomp.profile import load_profile, save_profile
from ffcomp.profile_set import set_values, to_frame


def _write(ms, d):
    d.mkdir(parents=True, exist_ok=True)
    for i, m in enumerate(ms):
        save_frf(m, d / f"{i:02d}.csv")
    return d


def _strict(text):
    def bad(c):
        raise ValueError(f"not JSON: {c}")

    return json.loads(text, parse_constant=bad)


def test_identify_refines_with_the_other_towers_carriage_sweeps(capsys, tmp_path):
    p = truth()
    plan = [PlanItem("carriage", (0.0, 0.0, 30.0), q, q) for q in ("qA", "qB", "qC")]
    plan.append(PlanItem("assembled", (0.0, 0.0, 30.0), "z", "qA"))
    ms = virtual_measurements(p, [{"name": "tower_scale", "k_scale_B": 0.75}], freq_hz=np.geomspace(5, 400, 120),
                              noise=0.02, seed=11, plan=plan)
    _write(ms, tmp_path / "s")
    a, b, c, asm = (tmp_path / "s" / f"{i:02d}.csv" for i in range(4))
    prof_path = tmp_path / "geom.toml"
    save_profile(p, prof_path)
    base = ["identify", a, asm, "--m-n", "0.141", "--m-f", "0.029", "--profile", prof_path]
    code, _, err = run(capsys, *base, "-o", tmp_path / "two.toml")
    err = " ".join(err.split())
    assert code == 0 and "towers B and C" in err and "--sweep" in err  # biased, and says what to add
    two = load_profile(tmp_path / "two.toml").dynamics
    assert two.k[0] < 0.9 * p.dynamics.k[0]
    out = run_json(capsys, *base, "--sweep", b, "--sweep", c, "-o", tmp_path / "four.toml")
    assert out["refined"]["k_ratio_to_A"][1] == pytest.approx(0.75, rel=0.03)
    four = load_profile(tmp_path / "four.toml")
    assert four.dynamics.k[0] == pytest.approx(p.dynamics.k[0], rel=0.03)
    assert four.dynamics.k[1] == pytest.approx(0.75 * p.dynamics.k[1], rel=0.03)
    assert four.dynamics.m[0] == pytest.approx(p.dynamics.m[0], rel=0.05)
    # identifying again from the identified profile does not grow the name
    code, _, _ = run(capsys, "identify", a, asm, "--m-n", "0.141", "--m-f", "0.029", "--profile",
                     tmp_path / "two.toml", "-o", tmp_path / "again.toml")
    assert load_profile(tmp_path / "again.toml").name.count("identified from") == 1


def test_identify_outside_the_model_writes_a_physical_profile_and_warns(capsys, tmp_path):
    from ffcomp.model.effects import load_plugin

    load_plugin(str(PLUGIN))
    ms = make_set([{"name": "motor_mount", "f_hz": 250.0, "zeta": 0.03, "mu": 0.6, "zeta_zero": 0.02}], n_freq=120,
                  heights=(30.0,), seed=12)
    _write(ms[:2], tmp_path / "s")
    code, _, err = run(capsys, "identify", tmp_path / "s" / "00.csv", tmp_path / "s" / "01.csv", "--m-n", "0.141",
                       "--m-f", "0.029", "-o", tmp_path / "p.toml", "--plot", tmp_path / "id.png")
    err = " ".join(err.split())
    assert code == 0 and "does not fit the carriage sweep" in err and "no --profile" in err
    d = load_profile(tmp_path / "p.toml").dynamics  # loads: every value physical
    assert min(d.c) >= 0 and min(d.b) >= 0 and d.b_nt >= 0
    assert (tmp_path / "id.png").stat().st_size > 1000


def test_diagnose_json_is_valid_and_commands_name_real_paths(capsys, tmp_path):
    ms = make_set([{"name": "drive_delay", "delay_ms": 1.0}], n_freq=40, heights=(30.0,), seed=13)
    d = _write(ms, tmp_path / "data")
    save_profile(truth(), tmp_path / "t.toml")
    code, text, err = run(capsys, "diagnose", d, "--profile", tmp_path / "t.toml", "--json")
    out = _strict(text)  # no NaN / Infinity
    assert out["candidates"][0]["effect"] == "drive_delay"
    assert str(d) in out["verdict"] and str(tmp_path / "t.toml") in out["verdict"] and "P.toml" not in out["verdict"]
    assert "disagree" in err  # the coherence's floor (one average assumed) is not the data's
    code, text, _ = run(capsys, "fit", d, "--profile", tmp_path / "t.toml", "--add", "drive_delay", "--json")
    fit = _strict(text)
    assert fit["base"] is not None and fit["mean_residual_after"] < 1.5 * fit["noise_floor"]
    code, text, _ = run(capsys, "validate", d, "--profile", tmp_path / "t.toml", "--json", "--noise-floor", "5")
    v = _strict(text)
    assert v["summary"]["noise_source"] == "given" and "below the noise floor" in v["summary"]["below_floor"]


def test_profile_set_validates_and_writes(capsys, tmp_path):
    p = tmp_path / "p.toml"
    save_profile(truth(), p)
    code, _, err = run(capsys, "profile", "set", p, "geometry.delta_radius_mm=150",
                       "geometry.tower_angles_deg=0,120,240", "name=my delta")
    assert code == 0, err
    prof = load_profile(p)
    assert prof.geometry.delta_radius_mm == (150.0,) * 3 and prof.name == "my delta"
    before = p.read_text()
    for bad, why in (("dynamics.c=-1", "must be >= 0"), ("geometry.nope=1", "unknown key"),
                     ("dynamics.k", "KEY=VALUE")):
        code, _, err = run(capsys, "profile", "set", p, bad)
        assert code != 0 and why in err
    assert p.read_text() == before  # nothing written on an error
    with pytest.raises(Exception, match="no effect"):
        set_values(prof, ["effects.belt_span.l1_ref_mm=300"])


def test_import_frames(capsys, tmp_path):
    out = tmp_path / "m.toml"
    code, _, err = run(capsys, "profile", "import", "--m665", "M665 L330 R155 B120 H300 X0.5", "--frame", "paper",
                       "-o", out)
    assert code == 0, err
    assert load_profile(out).geometry.tower_angles_deg == (0.5, 120.0, 240.0)
    fw = to_frame(load_profile(out), "firmware")
    assert fw.geometry.tower_angles_deg == (210.5, 330.0, 90.0)
    code, _, err = run(capsys, "profile", "import", "--m665", "M665 L330 R155", "--frame", "sideways", "-o", out)
    assert code != 0 and "--frame" in err


def test_plugin_errors_name_the_file(capsys, tmp_path):
    from ffcomp.model.effects import load_plugin

    with pytest.raises(ValueError, match="no such file"):
        load_plugin(str(tmp_path / "missing.py"))
    empty = tmp_path / "empty.py"
    empty.write_text("x = 1\n")
    with pytest.raises(ValueError, match="registered no effect"):
        load_plugin(str(empty))
    broken = tmp_path / "broken.py"
    broken.write_text("raise RuntimeError('boom')\n")
    with pytest.raises(ValueError, match="broken.py.*boom"):
        load_plugin(str(broken))
    toml = tmp_path / "p.toml"
    toml.write_text(TRUTH.read_text() + '\n[[effects]]\nname = "motor_mount"\nplugin = "nowhere.py"\n')
    code, _, err = run(capsys, "validate", tmp_path, "--profile", toml)
    assert code != 0 and "nowhere.py" in err


def test_plugin_from_an_installed_module(tmp_path, monkeypatch):
    from ffcomp.model.effects import EFFECTS, build_effects, load_plugin

    pkg = tmp_path / "my_effects_pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text(PLUGIN.read_text().replace('name = "motor_mount"', 'name = "mount_pkg"'))
    monkeypatch.syspath_prepend(str(tmp_path))
    assert load_plugin("my_effects_pkg") == ["mount_pkg"]
    assert EFFECTS["mount_pkg"].plugin == "my_effects_pkg"
    eff = build_effects([{"name": "mount_pkg", "plugin": "my_effects_pkg", "f_hz": 300.0}])[0]
    assert eff.values["f_hz"] == 300.0
    with pytest.raises(ValueError, match="cannot import"):
        load_plugin("no_such_module_anywhere")


def test_identify_refined_with_a_whole_directory_reaches_the_floor(capsys, tmp_path):
    from ffcomp.loop.validate import validate

    ms = make_set([], n_freq=80, heights=(30.0, 130.0), seed=2)
    d = _write(ms, tmp_path / "data")
    save_profile(truth(), tmp_path / "g.toml")
    out = run_json(capsys, "identify", d / "00.csv", d / "01.csv", "--m-n", "0.141", "--m-f", "0.029", "--profile",
                   tmp_path / "g.toml", "--sweep", d, "-o", tmp_path / "p.toml")
    assert out["refined"]["mean_residual_after"] < out["refined"]["mean_residual_before"]
    v = validate(load_profile(tmp_path / "p.toml"), ms)
    assert v.mean_residual <= 1.25 * v.noise_floor


def test_refined_profile_is_the_model_that_was_fitted():
    """The refined profile, written with per-tower k, c and b, predicts exactly what the fit's model
    (base plus tower_scale, whose damping factor scales c + b) predicted: the same residuals."""
    from ffcomp.loop.fit import residuals_of
    from ffcomp.loop.identify_refine import refine_identification
    from ffcomp.model.lpv import LpvModel

    p = truth()
    plan = [PlanItem("carriage", (0.0, 0.0, 30.0), q, q) for q in ("qA", "qB", "qC")]
    plan.append(PlanItem("assembled", (0.0, 0.0, 30.0), "z", "qA"))
    ms = virtual_measurements(p, [{"name": "tower_scale", "k_scale_B": 0.8, "c_scale_C": 1.5}],
                              freq_hz=np.geomspace(5, 400, 80), noise=0.01, seed=4, plan=plan)
    ref = refine_identification(p, ms)
    assert ref.c_ratio[2] == pytest.approx(1.5, rel=0.15)
    res = residuals_of(LpvModel.from_profile(ref.profile), ms)
    assert np.allclose(res, ref.residual_after, rtol=1e-6, atol=1e-9)


def test_a_relative_plugin_name_resolves_per_profile_directory(tmp_path):
    """The same relative ``plugin = "fx.py"`` in two directories loads two different files."""
    from ffcomp.model.effects import load_plugin

    names = []
    for i in (1, 2):
        d = tmp_path / f"p{i}"
        d.mkdir()
        (d / "fx.py").write_text(
            "from ffcomp.model.effects import Effect, register\n"
            f"@register\nclass Fx{i}(Effect):\n    name = 'fx_rel_{i}'\n    summary = 'test'\n    params = {{}}\n"
            "    def apply(self, mats, model):\n        return mats\n")
        names.append(load_plugin("fx.py", base_dir=str(d)))
    assert names[0] != names[1]
