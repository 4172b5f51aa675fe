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
Both, cross-checked (:func:`noise_floors`, what validate/diagnose/fit use)
    A coherence column says nothing about how many averages it came from; without the
    ``averages`` header key one is assumed, and a file whose coherence came from 50 averages then
    claims a floor 7x too high.  So the data's own scatter is always computed too; when the two
    disagree by more than a factor ``1.5`` over the data set the disagreement is reported (with
    the number of averages that would reconcile them) and the data's estimate is used.  A floor
    given by the user (``--noise-floor``) overrides both.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .frf_file import FrfMeasurement

__all__ = ["noise_floor", "noise_from_coherence", "noise_from_data", "NoiseFloors", "noise_floors",
           "below_floor_note"]


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


@dataclass(frozen=True)
class NoiseFloors:
    """Noise floor of each measurement of a data set and where it came from.

    Attributes
    ----------
    values : ndarray, shape (N,)
        The floor used (relative complex residual of a perfect model), per measurement.
    source : str
        ``"coherence"``, ``"data"``, ``"coherence and data"`` or ``"given"`` (override).
    from_data, from_coherence : ndarray, shape (N,)
        Both estimates (NaN where unavailable).
    note : str
        Why the data's estimate replaced the coherence's (empty if it did not).
    """

    values: np.ndarray
    source: str
    from_data: np.ndarray
    from_coherence: np.ndarray
    note: str = ""
    #: where each measurement's floor came from (``coherence``, ``data`` or ``given``)
    sources: tuple = ()

    @property
    def mean(self) -> float:
        return float(np.mean(self.values)) if len(self.values) else float("nan")

    def to_dict(self) -> dict:
        def clean(a):
            return [float(v) if np.isfinite(v) else None for v in a]

        return {"mean": self.mean, "source": self.source, "note": self.note, "values": clean(self.values),
                "from_data": clean(self.from_data), "from_coherence": clean(self.from_coherence)}


def noise_floors(measurements, *, override: float | None = None, ratio_tol: float = 1.5,
                 predictions=None) -> NoiseFloors:
    """Noise floors of a data set: coherence and the data's scatter, cross-checked (module docstring).

    Parameters
    ----------
    measurements : sequence of FrfMeasurement
    override : float, optional
        Use this floor everywhere (``--noise-floor``).
    ratio_tol : float
        Largest ratio between the two estimates (set medians) still called agreement.
    predictions : sequence of ndarray, optional
        A model's FRFs for the measurements.  The scatter is then also taken on ``H / H_pred``,
        which is smooth where ``H`` itself is not (the resonances divide out), so a coarse
        frequency grid no longer inflates the estimate with curvature; the smaller estimate is
        used (curvature only ever adds).
    """
    ms = list(measurements)
    n = len(ms)
    dat = np.array([noise_from_data(m.freq_hz, m.H) for m in ms]) if n else np.zeros(0)
    if predictions is not None:
        for i, (m, Hp) in enumerate(zip(ms, predictions)):
            Hp = np.asarray(Hp, complex)
            if np.all(np.abs(Hp) > 0) and np.all(np.isfinite(Hp)):
                v = noise_from_data(m.freq_hz, m.H / Hp)
                if np.isfinite(v) and (not np.isfinite(dat[i]) or v < dat[i]):
                    dat[i] = v
    coh = np.full(n, np.nan)
    noiseless = np.zeros(n, bool)
    for i, m in enumerate(ms):
        if m.coherence is not None and np.any(m.coherence < 1.0):
            coh[i] = noise_from_coherence(m)
        elif m.coherence is not None:
            noiseless[i] = True
            coh[i] = 0.0
    if override is not None:
        if not (np.isfinite(override) and override > 0):
            raise ValueError(f"--noise-floor must be a positive number, got {override!r}")
        return NoiseFloors(np.full(n, float(override)), "given", dat, coh, "", ("given",) * n)
    fill = float(np.nanmedian(dat)) if np.any(np.isfinite(dat)) else 0.0
    dat_f = np.where(np.isfinite(dat), dat, fill)
    has_c = np.isfinite(coh) & ~noiseless
    both = has_c & np.isfinite(dat) & (dat > 0)
    note = ""
    values = np.where(np.isfinite(coh), coh, dat_f)
    if both.any():
        ratio = float(np.median(coh[both] / dat[both]))
        if not (1.0 / ratio_tol <= ratio <= ratio_tol):
            n_avg = sorted({_averages(ms[i]) for i in np.flatnonzero(both)})
            said = ("the header's averages = " + "/".join(f"{a:g}" for a in n_avg)
                    if any("averages" in ms[i].meta for i in np.flatnonzero(both)) else "one average assumed: "
                    "no 'averages' header key")
            fix = ""
            if ratio > 1:
                need = ratio**2 * n_avg[0]
                fix = (f"; the coherence matches the data if it came from about {need:.0f} averages (add "
                       f"'# averages: {need:.0f}' to the files' headers, or pass --noise-floor)")
            else:
                fix = ("; the data scatter more than the coherence says (coarse frequency grid, or a "
                       "coherence from the wrong averages count)")
            note = (f"noise floor: coherence gives {np.median(coh[both]):.4f} ({said}), the data's own scatter "
                    f"{np.median(dat[both]):.4f}: they disagree ({ratio:.1f}x), using the data's{fix}")
            values = np.where(has_c, dat_f, values)
    if noiseless.all() and n:
        src = "coherence"
    elif note or not has_c.any():
        src = "data"
    elif has_c.all():
        src = "coherence"
    else:
        src = "coherence and data"
    per = tuple("coherence" if np.isfinite(coh[i]) and not (note and has_c[i]) else "data" for i in range(n))
    return NoiseFloors(values, src, dat, coh, note, per)


def below_floor_note(mean_residual: float, floor: float, source: str, factor: float = 0.7) -> str:
    """A warning when a residual sits well below the noise floor (the floor is then overestimated)."""
    if not (np.isfinite(mean_residual) and np.isfinite(floor)) or floor <= 0 or mean_residual >= factor * floor:
        return ""
    return (f"the residual ({mean_residual:.4f}) sits {floor / max(mean_residual, 1e-12):.1f}x below the noise "
            f"floor ({floor:.4f} from {source}): the floor is overestimated (a coherence from more averages than "
            "the header says?) or the model was fitted to this very noise; set it with --noise-floor")
