"""Virtual measurements, batched prediction, noise floors, data sets on disk."""

import numpy as np
import pytest

from ffcomp.errors import MeasurementError
from ffcomp.measure.frf_file import FrfMeasurement, load_frf, save_frf
from ffcomp.measure.noise import noise_floor, noise_from_data
from ffcomp.measure.predict import BatchPredictor, check_measurements, predict
from ffcomp.measure.virtual import measurement_plan, virtual_measurements
from ffcomp.model import LpvModel, frequency_response
from ffcomp.model.submodels import g_qd

F = np.geomspace(5, 400, 60)


def test_plan_has_identification_and_table2_sweeps(profile):
    plan = measurement_plan(profile)
    assert plan[0].kind == "carriage" and (plan[0].input, plan[0].output) == ("qA", "qA")
    assert (plan[1].kind, plan[1].input, plan[1].output) == ("assembled", "z", "qA")
    task = plan[2:]
    assert len(task) == 7 * 2 * 3
    assert {p.position_mm for p in task} >= {(0.0, 0.0, 30.0), (100.0, 0.0, 130.0), (0.0, -100.0, 30.0)}
    assert {p.position_mm[2] for p in task} == {30.0, 130.0}
    small = profile.with_(geometry=profile.geometry.__class__(print_radius_mm=60.0))
    assert max(np.hypot(*p.position_mm[:2]) for p in measurement_plan(small)) <= 45.0 + 1e-9


def test_virtual_measurements_are_the_model_plus_noise(profile):
    ms = virtual_measurements(profile, [], freq_hz=F, noise=0.0)
    model = LpvModel.from_profile(profile)
    d = profile.dynamics
    s = 2j * np.pi * F
    np.testing.assert_allclose(ms[0].H, g_qd(s, d.m[0], d.c[0], d.b[0], d.k[0], d.d0[0], d.d1[0], d.d2[0]),
                               rtol=1e-12)  # carriage alone = the paper's G_qd
    H = frequency_response(model, np.array([[100, 0, 130]]) * 1e-3, F, frame="task")[0, 0, 0]
    m = next(m for m in ms if m.input == m.output == "x" and tuple(m.position_mm) == (100, 0, 130))
    np.testing.assert_allclose(m.H, H, rtol=1e-12)
    a = virtual_measurements(profile, [{"name": "drive_delay", "delay_ms": 1.0}], freq_hz=F, noise=0.02, seed=4)
    b = virtual_measurements(profile, [{"name": "drive_delay", "delay_ms": 1.0}], freq_hz=F, noise=0.02, seed=4)
    np.testing.assert_array_equal(a[5].H, b[5].H)
    np.testing.assert_allclose(a[5].coherence, 1 / (1 + 0.02**2))
    assert "delay" not in a[5].source  # the hidden effect is not written into the files


def test_batch_predictor_matches_predict_on_mixed_grids(profile):
    model = LpvModel.from_profile(profile.with_(effects=({"name": "belt_span", "l1_ref_mm": 350.0},)))
    ms = virtual_measurements(profile, [], freq_hz=F, noise=0.0)
    rng = np.random.default_rng(1)
    mixed = []
    for i, m in enumerate(ms[:12]):
        f = np.sort(rng.uniform(3, 450, 30 + i)) if i % 2 else m.freq_hz
        mixed.append(FrfMeasurement(f, np.ones_like(f, complex), None, m.kind, m.position_mm, m.input, m.output))
    one = np.ones_like(F, complex)
    mixed.append(FrfMeasurement(F, one, None, "assembled", np.array([20.0, -30.0, 60.0]), "qB", "y"))
    mixed.append(FrfMeasurement(F, one, None, "carriage", np.array([50.0, 0.0, 30.0]), "qC", "qC"))
    for m, H in zip(mixed, BatchPredictor(mixed)(model)):
        np.testing.assert_allclose(H, predict(model, m), rtol=1e-10, atol=1e-14)


def test_check_measurements_names_the_file(model):
    bad = FrfMeasurement(F, np.ones_like(F, complex), None, "carriage", np.zeros(3), "x", "qA", path="c.csv")
    with pytest.raises(MeasurementError, match="c.csv.*carriage input"):
        check_measurements(model, [bad])
    far = FrfMeasurement(F, np.ones_like(F, complex), None, "assembled", np.array([300.0, 0, 30]), "x", "x",
                         path="far.csv")
    with pytest.raises(MeasurementError, match="far.csv.*outside the profile's workspace"):
        check_measurements(model, [far])


@pytest.mark.parametrize("rel", [0.005, 0.02, 0.05])
def test_noise_floor_from_coherence_and_from_data(profile, rel):
    ms = virtual_measurements(profile, [], freq_hz=np.geomspace(5, 400, 150), noise=rel, seed=3)
    for m in ms[:6]:
        v, src = noise_floor(m)
        assert src == "coherence" and v == pytest.approx(rel, rel=1e-6)
        assert noise_from_data(m.freq_hz, m.H) == pytest.approx(rel, rel=0.3)
    m = ms[3]
    v, src = noise_floor(FrfMeasurement(m.freq_hz, m.H, None, m.kind, m.position_mm, m.input, m.output))
    assert src == "data" and v == pytest.approx(rel, rel=0.3)
    m2 = FrfMeasurement(m.freq_hz, m.H, m.coherence, m.kind, m.position_mm, m.input, m.output, meta={"averages": "16"})
    assert noise_floor(m2)[0] == pytest.approx(rel / 4, rel=1e-6)  # H1 error falls with sqrt(averages)


def test_virtual_measure_cli_writes_a_loadable_set(tmp_path, capsys):
    from cli_util import run, run_json

    out = run_json(capsys, "virtual-measure", "-o", tmp_path / "d", "--effect", "tower_scale:k_scale_B=0.8",
                   "--effect", "drive_delay=0.5", "--n", "40", "--seed", "7", "--truth", tmp_path / "truth.toml")
    assert len(out["files"]) == 44
    m = load_frf(out["files"][1])
    assert m.kind == "assembled" and m.input == "z" and m.output == "qA" and m.coherence is not None
    from ffcomp.profile import load_profile

    truth = load_profile(tmp_path / "truth.toml")
    assert {e["name"]: e for e in truth.effects}["tower_scale"]["k_scale_B"] == 0.8
    assert {e["name"]: e for e in truth.effects}["drive_delay"]["delay_ms"] == 0.5
    code, _, err = run(capsys, "virtual-measure", "-o", tmp_path / "e", "--effect", "no_such_effect=1")
    assert code != 0 and "unknown effect" in err
    code, _, err = run(capsys, "virtual-measure", "-o", tmp_path / "e", "--effect", "belt_span:nope=1")
    assert code != 0 and "no parameter 'nope'" in err


def test_dataset_skips_notes_and_reads_frf_files(tmp_path, profile):
    from ffcomp.measure.dataset import load_dataset

    ms = virtual_measurements(profile, [], freq_hz=F, noise=0.01)
    for i, m in enumerate(ms[:3]):
        save_frf(m, tmp_path / f"m{i}.csv", polar=bool(i % 2))
    (tmp_path / "README.md").write_text("notes")
    (tmp_path / "raw.csv").write_text("#time,accel_x\n0,1\n")
    skipped = []
    got = load_dataset(tmp_path, skipped=skipped)
    assert len(got) == 3 and {p.split("/")[-1] for p, _ in skipped} == {"raw.csv"}
    with pytest.raises(MeasurementError, match="no measurements found"):
        load_dataset(tmp_path / "nothing" if (tmp_path / "nothing").mkdir() is None else tmp_path)
