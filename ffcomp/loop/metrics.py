"""Goodness-of-fit measures between a measured and a predicted FRF (pure numpy).

* :func:`r2` is the paper's Eq. 36, ``1 - sum (v - g)^2 / sum (v - mean v)^2``;
* :func:`r2_magnitude` applies it to ``|H|`` (linear by default, or in dB) and :func:`r2_phase` to
  the unwrapped phase in degrees;
* :func:`complex_residual` is ``||H_pred - H_meas|| / ||H_meas||``, the error Eq. 36 hides: a
  dominant lightly damped peak keeps the magnitude R^2 near one while other modes are wrong.
"""

from __future__ import annotations

import numpy as np

__all__ = ["r2", "r2_magnitude", "r2_phase", "complex_residual", "band_residuals"]


def r2(v, g, w=None) -> float:
    """Coefficient of determination of prediction ``g`` for data ``v`` (Eq. 36), optional weights."""
    v = np.asarray(v, float)
    g = np.asarray(g, float)
    w = np.ones_like(v) if w is None else np.asarray(w, float)
    vbar = np.sum(w * v) / np.sum(w)
    den = np.sum(w * (v - vbar) ** 2)
    return float(1.0 - np.sum(w * (v - g) ** 2) / den) if den > 0 else float("nan")


def r2_magnitude(H_meas, H_pred, *, db: bool = False, w=None) -> float:
    """Eq. 36 on the magnitude, linear ratio (default) or dB."""
    a, b = np.abs(H_meas), np.abs(H_pred)
    if db:
        a, b = 20 * np.log10(a), 20 * np.log10(b)
    return r2(a, b, w)


def _phase_deg(H):
    return np.rad2deg(np.unwrap(np.angle(H)))


def r2_phase(H_meas, H_pred, w=None) -> float:
    """Eq. 36 on the unwrapped phase in degrees (both unwrapped from their first sample, aligned to
    the same branch at the first frequency)."""
    pm, pp = _phase_deg(H_meas), _phase_deg(H_pred)
    pp = pp + 360.0 * np.round((pm[0] - pp[0]) / 360.0)
    return r2(pm, pp, w)


def complex_residual(H_meas, H_pred, w=None) -> float:
    """Normalised complex residual ``||H_pred - H_meas|| / ||H_meas||`` (optionally weighted)."""
    H_meas = np.asarray(H_meas)
    w = np.ones(H_meas.shape, float) if w is None else np.asarray(w, float)
    num = np.sum(w * np.abs(np.asarray(H_pred) - H_meas) ** 2)
    den = np.sum(w * np.abs(H_meas) ** 2)
    return float(np.sqrt(num / den))


def band_residuals(freq_hz, H_meas, H_pred, edges_hz) -> np.ndarray:
    """:func:`complex_residual` within each band ``[edges[i], edges[i+1])``; NaN for empty bands."""
    f = np.asarray(freq_hz)
    out = np.full(len(edges_hz) - 1, np.nan)
    for i in range(len(edges_hz) - 1):
        sel = (f >= edges_hz[i]) & (f < edges_hz[i + 1])
        if sel.any():
            out[i] = complex_residual(np.asarray(H_meas)[sel], np.asarray(H_pred)[sel])
    return out
