"""UFF dataset 58 through pyuff (optional): round trip, coherence, quantities, metadata, missing package."""

import sys

import numpy as np
import pytest

from ffcomp.errors import MeasurementError
from ffcomp.measure.frf_file import FrfMeasurement

pyuff = pytest.importorskip("pyuff")

F = np.geomspace(5, 300, 40)


def _meas(i=0, coh=True):
    H = 1.0 / (1 + 1j * F / (50 + 10 * i)) * np.exp(-1j * F * 1e-3)
    return FrfMeasurement(F, H, np.linspace(0.8, 0.99, len(F)) if coh else None, "assembled",
                          np.array([10.0 * i, -5.0, 30.0]), "xyz"[i % 3], "xyz"[i % 3], f"test {i}")


def test_round_trip_with_coherence(tmp_path):
    from ffcomp.measure.uff import load_uff, save_uff

    ms = [_meas(0), _meas(1, coh=False), _meas(2)]
    save_uff(ms, tmp_path / "set.uff")
    back = load_uff(tmp_path / "set.uff")
    assert len(back) == 3
    for a, b in zip(ms, back):
        np.testing.assert_allclose(b.freq_hz, a.freq_hz, rtol=1e-5)
        np.testing.assert_allclose(b.H, a.H, rtol=1e-8)
        assert (b.kind, b.input, b.output) == (a.kind, a.input, a.output)
        np.testing.assert_allclose(b.position_mm, a.position_mm)
        assert (b.coherence is None) == (a.coherence is None)
        if a.coherence is not None:
            np.testing.assert_allclose(b.coherence, a.coherence, rtol=1e-6)


def test_accelerance_without_metadata(tmp_path):
    from ffcomp.measure.uff import load_uff

    Hd = 1.0 / (1 + 1j * F / 60)
    acc = Hd * (2j * np.pi * F) ** 2
    rec = pyuff.prepare_58(func_type=4, rsp_node=1, rsp_dir=-2, ref_node=1, ref_dir=2, data=acc, x=F, id1="rig",
                           abscissa_spacing=0, binary=0, ord_data_type=6, abscissa_spec_data_type=18,
                           ordinate_spec_data_type=12, orddenom_spec_data_type=8)
    pyuff.UFF(str(tmp_path / "a.unv")).write_sets([rec], mode="overwrite")
    with pytest.raises(MeasurementError, match="no position"):
        load_uff(tmp_path / "a.unv")
    m = load_uff(tmp_path / "a.unv", position_mm=(0, 0, 30))[0]
    assert (m.input, m.output) == ("y", "y")
    np.testing.assert_allclose(m.H, -Hd, rtol=1e-4)  # acceleration -> displacement, flipped response direction


def test_dataset_reads_uff_next_to_csv(tmp_path):
    from ffcomp.measure.dataset import load_dataset
    from ffcomp.measure.frf_file import save_frf
    from ffcomp.measure.uff import save_uff

    save_uff([_meas(0), _meas(1)], tmp_path / "b.uff")
    save_frf(_meas(2), tmp_path / "a.csv")
    ms = load_dataset(tmp_path)
    assert len(ms) == 3 and ms[0].path.endswith("a.csv") and ms[1].meta["uff_record"] == "0"


def test_missing_pyuff_is_a_clear_error(tmp_path, monkeypatch):
    from ffcomp.measure import uff

    (tmp_path / "x.uff").write_text("    -1\n")
    monkeypatch.setitem(sys.modules, "pyuff", None)
    assert not uff.pyuff_available()
    with pytest.raises(MeasurementError, match="pip install"):
        uff.load_uff(tmp_path / "x.uff")
