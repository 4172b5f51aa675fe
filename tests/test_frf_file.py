"""FRF measurement files (shared/FRF_FORMAT.md): round trips and every malformed case."""

import numpy as np
import pytest

from ffcomp.errors import MeasurementError
from ffcomp.measure.frf_file import FrfMeasurement, load_frf, load_frf_dir, save_frf

GOOD = """# ffcomp-frf 1
# kind: assembled            carriage = forearms and effector detached
# position_mm: 0, 0, 30      task-space point
# input: z                   the commanded coordinate
# output: qA
# source: bench test
# sweep_type: chirp
freq_hz,real,imag,coherence
5.0,1.0012,-0.0031,0.998
6.0,1.0020,-0.0040,0.997
7.0,1.0031,-0.0052,0.990
"""


def test_reads_the_spec_example(tmp_path):
    p = tmp_path / "a.csv"
    p.write_text(GOOD)
    m = load_frf(p)
    assert m.kind == "assembled" and m.input == "z" and m.output == "qA"
    np.testing.assert_array_equal(m.position_mm, [0, 0, 30])
    assert m.H[0] == pytest.approx(1.0012 - 0.0031j)
    assert m.coherence[2] == pytest.approx(0.99)
    assert m.meta == {"sweep_type": "chirp"}  # unknown keys survive


def test_round_trip_rect_and_polar(tmp_path):
    f = np.geomspace(2, 300, 50)
    H = np.exp(-1j * f / 50) / (1 + 1j * f / 80)
    m = FrfMeasurement(f, H, np.linspace(0.5, 1, 50), "carriage", np.array([1.5, -2, 30]), "qB", "qB", "t",
                       meta={"x": "1"})
    for polar in (False, True):
        p = tmp_path / f"r{polar}.csv"
        save_frf(m, p, polar=polar)
        r = load_frf(p)
        np.testing.assert_allclose(r.H, H, rtol=1e-8)
        np.testing.assert_allclose(r.freq_hz, f, rtol=1e-9)
        assert r.meta == {"x": "1"} and r.kind == "carriage" and r.input == "qB"
    assert len(load_frf_dir(tmp_path)) == 2


@pytest.mark.parametrize(
    "old,new,line,fragment",
    [
        ("6.0,1.0020", "6.0,1.0O20", 10, "not a number: '1.0O20'"),
        ("7.0,1.0031", "5.5,1.0031", 11, "strictly increasing"),
        ("# ffcomp-frf 1", "# ffcomp-frf 2", 1, "unsupported format version"),
        ("# ffcomp-frf 1\n", "", 1, "missing magic line"),
        ("# kind: assembled ", "# kind: partial ", 2, "kind must be one of"),
        ("# position_mm: 0, 0, 30", "# position_mm: 0, 0", 3, "position_mm"),
        ("0.998", "1.5", 9, "coherence 1.5 outside"),
        ("freq_hz,real,imag,coherence", "freq_hz,re,im", 8, "bad column header"),
        ("6.0,1.0020,-0.0040,0.997", "6.0,1.0020,-0.0040", 10, "expected 4 values"),
        ("# input: z ", "# input: w ", 4, "input must be one of"),
    ],
)
def test_malformed_files_name_file_line_and_value(tmp_path, old, new, line, fragment):
    assert old in GOOD
    p = tmp_path / "bad.csv"
    p.write_text(GOOD.replace(old, new, 1))
    with pytest.raises(MeasurementError) as e:
        load_frf(p)
    msg = str(e.value)
    assert fragment in msg
    assert f"{p}:{line}" in msg if fragment not in ("missing magic line",) else str(p) in msg


def test_missing_header_and_empty(tmp_path):
    p = tmp_path / "b.csv"
    p.write_text(GOOD.replace("# output: qA\n", ""))
    with pytest.raises(MeasurementError, match="missing header '# output"):
        load_frf(p)
    p.write_text("# ffcomp-frf 1\n# kind: carriage\n")
    with pytest.raises(MeasurementError, match="no data rows"):
        load_frf(p)
    p.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(MeasurementError, match="UTF-8"):
        load_frf(p)
    with pytest.raises(MeasurementError, match="no such file"):
        load_frf_dir(tmp_path / "none")
