"""Shapers applied on the simulator, the variant registry, the bench and the simulation CLI."""

import json

import numpy as np
import pytest
from cli_util import run

from ffcomp.kinematics import inverse
from ffcomp.sim import bench, shapers
from ffcomp.sim.moves import pattern, plan_polyline
from ffcomp.sim.plant import DeltaPlant


@pytest.fixture(scope="module")
def plant(model):
    return DeltaPlant(model)


def test_tuning_is_the_centre_xy_mode(profile, model):
    from ffcomp.model.modes import modes

    tu = bench.shaper_tuning(profile)
    m = modes(model, np.array([[0.0, 0.0, 0.03]]))
    lateral = m.freq_hz[0][m.direction[0] != "z"]
    assert tu.centre_hz == pytest.approx(lateral.min())
    assert lateral.min() < tu.avg_hz < 1.3 * lateral.max()  # lateral modes split (and rise) off-centre


def test_shaped_move_excites_the_centre_mode_less(plant, profile):
    f = bench.shaper_tuning(profile).centre_hz
    t, xyz = plan_polyline([[-0.01, 0.0, 0.03], [0.01, 0.0, 0.03]], 0.15, 10.0, pad_s=(0.05, 0.3))
    moving = np.flatnonzero(np.any(np.diff(xyz, axis=0) != 0, axis=1))
    t_stop = t[moving[-1] + 1]
    cmds = [inverse(plant.geometry, xyz)]
    for name in shapers.SHAPERS:
        A, T = shapers.shaper_impulses(name, f)
        assert A.sum() == pytest.approx(1.0, abs=1e-12)
        # EI shapers leave exactly their design tolerance (5 %) at the design frequency
        assert shapers.residual_vibration(A, T, f) <= shapers.EI_VIBRATION_TOLERANCE * 1.03
        cmds.append(inverse(plant.geometry, shapers.shape_cartesian(t, xyz, (A, T), (A, T), None)))
    res = plant.simulate(t, np.stack(cmds))
    after = t > t_stop + 0.03  # every shaped move has ended (longest shaper: 19 ms)
    ringing = np.abs(res.xyz_m[:, after] - xyz[-1]).max(axis=(1, 2))
    assert ringing[0] > 20e-6  # the unshaped stop rings at the centre mode
    for k, name in enumerate(shapers.SHAPERS, start=1):
        assert ringing[k] < 0.2 * ringing[0], name


def test_registry_rows_and_custom_variant(profile):
    names = list(bench.VARIANTS)
    assert names[0] == "none"
    for s in shapers.SHAPERS:
        assert f"{s}-centre" in names and f"{s}-avg" in names
    info = bench.describe_variant("mzv-avg", profile)
    assert info["freq_hz"] == pytest.approx(bench.shaper_tuning(profile).avg_hz)
    assert 0 < info["smoothing_mm"] < 0.2

    @bench.register_variant("test-offset")
    def _offset(profile, t_s, xyz_ref_m, q_ref_m):
        return q_ref_m + 1e-5

    try:
        tr = pattern("square", profile.geometry_si(), (0, 0, 30), loops=1, side_m=0.01)
        c = bench.run_case(DeltaPlant.from_profile(profile), profile, tr, ["none", "test-offset"])
        assert c.names == ("none", "test-offset")
        dz = c.xyz_act_m[1, -1, 2] - c.xyz_act_m[0, -1, 2]
        assert dz == pytest.approx(1e-5, rel=1e-3)  # all carriages up 10 um = nozzle up 10 um
        assert bench.describe_variant("test-offset", profile)["kind"] == "compensation"
    finally:
        del bench.VARIANTS["test-offset"]


def test_crop_at_rest(profile):
    geom = profile.geometry_si()
    tr = pattern("zigzag", geom, (0, 0, 2), lines=8)
    cut = bench.crop_at_rest(tr, 0.6, geom)
    assert cut.duration_s <= 0.6 + 0.05 + 0.25 + 1e-9
    assert np.all(cut.xyz_m[0] == cut.xyz_m[1])  # starts at rest
    assert np.all(cut.xyz_m[-1] == cut.xyz_m[-2])  # ends at rest
    acc = np.diff(cut.xyz_m, 2, axis=0) / 1e-6
    assert np.abs(acc).max() < 2 * 10.0 + 1e-6  # stopped, not cut: planner-like accelerations only
    assert np.allclose(inverse(geom, cut.xyz_m), cut.q_m, atol=1e-12)


def test_bench_quick_cli(capsys, tmp_path):
    # (no wall-time bound: the suite runs on two workers of a shared machine; speed is the
    # benchmarks' business)
    code, out, err = run(capsys, "bench", "--quick", "--out", tmp_path, "--json")
    assert code == 0, err
    d = json.loads(out)
    rows = [r["name"] for r in d["summary"]]
    assert rows == list(bench.VARIANTS)
    by = {r["name"]: r for r in d["summary"]}
    assert by["zvd-centre"]["lag_rms_um"] < 0.5 * by["none"]["lag_rms_um"]
    assert 2.0 < by["none"]["lag_ms"] < 4.0
    for name in ("bench.md", "bench.json", "bench_rms.png", "bench_time.png", "bench_bed.png"):
        assert (tmp_path / name).stat().st_size > 0
    md = (tmp_path / "bench.md").read_text()
    assert "| mzv-centre |" in md and "| none |" in md


GCODE = """G90
M204 S10000
G1 Z20 F6000
G1 X20 Y0 F9000
G1 X20 Y20
G1 X0 Y20
G1 X0 Y0
G4 P200
"""


def test_simulate_cli(capsys, tmp_path):
    g = tmp_path / "sq.gcode"
    g.write_text(GCODE)
    other = tmp_path / "slow.gcode"
    other.write_text(GCODE.replace("F9000", "F3000"))
    code, out, err = run(capsys, "simulate", g, "--shaper", "zvd@62", "--shape-z", "--compare", other, "--quantize",
                         "--plot", tmp_path / "p", "--json")
    assert code == 0, err
    d = json.loads(out)
    names = [r["name"] for r in d["runs"]]
    assert names == ["planned", "zvd@62+z", "slow.gcode"]
    assert d["quantized"] is True
    assert all(r["lag"]["rms_norm_um"] > 0 for r in d["runs"])
    assert (tmp_path / "p_time.png").exists() and (tmp_path / "p_bed.png").exists()
    code, out, err = run(capsys, "simulate", g)  # starts at the planner's default (0, 0, 0)
    assert code == 0, err
    assert "planned" in out and "lag" in out
    code, out, err = run(capsys, "simulate", g, "--shaper", "nope@3")
    assert code != 0


def test_sim_measure_cli(capsys, tmp_path):
    from ffcomp.measure.frf_file import load_frf

    f = tmp_path / "m.csv"
    code, out, err = run(capsys, "sim-measure", "--at", "0,0,30", "--input", "z", "--output", "qA", "-o", f,
                         "--fmin", "20", "--fmax", "150", "--periods", "1", "--plot", tmp_path / "m.png",
                         "--json")
    assert code == 0, err
    d = json.loads(out)
    assert d["max_rel_dev_from_model"] < 0.05
    m = load_frf(f)
    assert m.kind == "assembled" and m.output == "qA" and m.coherence is not None
    assert (tmp_path / "m.png").exists()
    code, out, err = run(capsys, "sim-measure", "--kind", "carriage", "--input", "z", "-o", f)
    assert code != 0


def test_limit_ratios_and_table(geom):
    """Every table row is divided by the limit row's lag-aligned RMS, case by case."""
    from ffcomp.sim import metrics

    tr = pattern("square", geom, (0.0, 0.0, 30.0), loops=1)
    reps = []
    for off in (30e-6, 10e-6):  # a row 30 um off, the "limit" 10 um off, both along x
        act = tr.xyz_m + np.array([off, 0.0, 0.0]) * np.sin(np.arange(len(tr.t_s)) * 0.3)[:, None]
        reps.append(metrics.evaluate(tr.t_s, tr.xyz_m, act))
    rows = [{"name": "row", "kind": "compensation"}, {"name": bench.LIMIT_ROW, "kind": "compensation"}]
    res = bench.BenchResult("p", bench.ShaperTuning(60.0, 62.0, 0.1, 0.03), rows)
    res.cases.append(bench.CaseResult(tr, ("row", bench.LIMIT_ROW), np.stack([tr.xyz_m] * 2), tuple(reps), 0.0))
    r = bench.limit_ratios(res)
    assert r[0][0] == pytest.approx(3.0, rel=0.02) and r[1][0] == pytest.approx(1.0)
    table = bench.markdown_table(res)
    assert "Distance from the physical limit" in table and "| row | 3.00x |" in table


def test_bench_cases_include_polygon_and_z_loops_and_fit_a_smaller_bed(profile):
    from pathlib import Path

    from ffcomp.profile import load_profile

    small = load_profile(Path(__file__).resolve().parents[1] / "samples" / "profiles" / "other_delta.toml")
    for p in (profile, small):
        names = [c.name for c in bench.bench_cases(p)]
        assert sum(n.startswith("polygon") for n in names) == 2 and sum(n.startswith("zmove") for n in names) == 2
    z = [c for c in bench.bench_cases(small) if c.name.startswith("zmove")][0]
    assert np.ptp(z.xyz_m[:, 2]) > 0.01  # the z loop climbs


def test_simulate_reports_the_printed_lines_apart(profile, tmp_path, capsys):
    """``simulate_gcode`` scores the samples where the plan extrudes while it moves on their own
    (the printed lines): the same per-sample errors as the whole report, masked; a travel-only file
    has no such samples; the CLI prints and the JSON carries them."""
    from ffcomp.pipeline.sim_flow import extruding_samples, simulate_gcode

    lines = ["G90", "M83", "M204 S10000", "G1 Z5 F6000", "G1 X20 Y0 F9000"]
    for x, y in ((20, 20), (0, 20), (0, 0), (20, 0)):
        lines.append(f"G1 X{x} Y{y} E1.0")
    lines += ["G1 X-20 Y-10 F9000", "G4 P200"]
    g = tmp_path / "sq.gcode"
    g.write_text("\n".join(lines) + "\n")
    rep = simulate_gcode(profile, g, shaper="zv@62")
    m = extruding_samples(rep.reference)
    assert 0.3 < m.mean() < 0.9 and rep.extruded_share == pytest.approx(m.mean())
    for r in rep.runs:
        lag = np.sqrt(np.mean(np.sum(r.err_lag_m[m] ** 2, axis=1))) * 1e6
        assert r.extruded_um[0] == pytest.approx(lag)
        assert r.extruded_um[1] == pytest.approx(np.sqrt(np.mean(r.contour_m[m] ** 2)) * 1e6)
    assert rep.runs[1].extruded_um[0] < rep.runs[0].extruded_um[0]  # the shaper helps there too
    dry = tmp_path / "dry.gcode"
    dry.write_text(GCODE)
    rep = simulate_gcode(profile, dry)
    assert rep.extruded_share == 0.0 and rep.runs[0].extruded_um is None
    code, out, err = run(capsys, "simulate", g, "--json")
    assert code == 0, err
    d = json.loads(out)
    assert d["extruded_share"] > 0.3 and d["runs"][0]["extruded_lag_rms_um"] > 0
    code, out, err = run(capsys, "simulate", g)
    assert code == 0 and "printed lines" in out
