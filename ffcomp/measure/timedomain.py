"""Time-domain data to an FRF: H1 estimate and coherence from a known command and a measured response.

Inputs are CSV time series with a header naming the columns; ``#`` comment lines are skipped,
except that a commented header is accepted, as in Klipper's raw accelerometer files
(``ACCELEROMETER_MEASURE``)::

    #time,accel_x,accel_y,accel_z
    1234.500312,-12.3,45.6,9806.1          (s, mm/s^2)

The time column is ``time``/``t``/``time_s``/``t_s`` (seconds) or ``time_ms``.  The command is the
commanded position (mm) of the swept coordinate, on the same clock (e.g. logged by the sweep
script); the response is a position (mm) or an acceleration (mm/s^2).

Processing (:func:`frf_from_time`):

1. both signals are linearly interpolated onto one uniform grid over their common time span, at
   the response's mean sample rate (or ``fs_hz``);
2. Welch averaging, Hann window, 50 % overlap, segments of ``fs / resolution_hz`` samples rounded
   to a power of two (at most a quarter of the record, so at least 7 averages):
   ``H1 = P_uy / P_uu`` (:func:`scipy.signal.csd`, :func:`scipy.signal.welch`) and
   ``coherence = |P_uy|^2 / (P_uu P_yy)``;
3. an acceleration response gives an accelerance (1/s^2); the displacement FRF is
   ``H_disp = H_acc / (j w)^2 = -H_acc / w^2``.  Double integration amplifies low-frequency noise
   and offsets, so the result is band-limited: by default from ``max(5 Hz, 3 df)`` (``df`` the
   frequency resolution) to ``0.4 fs``; for a position response from ``3 df``.

The result carries extra FRF header keys (compatible with FRF_FORMAT: readers keep unknown keys):
``averages`` (number of Welch segments, used for the coherence-based noise floor), ``estimator``,
``fs_hz``, ``nperseg``, ``quantity``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import signal

from ..errors import MeasurementError
from .frf_file import FrfMeasurement

__all__ = ["TimeSeries", "read_timeseries", "h1_estimate", "FrfEstimate", "frf_from_time"]

_TIME = {"time": 1.0, "t": 1.0, "time_s": 1.0, "t_s": 1.0, "time_ms": 1e-3, "t_ms": 1e-3}


@dataclass(frozen=True)
class TimeSeries:
    """Columns of a CSV time series: ``t_s`` (N,) seconds and ``columns`` name -> (N,) values."""

    t_s: np.ndarray
    columns: dict = field(default_factory=dict)
    path: str = ""

    def column(self, name: str) -> np.ndarray:
        """Values of column ``name``; :class:`MeasurementError` listing the columns if missing."""
        if name not in self.columns:
            raise MeasurementError(self.path, None, f"no column {name!r} (columns: {', '.join(self.columns)})")
        return self.columns[name]


def _split(text: str) -> list[str]:
    for sep in (",", ";", "\t"):
        if sep in text:
            return [p.strip() for p in text.split(sep)]
    return text.split()


def read_timeseries(path) -> TimeSeries:
    """Read a CSV time series (Klipper raw accelerometer CSV included); errors name file and line."""
    path = str(path)
    try:
        with open(path, encoding="utf-8") as f:
            lines = f.read().splitlines()
    except (OSError, UnicodeDecodeError) as e:
        raise MeasurementError(path, None, f"cannot read: {e}") from e
    names, rows, first = None, [], 0
    for n, raw in enumerate(lines, 1):
        t = raw.strip()
        if not t:
            continue
        if t.startswith("#"):
            body = _split(t[1:].strip())
            if names is None and body and body[0].lower() in _TIME:
                names, first = body, n
            continue
        parts = _split(t)
        if names is None:
            if parts and parts[0].lower() in _TIME:
                names, first = parts, n
                continue
            raise MeasurementError(path, n, "expected a header line naming the columns (time, ...)", raw)
        if len(parts) != len(names):
            raise MeasurementError(path, n, f"expected {len(names)} values, got {len(parts)}", raw)
        try:
            rows.append([float(p) for p in parts])
        except ValueError:
            raise MeasurementError(path, n, "not a number", raw) from None
    if names is None or len(rows) < 16:
        raise MeasurementError(path, first or None, "need a header and at least 16 samples")
    data = np.array(rows)
    scale = _TIME[names[0].lower()]
    t = data[:, 0] * scale
    order = np.argsort(t, kind="stable")
    t, data = t[order], data[order]
    keep = np.concatenate([[True], np.diff(t) > 0])
    return TimeSeries(t[keep], {nm: data[keep, i] for i, nm in enumerate(names[1:], 1)}, path)


def h1_estimate(u, y, fs_hz: float, nperseg: int):
    """H1 estimate ``P_uy / P_uu`` and coherence.

    Returns
    -------
    freq_hz, H, coherence : ndarray, shape (nperseg // 2 + 1,)
    averages : int
        Number of Welch segments.
    """
    kw = dict(fs=fs_hz, window="hann", nperseg=nperseg, noverlap=nperseg // 2, detrend="constant")
    f, Puu = signal.welch(u, **kw)
    _, Pyy = signal.welch(y, **kw)
    _, Puy = signal.csd(u, y, **kw)
    with np.errstate(divide="ignore", invalid="ignore"):
        H = Puy / Puu
        coh = np.clip(np.abs(Puy) ** 2 / (Puu * Pyy), 0.0, 1.0)
    n_avg = 1 + (len(u) - nperseg) // (nperseg // 2)
    return f, H, np.nan_to_num(coh), int(n_avg)


@dataclass(frozen=True)
class FrfEstimate:
    """An estimated FRF with its processing record (``quantity``: ``position`` or ``acceleration``)."""

    freq_hz: np.ndarray
    H: np.ndarray
    coherence: np.ndarray
    fs_hz: float
    nperseg: int
    averages: int
    quantity: str

    def to_measurement(self, kind: str, position_mm, input_: str, output: str, source: str = "") -> FrfMeasurement:
        """An :class:`FrfMeasurement` with the processing record as extra header keys."""
        meta = {"averages": str(self.averages), "estimator": "H1 (Welch, Hann, 50% overlap)",
                "fs_hz": f"{self.fs_hz:.6g}", "nperseg": str(self.nperseg),
                "quantity": ("displacement from acceleration / (j w)^2" if self.quantity == "acceleration"
                             else "displacement")}
        return FrfMeasurement(self.freq_hz, self.H, self.coherence, kind, np.asarray(position_mm, float), input_,
                              output, source, None, meta)

    def to_dict(self) -> dict:
        return {"freq_hz": self.freq_hz.tolist(), "real": self.H.real.tolist(), "imag": self.H.imag.tolist(),
                "coherence": self.coherence.tolist(), "fs_hz": self.fs_hz, "nperseg": self.nperseg,
                "averages": self.averages, "quantity": self.quantity}


def frf_from_time(command: TimeSeries, command_column: str, response: TimeSeries, response_column: str, *,
                  quantity: str = "auto", fs_hz: float | None = None, resolution_hz: float = 1.0,
                  f_lo_hz: float | None = None, f_hi_hz: float | None = None, scale: float = 1.0,
                  min_coherence: float = 0.0) -> FrfEstimate:
    """Position-to-position FRF from a command (mm) and a response (mm or mm/s^2).

    Parameters
    ----------
    quantity : {"auto", "position", "acceleration"}
        ``auto``: acceleration if the response column name starts with ``accel``.
    fs_hz : float, optional
        Resampling rate, Hz (default: the response's median rate).
    resolution_hz : float
        Target frequency resolution, Hz (sets the Welch segment length).
    f_lo_hz, f_hi_hz : float, optional
        Band kept in the result (defaults in the module docstring).
    scale : float
        Factor applied to the response (sign or unit fix: e.g. -1 for a flipped sensor axis).
    min_coherence : float
        Drop frequencies whose coherence is below this.
    """
    if quantity == "auto":
        quantity = "acceleration" if response_column.lower().startswith("acc") else "position"
    if quantity not in ("position", "acceleration"):
        raise ValueError(f"quantity must be auto, position or acceleration, got {quantity!r}")
    u_raw, y_raw = command.column(command_column), response.column(response_column) * scale
    t0 = max(command.t_s[0], response.t_s[0])
    t1 = min(command.t_s[-1], response.t_s[-1])
    if not t1 > t0:
        raise MeasurementError(response.path, None, f"command ({command.path}) and response do not overlap in time "
                               f"(command {command.t_s[0]:.3f}..{command.t_s[-1]:.3f} s, response "
                               f"{response.t_s[0]:.3f}..{response.t_s[-1]:.3f} s): same clock?")
    # mean rate over the record: robust to time stamps rounded to the microsecond (Klipper's CSV)
    fs = float(fs_hz or (len(response.t_s) - 1) / (response.t_s[-1] - response.t_s[0]))
    t = t0 + np.arange(int((t1 - t0) * fs)) / fs
    if len(t) < 64:
        raise MeasurementError(response.path, None, f"only {len(t)} common samples at {fs:.1f} Hz")
    u = np.interp(t, command.t_s, u_raw)
    y = np.interp(t, response.t_s, y_raw)
    nper = 2 ** int(round(math.log2(max(fs / resolution_hz, 16))))
    nper = int(min(nper, 2 ** int(math.log2(len(t) // 4))))
    f, H, coh, n_avg = h1_estimate(u, y, fs, nper)
    df = fs / nper
    lo = f_lo_hz if f_lo_hz is not None else (max(5.0, 3 * df) if quantity == "acceleration" else 3 * df)
    hi = f_hi_hz if f_hi_hz is not None else 0.4 * fs
    sel = (f >= lo) & (f <= hi) & (f > 0) & np.isfinite(H) & (coh >= min_coherence)
    if sel.sum() < 2:
        raise MeasurementError(response.path, None, f"no frequencies left in {lo:g}..{hi:g} Hz "
                               f"(resolution {df:.3g} Hz, coherence >= {min_coherence})")
    f, H, coh = f[sel], H[sel], coh[sel]
    if quantity == "acceleration":
        H = H / (2j * np.pi * f) ** 2
    return FrfEstimate(f, H, coh, fs, nper, n_avg, quantity)
