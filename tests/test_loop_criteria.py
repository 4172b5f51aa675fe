"""The model loop on sets it has never seen (issue 11's criteria, on small sets).

Paper-frame delta (arm 330, radius 155, H_ez 25 mm), 2 % complex noise, coherence column from 50
averages and no ``averages`` key; the profile under test is what ``identify`` makes of the two
identification sweeps in the set.  Full-size figures: ``benchmarks/bench_diagnose.py``.
"""

from dataclasses import replace

import numpy as np
import pytest
from loop_sets import PLUGIN, identified, make_set, truth

from ffcomp.loop.diagnose import diagnose
from ffcomp.loop.fit import fit_effects, fitted_profile
from ffcomp.loop.validate import validate

BELT = {"name": "belt_span", "l1_ref_mm": 300.0, "loop_mm": 1300.0}
TOWER_B = {"name": "tower_scale", "k_scale_B": 0.75}
FOREARM = {"name": "forearm_inertia", "scale": 1.0}


def _loop(profile, ms, max_rounds=5):
    """diagnose -> fit the best significant candidate -> ... until nothing significant is left."""
    applied = []
    for _ in range(max_rounds):
        d = diagnose(profile, ms)
        if d.status in ("ok", "unexplained") or not d.significant:
            return profile, applied, d
        best = d.significant[0]
        profile = fitted_profile(profile, fit_effects(profile, ms, [] if best.refit else [best.effect]))
        applied.append(best.label)
    return profile, applied, d


def test_no_hidden_effect_nothing_reported():
    ms = make_set([], n_freq=150, heights=(30.0,), seed=2)
    _, prof = identified(ms)
    d = diagnose(prof, ms)
    # no physical effect; at most the base itself (the two-sweep b_nt is a few percent off by chance)
    assert all(c.refit and c.effect == "base dynamics" for c in d.significant), d.verdict
    final, applied, last = _loop(prof, ms)
    assert applied in ([], ["refit base dynamics"]) and last.status == "ok", (applied, last.verdict)
    v = validate(final, ms)
    assert v.noise_source == "data" and v.noise_floor == pytest.approx(0.02, rel=0.1)
    assert v.mean_residual <= 1.25 * v.noise_floor


def test_one_hidden_effect_tower_b_ranked_first_applied_with_the_base():
    ms = make_set([TOWER_B], n_freq=60, heights=(30.0,), seed=3)
    ident, prof = identified(ms)
    assert ident.k < 0.9 * truth().dynamics.k[0]  # the two-sweep identification is biased
    assert any("towers B and C" in w for w in ident.warnings)  # and says so, with the sweeps to add
    d = diagnose(prof, ms)
    assert d.best.effect == "tower_scale" and d.best.significant and d.status == "explained", d.verdict
    fit = fit_effects(prof, ms, ["tower_scale"])
    assert fit.base is not None  # the base was refitted with the effect
    after = validate(fitted_profile(prof, fit), ms)
    assert after.mean_residual <= 1.5 * after.noise_floor
    assert fit.value("tower_scale", "k_scale_B") == pytest.approx(0.75, rel=0.10)
    assert fit.base["k"] == pytest.approx(truth().dynamics.k[0], rel=0.05)
    est = {(e.effect, e.param): e for e in fit.estimates}
    assert np.isfinite(est[("base", "m")].stderr) and not est[("base", "m")].at_bound


def test_one_hidden_effect_belt_span_ranked_first_and_recovered():
    ms = make_set([BELT], n_freq=50, heights=(30.0, 230.0), seed=4)
    _, prof = identified(ms)
    d = diagnose(prof, ms)
    assert d.best.effect == "belt_span" and d.best.significant, d.verdict
    fit = fit_effects(prof, ms, ["belt_span"])
    after = validate(fitted_profile(prof, fit), ms)
    assert after.mean_residual <= 1.5 * after.noise_floor
    assert fit.value("belt_span", "l1_ref_mm") == pytest.approx(300.0, rel=0.10)


def test_three_hidden_effects_recovered_by_running_the_loop():
    ms = make_set([BELT, TOWER_B, FOREARM], n_freq=45, heights=(30.0, 230.0), seed=5)
    _, prof = identified(ms)
    final, applied, d = _loop(prof, ms)
    assert sorted(applied) == ["belt_span", "forearm_inertia", "tower_scale"], (applied, d.verdict)
    v = validate(final, ms)
    assert v.mean_residual <= 1.75 * v.noise_floor
    eff = {e["name"]: e for e in final.effects}
    assert eff["tower_scale"]["k_scale_B"] == pytest.approx(0.75, rel=0.1)
    assert eff["forearm_inertia"]["scale"] == pytest.approx(1.0, rel=0.2)


@pytest.mark.parametrize("what", ["delta_radius", "arm_length", "tower_frame"])
def test_geometry_and_frame_errors_are_named_as_such(what):
    ms = make_set([], n_freq=50, heights=(30.0, 230.0), seed=6)
    _, prof = identified(ms)
    g = prof.geometry
    wrong = {"delta_radius": dict(delta_radius_mm=(160.0,) * 3), "arm_length": dict(arm_length_mm=(340.0,) * 3),
             "tower_frame": dict(tower_angles_deg=(210.0, 330.0, 90.0))}[what]
    d = diagnose(prof.with_(geometry=replace(g, **wrong)), ms)
    assert d.best.kind == "geometry" and d.best.effect == what and d.best.significant, d.verdict
    assert d.verdict.startswith("Geometry, not a physical effect")
    if what == "delta_radius":
        assert d.best.params["delta_radius_mm"] == pytest.approx(155.0, abs=1.0)
        assert "delta radius 15" in d.verdict and "profile set" in d.verdict
    elif what == "arm_length":
        assert d.best.params["arm_length_mm"] == pytest.approx(330.0, abs=1.5)
    else:
        assert "tower_angles_deg=0,120,240" in d.best.command and "paper frame" in d.verdict


def test_effect_outside_the_library_identify_diagnose_and_a_plugin():
    from ffcomp.model.effects import load_plugin

    load_plugin(str(PLUGIN))
    mount = {"name": "motor_mount", "f_hz": 250.0, "zeta": 0.03, "mu": 0.6, "zeta_zero": 0.02}
    ms = make_set([mount], n_freq=100, heights=(30.0,), seed=7)
    ident, prof = identified(ms)
    # identify: physical values, a warning naming the sweep and the band, still a usable profile
    assert min(ident.m, ident.c, ident.b, ident.k, ident.b_nt) >= 0
    assert any("carriage sweep" in w and "Hz" in w for w in ident.warnings)
    band = [w for w in ident.warnings if "worst in" in w][0].split("worst in ")[1].split(" Hz")[0]
    lo, hi = (float(x) for x in band.split("-"))
    assert lo <= 250.0 <= hi + 5.0
    # diagnose: unexplained, with the fixed-band evidence (every pose, the carriage sweep too)
    d = diagnose(prof, ms)
    assert d.status == "unexplained", d.verdict
    fb = [e for e in d.evidence if e.key == "fixed_band"]
    assert fb and "carriage sweep" in fb[0].text and "7 of 7 poses" in fb[0].text
    # once the user's plug-in is named, diagnose finds it; fitted jointly with the base it brings the
    # residual to the floor
    d2 = diagnose(prof, ms, extra=["motor_mount"])
    assert d2.best.effect == "motor_mount" and d2.status == "explained", d2.verdict
    fit = fit_effects(prof, ms, ["motor_mount"])
    after = validate(fitted_profile(prof, fit), ms)
    assert after.mean_residual <= 1.5 * after.noise_floor
    assert fit.value("motor_mount", "f_hz") == pytest.approx(250.0, rel=0.02)
    assert fitted_profile(prof, fit).effects[0]["plugin"].endswith("effects_example_motor_mount.py")
