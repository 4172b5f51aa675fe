"""ffcomp validate: metrics, Table II layout, bands, comparison, HTML/PNG output, robustness."""

import json
import re
from dataclasses import replace

import numpy as np
import pytest

from ffcomp.loop.validate import band_edges, compare, validate
from ffcomp.measure.frf_file import FrfMeasurement, save_frf
from ffcomp.measure.virtual import measurement_plan, virtual_measurements

F = np.geomspace(5, 400, 80)


@pytest.fixture(scope="module")
def belt_data(profile):
    return virtual_measurements(profile, [{"name": "belt_span", "l1_ref_mm": 300.0}], freq_hz=F, noise=0.02, seed=11)


def test_perfect_model_scores(profile):
    ms = virtual_measurements(profile, [], freq_hz=F, noise=0.0)
    rep = validate(profile, ms)
    assert rep.mean_residual < 1e-12 and rep.noise_floor == 0.0
    assert rep.mean_r2_mag == pytest.approx(1.0) and rep.mean_r2_phase == pytest.approx(1.0)
    noisy = validate(profile, virtual_measurements(profile, [], freq_hz=F, noise=0.02, seed=1))
    assert noisy.mean_residual == pytest.approx(0.02, rel=0.15) and noisy.noise_floor == pytest.approx(0.02)


def test_table2_bands_and_worst(profile, belt_data):
    rep = validate(profile, belt_data)
    t2 = rep.table2()
    assert t2[0]["position_mm"] == [0.0, 0.0, 30.0] and len(t2) == 14
    assert set(t2[0]["rows"]) == {"x->x", "y->y", "z->z"}
    assert {"r2_mag", "r2_phase", "residual"} <= set(t2[0]["rows"]["x->x"])
    # the model was identified at the centre at z = 30: it fits there and fails at 130
    assert t2[0]["rows"]["x->x"]["residual"] < 0.04
    w = rep.worst()
    assert w["pose"]["position_mm"][2] == 130.0 and w["pose"]["mean_residual"] > 0.2
    names = {b["band"] for b in rep.by_band()}
    assert {"below", "drive+mechanical", "above"} <= names
    ranked = rep.ranked()
    assert ranked[0].residual >= ranked[-1].residual
    for s in ranked[:3]:
        assert s.worst_band is not None and np.isfinite(s.r2_mag_db)
    d = json.loads(json.dumps(rep.to_dict()))
    assert d["summary"]["n_measurements"] == len(belt_data) and d["measurements"][0]["residual"] == ranked[0].residual


def test_band_edges():
    names, edges = band_edges(60.0, [62.0, 62.0, 99.0])
    assert names == ["below", "drive+mechanical", "mechanical", "above"]
    assert edges[1] == pytest.approx(42.0) and edges[-2] == pytest.approx(1.4 * 99.0) and np.isinf(edges[-1])
    names, _ = band_edges(60.0, [116.0])
    assert names == ["below", "drive", "mechanical", "above"]


def test_compare_side_by_side(profile, belt_data):
    fixed = profile.with_(effects=({"name": "belt_span", "l1_ref_mm": 300.0},), name="fixed")
    c = compare(validate(profile, belt_data), validate(fixed, belt_data))
    assert c["mean_residual_after"] < 0.03 < 0.1 < c["mean_residual_before"]
    assert c["rows"][0]["residual_before"] >= c["rows"][-1]["residual_before"]


def _write(ms, d):
    d.mkdir(parents=True, exist_ok=True)
    for i, m in enumerate(ms):
        save_frf(m, d / f"m{i:02d}.csv")


def test_cli_validate_json_report_plots(tmp_path, capsys, profile, belt_data):
    from cli_util import run, run_json

    from ffcomp.profile import save_profile

    _write(belt_data[2:5] + belt_data[26:29], tmp_path / "d")
    save_profile(profile.with_(effects=({"name": "belt_span", "l1_ref_mm": 300.0},)), tmp_path / "p2.toml")
    out = run_json(capsys, "validate", tmp_path / "d", "--profile", tmp_path / "p2.toml", "--compare",
                   "ffcomp/data/monoprice_delta_pro.toml", "--report", tmp_path / "r.html", "--plot", tmp_path / "png",
                   "--bode", "3")
    assert out["compare"]["mean_residual_after"] < out["compare"]["mean_residual_before"]
    assert out["summary"]["noise_floor"] == pytest.approx(0.02, rel=1e-3)
    html = (tmp_path / "r.html").read_text()
    assert html.count("data:image/png;base64,") == 5 and "Table II" in html and "Before and after" in html
    assert not re.search(r'src="(?!data:)', html)  # self-contained
    pngs = sorted(p.name for p in (tmp_path / "png").iterdir())
    assert "error_map.png" in pngs and "bands.png" in pngs and sum(p.startswith("bode_") for p in pngs) == 6
    code, text, _ = run(capsys, "validate", tmp_path / "d")
    assert code == 0 and "Table II" in text and "worst fits" in text and "fails worst" in text


def test_robust_to_missing_coherence_mixed_grids_and_kinds(tmp_path, capsys, profile):
    from cli_util import run_json

    ms = virtual_measurements(profile, [], freq_hz=F, noise=0.02, seed=5)
    rng = np.random.default_rng(0)
    odd = []
    for i, m in enumerate(ms[:12]):
        f = np.geomspace(rng.uniform(3, 8), rng.uniform(250, 500), 60 + 7 * i)
        H = virtual_measurements(profile, [], freq_hz=f, noise=0.02, seed=i,
                                 plan=[measurement_plan(profile)[i]])[0].H
        odd.append(FrfMeasurement(f, H, None if i % 3 == 0 else m.coherence[:1].repeat(len(f)), m.kind,
                                  m.position_mm, m.input, m.output))
    _write(odd, tmp_path / "d")
    out = run_json(capsys, "validate", tmp_path / "d")
    assert out["summary"]["n_measurements"] == 12
    assert out["summary"]["mean_residual"] == pytest.approx(0.02, rel=0.25)
    srcs = {m["noise_source"] for m in out["measurements"]}
    assert srcs == {"data", "coherence"}
    assert out["summary"]["noise_floor"] == pytest.approx(0.02, rel=0.25)


def test_per_tower_klipper_geometry_profile(profile):
    """A different printer: Klipper tower angles, unequal arms, per-tower dynamics."""
    g = replace(profile.geometry, tower_angles_deg=(210.0, 330.0, 90.0), arm_length_mm=(300.0, 302.0, 299.0),
                delta_radius_mm=(140.0, 141.0, 139.5), print_radius_mm=110.0, effector_offset_z_mm=20.0)
    d = replace(profile.dynamics, k=(8.0e4, 9.0e4, 8.6e4), m=(0.15, 0.16, 0.155))
    other = profile.with_(geometry=g, dynamics=d, name="other delta")
    ms = virtual_measurements(other, [], freq_hz=F, noise=0.01, seed=2)
    assert max(np.hypot(*m.position_mm[:2]) for m in ms) <= 0.75 * 110 + 1e-9
    rep = validate(other, ms)
    assert rep.mean_residual == pytest.approx(0.01, rel=0.2)
    assert validate(profile, ms).mean_residual > 5 * rep.mean_residual  # the wrong printer's model is far off
