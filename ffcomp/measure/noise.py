"""Noise floor of a measured FRF: the normalised complex residual a perfect model would leave.

From coherence (preferred)
    An H1 estimate from ``n`` averages has a relative complex error of variance
    ``(1 - g^2) / (g^2 n)`` at each frequency (Bendat & Piersol); the header key ``averages: n``
    gives ``n`` (``ffcomp frf`` writes it), else ``n = 1``, which is also what the virtual
    measurements' coherence ``1 / (1 + rel^2)`` means (relative noise ``rel``).  The floor is the
    ``|H|^2``-weighted RMS of that error, weighted by coherence as the residual is.
From the data (no coherence column)
    The deviation of each point from the cubic through its four neighbours (in log frequency) is
    noise plus the FRF's own curvature; on a grid that resolves the resonances the median of its
    normalised square, divided by ``ln 2`` (median of an exponential distribution), estimates the
    relative noise variance.  Curvature makes it an upper bound on coarse grids.
"""

from __future__ import annotations

import numpy as np

from .frf_file import FrfMeasurement

__all__ = ["noise_floor", "noise_from_coherence", "noise_from_data"]


def _averages(meas: FrfMeasurement) -> float:
    try:
        n = float(str(meas.meta.get("averages", "1")).split()[0])
    except ValueError:
        return 1.0
    return n if np.isfinite(n) and n >= 1 else 1.0


def noise_from_coherence(meas: FrfMeasurement) -> float:
    """Relative complex noise from the coherence column and ``averages`` header (dimensionless)."""
    g2 = np.clip(meas.coherence, 1e-6, 1.0)
    eps2 = (1.0 - g2) / g2 / _averages(meas)
    w = meas.weights * np.abs(meas.H) ** 2
    return float(np.sqrt(np.sum(w * eps2) / np.sum(w)))


def noise_from_data(freq_hz, H) -> float:
    """Relative complex noise from the scatter about neighbour interpolation (dimensionless).

    Each point is predicted by the cubic through its two neighbours on either side (Lagrange, in
    log frequency); the prediction error is ``noise * sqrt(1 + sum w^2)`` plus the (fourth-order)
    curvature of the FRF.  Returns NaN with fewer than 7 points.
    """
    x = np.log(np.asarray(freq_hz, float))
    H = np.asarray(H, complex)
    if len(x) < 7:
        return float("nan")
    k = np.arange(2, len(x) - 2)
    nb = np.stack([k - 2, k - 1, k + 1, k + 2], 1)  # (K, 4)
    xn = x[nb]
    w = np.ones_like(xn)
    for j in range(4):
        for m in range(4):
            if m != j:
                w[:, j] *= (x[k] - xn[:, m]) / (xn[:, j] - xn[:, m])
    r = H[k] - np.sum(w * H[nb], axis=1)
    var = np.abs(r) ** 2 / (np.abs(H[k]) ** 2 * (1.0 + np.sum(w**2, axis=1)))
    return float(np.sqrt(np.median(var) / np.log(2.0)))


def noise_floor(meas: FrfMeasurement) -> tuple[float, str]:
    """``(floor, source)``: source is ``"coherence"`` or ``"data"``."""
    if meas.coherence is not None and np.any(meas.coherence < 1.0):
        return noise_from_coherence(meas), "coherence"
    if meas.coherence is not None:  # coherence all exactly 1: noiseless (a model prediction)
        return 0.0, "coherence"
    return noise_from_data(meas.freq_hz, meas.H), "data"
