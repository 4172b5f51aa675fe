"""The loop validate -> diagnose -> fit -> validate on data with hidden effects (2 % complex noise).

For every effect in the library: the hidden effect lifts the base model's residual well above the
noise floor, ``diagnose`` ranks it first, fitting it brings the mean residual back to within 1.5x
the noise floor (mean magnitude R^2 >= 0.99) and recovers its parameter within 10 %.  Without a
hidden effect nothing is significant; two hidden effects are found by running the loop twice.
"""

import numpy as np
import pytest

from ffcomp.loop.diagnose import diagnose, pose_folds
from ffcomp.loop.fit import fit_effects, fitted_profile
from ffcomp.loop.validate import validate
from ffcomp.measure.virtual import virtual_measurements

F = np.geomspace(5, 400, 100)
NOISE = 0.02

# effect -> (hidden parameters, the parameter to recover)
CASES = {
    "belt_span": ({"l1_ref_mm": 300.0}, "l1_ref_mm"),
    "tower_scale": ({"k_scale_B": 0.8}, "k_scale_B"),
    "forearm_inertia": ({"scale": 0.7}, "scale"),
    "frame_coupling": ({"coupling": 0.05}, "coupling"),
    "drive_delay": ({"delay_ms": 0.8}, "delay_ms"),
}


def _data(profile, effects, seed):
    return virtual_measurements(profile, effects, freq_hz=F, noise=NOISE, seed=seed)


@pytest.mark.parametrize("name", list(CASES))
def test_hidden_effect_is_found_fitted_and_recovered(profile, name):
    params, key = CASES[name]
    ms = _data(profile, [{"name": name, **params}], seed=21)
    base = validate(profile, ms)
    assert base.mean_residual > 3 * base.noise_floor  # well above the noise
    d = diagnose(profile, ms)
    assert d.noise_floor == pytest.approx(NOISE, rel=0.01)
    assert d.best.effect == name and d.best.significant and d.status == "explained", d.verdict
    assert name in d.verdict and d.best.explanation
    fit = fit_effects(profile, ms, [name])
    after = validate(fitted_profile(profile, fit), ms)
    assert after.mean_residual <= 1.5 * after.noise_floor
    assert after.mean_r2_mag >= 0.99
    assert fit.value(name, key) == pytest.approx(params[key], rel=0.10)


def test_no_hidden_effect_nothing_significant(profile):
    d = diagnose(profile, _data(profile, [], seed=22))
    assert d.status == "ok" and not d.base_significant and d.significant == []
    assert "nothing significant" in d.verdict
    for c in d.candidates:
        assert c.mean_heldout <= 1.1 * d.noise_floor or c.removed <= 0


def test_two_hidden_effects_found_by_running_the_loop_twice(profile):
    hidden = [{"name": "tower_scale", "k_scale_C": 0.85}, {"name": "forearm_inertia", "scale": 0.9}]
    ms = virtual_measurements(profile, hidden, freq_hz=np.geomspace(5, 400, 70), noise=NOISE, seed=23)
    prof, found = profile, []
    for _ in range(2):
        d = diagnose(prof, ms)
        assert d.best.significant, d.verdict
        found.append(d.best.effect)
        prof = fitted_profile(prof, fit_effects(prof, ms, [d.best.effect]))
    assert sorted(found) == ["forearm_inertia", "tower_scale"]
    final = validate(prof, ms)
    assert final.mean_residual <= 1.5 * final.noise_floor and final.mean_r2_mag >= 0.99
    eff = {e["name"]: e for e in prof.effects}
    assert eff["tower_scale"]["k_scale_C"] == pytest.approx(0.85, rel=0.1)
    assert eff["forearm_inertia"]["scale"] == pytest.approx(0.9, rel=0.1)


def test_effect_outside_the_candidates_is_reported_unexplained(profile):
    ms = _data(profile, [{"name": "belt_span", "l1_ref_mm": 300.0}], seed=24)
    d = diagnose(profile, ms, candidates=["forearm_inertia", "drive_delay"])
    assert d.base_significant and d.status in ("unexplained", "partial")
    assert "explains" in d.verdict and "Most likely" not in d.verdict
    assert any(e.key == "height" for e in d.evidence)  # the signature is still described


def test_wrong_parameters_of_an_existing_effect_call_for_a_refit(profile):
    wrong = profile.with_(effects=({"name": "belt_span", "l1_ref_mm": 600.0, "loop_mm": 1500.0},))
    ms = _data(profile, [{"name": "belt_span", "l1_ref_mm": 300.0}], seed=25)
    d = diagnose(wrong, ms)
    assert d.status == "explained" and d.best.refit and d.best.effect.endswith("belt_span"), d.verdict
    # new effects add nothing to the refit of the base and the profile's own effect
    assert [c.label for c in d.significant] == ["refit base dynamics+belt_span"]
    assert "--add" not in d.best.command


def test_pose_folds_keep_poses_together(profile):
    ms = _data(profile, [], seed=1)
    folds = pose_folds(ms, 4)
    assert len(folds) == 4 and sorted(np.concatenate(folds).tolist()) == list(range(len(ms)))
    for f in folds:
        others = set(np.setdiff1d(np.arange(len(ms)), f))
        for i in f:
            assert all(tuple(ms[j].position_mm) != tuple(ms[i].position_mm) for j in others)


def test_cli_loop_diagnose_fit_validate(tmp_path, capsys, profile):
    from cli_util import run, run_json

    from ffcomp.profile import load_profile

    d = tmp_path / "data"
    run_json(capsys, "virtual-measure", "-o", d, "--effect", "drive_delay=1.2", "--n", "60", "--seed", "5")
    diag = run_json(capsys, "diagnose", d)
    assert diag["status"] == "explained" and diag["candidates"][0]["effect"] == "drive_delay"
    assert any("delay" in e for e in diag["candidates"][0]["evidence"])
    out = run_json(capsys, "fit", d, "--add", "drive_delay", "-o", tmp_path / "p2.toml")
    assert out["mean_residual_after"] < 1.5 * out["noise_floor"] < out["mean_residual_before"]
    p2 = load_profile(tmp_path / "p2.toml")
    assert p2.effects[0]["name"] == "drive_delay" and p2.effects[0]["delay_ms"] == pytest.approx(1.2, rel=0.1)
    code, text, _ = run(capsys, "validate", d, "--profile", tmp_path / "p2.toml", "--compare",
                        "ffcomp/data/monoprice_delta_pro.toml")
    assert code == 0 and "before / after" in text
    code, text, _ = run(capsys, "diagnose", d, "--profile", tmp_path / "p2.toml")
    assert code == 0 and "nothing significant" in text
    code, _, err = run(capsys, "fit", d, "--add", "warp_drive")
    assert code != 0 and "unknown effect" in err
