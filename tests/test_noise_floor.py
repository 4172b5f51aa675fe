"""The noise floor from the data itself, cross-checked with coherence and the averages count."""

import numpy as np
import pytest
from loop_sets import TRUTH, make_set

from ffcomp.measure.noise import below_floor_note, noise_floors
from ffcomp.measure.predict import BatchPredictor
from ffcomp.model.lpv import LpvModel
from ffcomp.profile import load_profile


def test_coherence_without_averages_key_is_overruled_by_the_data():
    ms = make_set([], n_freq=250, heights=(30.0,), averages=50)  # coherence of 50 averages, no header key
    nfs = noise_floors(ms)
    assert nfs.source == "data" and "disagree" in nfs.note and "averages" in nfs.note
    assert nfs.mean == pytest.approx(0.02, rel=0.12)
    assert np.nanmedian(nfs.from_coherence) == pytest.approx(0.02 * np.sqrt(50), rel=0.01)
    # the note says how many averages would reconcile them (50, within the data estimate's scatter)
    n = float(nfs.note.split("about ")[1].split()[0])
    assert 35 <= n <= 65


def test_coherence_with_the_right_averages_key_is_used():
    ms = make_set([], n_freq=120, heights=(30.0,), averages=50)
    ms = [type(m)(m.freq_hz, m.H, m.coherence, m.kind, m.position_mm, m.input, m.output, m.source,
                  meta={"averages": "50"}) for m in ms]
    nfs = noise_floors(ms)
    assert nfs.source == "coherence" and nfs.note == ""
    assert nfs.mean == pytest.approx(0.02, rel=0.01)


def test_model_ratio_removes_the_curvature_bias_of_a_coarse_grid():
    ms = make_set([], n_freq=50, heights=(30.0,), averages=1)
    raw = noise_floors([m for m in ms], override=None).from_data
    preds = BatchPredictor(ms)(LpvModel.from_profile(load_profile(TRUTH)))
    ratio = noise_floors(ms, predictions=preds).from_data
    assert np.mean(raw) > 1.1 * 0.02  # curvature inflates the raw estimate on 50 points
    assert np.mean(ratio) == pytest.approx(0.02, rel=0.12)


def test_override_and_flag_below_floor():
    ms = make_set([], n_freq=60, heights=(30.0,))
    nfs = noise_floors(ms, override=0.05)
    assert nfs.source == "given" and np.all(nfs.values == 0.05)
    with pytest.raises(ValueError, match="noise-floor"):
        noise_floors(ms, override=-1.0)
    assert "below the noise floor" in below_floor_note(0.02, 0.14, "coherence")
    assert below_floor_note(0.02, 0.021, "data") == ""


def test_virtual_measure_writes_averages_unless_told_not_to(tmp_path, capsys):
    from cli_util import run_json

    from ffcomp.measure.dataset import load_dataset

    for flag, expect in (([], "50"), (["--no-averages-key"], None)):
        d = tmp_path / f"d{len(flag)}"
        run_json(capsys, "virtual-measure", "-o", d, "--n", "20", "--averages", "50", "--heights", "30", *flag)
        m = load_dataset(d)[0]
        assert m.meta.get("averages") == expect
        assert m.coherence[0] == pytest.approx(1 / (1 + 50 * 0.02**2))
