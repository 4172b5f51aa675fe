"""Time-domain data to FRF: H1 and coherence, Klipper raw accelerometer CSV, acceleration -> displacement."""

import numpy as np
import pytest
from scipy import signal

from ffcomp.errors import MeasurementError
from ffcomp.measure.frf_file import load_frf
from ffcomp.measure.timedomain import frf_from_time, read_timeseries

FS = 3200.0
WN, ZETA = 2 * np.pi * 80.0, 0.08


def _sim(seconds=24.0, noise_accel=0.0, seed=0, t0=1234.5):
    """Command (mm, random multisine-ish), response position (mm) and acceleration (mm/s^2)."""
    rng = np.random.default_rng(seed)
    n = int(seconds * FS)
    t = np.arange(n) / FS
    u = signal.lfilter(*signal.butter(4, 600 / (FS / 2)), rng.standard_normal(n)) * 0.05
    sys_pos = signal.lti([WN**2], [1, 2 * ZETA * WN, WN**2])
    sys_acc = signal.lti([WN**2, 0, 0], [1, 2 * ZETA * WN, WN**2])
    _, y, _ = signal.lsim(sys_pos, u, t)
    _, a, _ = signal.lsim(sys_acc, u, t)
    a = a + noise_accel * rng.standard_normal(n)
    return t + t0, u, y, a


def _truth(f):
    s = 2j * np.pi * f
    return WN**2 / (s**2 + 2 * ZETA * WN * s + WN**2)


def _write(path, header, cols):
    with open(path, "w") as fh:
        fh.write(header + "\n")
        for row in zip(*cols):
            fh.write(",".join(f"{v:.12g}" for v in row) + "\n")


def test_klipper_accelerometer_csv_to_displacement_frf(tmp_path):
    t, u, _, a = _sim(noise_accel=5.0)
    _write(tmp_path / "adxl345-x.csv", "#time,accel_x,accel_y,accel_z", (t, a, 0 * a, 9806.65 + 0 * a))
    _write(tmp_path / "cmd.csv", "time,x", (t, u))
    resp, cmd = read_timeseries(tmp_path / "adxl345-x.csv"), read_timeseries(tmp_path / "cmd.csv")
    assert set(resp.columns) == {"accel_x", "accel_y", "accel_z"} and resp.t_s[0] == pytest.approx(1234.5)
    est = frf_from_time(cmd, "x", resp, "accel_x", resolution_hz=2.0)
    assert est.quantity == "acceleration" and est.freq_hz[0] >= 5.0 and est.freq_hz[-1] <= 0.4 * est.fs_hz + 1e-9
    assert est.fs_hz == pytest.approx(FS, rel=1e-3)
    band = (est.freq_hz > 10) & (est.freq_hz < 400)
    err = np.abs(est.H[band] / _truth(est.freq_hz[band]) - 1)
    assert np.median(err) < 0.02 and np.max(err) < 0.15
    assert np.median(est.coherence[band]) > 0.95
    assert est.averages >= 7


def test_position_response_and_cli(tmp_path, capsys):
    from cli_util import run, run_json

    t, u, y, _ = _sim(seconds=12.0)
    _write(tmp_path / "run.csv", "# sweep log\ntime,x_cmd,x_meas", (t, u, y))
    out = run_json(capsys, "frf", tmp_path / "run.csv", "-o", tmp_path / "frf.csv", "--command-column", "x_cmd",
                   "--response-column", "x_meas", "--input", "x", "--output-axis", "x", "--at", "10,0,30")
    assert out["quantity"] == "position"
    m = load_frf(tmp_path / "frf.csv")
    assert m.meta["averages"] == str(out["averages"]) and "H1" in m.meta["estimator"]
    assert m.kind == "assembled" and list(m.position_mm) == [10, 0, 30]
    band = (m.freq_hz > 5) & (m.freq_hz < 300)
    assert np.median(np.abs(m.H[band] / _truth(m.freq_hz[band]) - 1)) < 0.01
    code, _, err = run(capsys, "frf", tmp_path / "run.csv", "-o", tmp_path / "x.csv", "--command-column", "nope",
                       "--response-column", "x_meas")
    assert code != 0 and "no column 'nope'" in err


def test_timeseries_errors(tmp_path):
    (tmp_path / "a.csv").write_text("#time,accel_x\n0.0,1\n0.1,zz\n")
    with pytest.raises(MeasurementError, match=r"a.csv:3: not a number"):
        read_timeseries(tmp_path / "a.csv")
    (tmp_path / "b.csv").write_text("1,2\n3,4\n")
    with pytest.raises(MeasurementError, match="header line"):
        read_timeseries(tmp_path / "b.csv")
    t = np.arange(100) / 100.0
    _write(tmp_path / "c.csv", "time,x", (t, np.sin(t)))
    _write(tmp_path / "d.csv", "time,accel_x", (t + 10, np.sin(t)))
    with pytest.raises(MeasurementError, match="do not overlap"):
        frf_from_time(read_timeseries(tmp_path / "c.csv"), "x", read_timeseries(tmp_path / "d.csv"), "accel_x")
