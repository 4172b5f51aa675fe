"""What the base model's residual looks like: generic FRF signatures, in numbers and in words.

Each feature is computed from the measured and predicted FRFs alone (no candidate effect) and
returned as an :class:`Evidence` item with a key that effects list in ``evidence_keys``:

``delay``       phase of ``H_meas / H_pred`` falling linearly with frequency, alike on every axis;
``lag``         magnitude ratio falling at the top of the band, alike on every axis;
``height``      residual growing with the carriages' distance from the identification height;
``lateral``     residual growing with the difference between the carriage heights (off-centre);
``common_vs_lateral``  vertical (common-mode) responses fit, lateral ones do not;
``lateral_gain``  low-frequency gain of lateral responses off one while vertical stays one;
``peak_shift``  the measured resonance is shifted by the same fraction at every pose;
``height_shift``  the resonance shift changes sign/size with carriage height;
``identification``  the identification sweeps at the centre deviate too;
``fixed_band``  one frequency band fails at every pose and in the carriage sweep (:func:`fixed_band`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import spearmanr

from ..kinematics import inverse

__all__ = ["Evidence", "Features", "features", "evidence", "fixed_band"]


@dataclass(frozen=True)
class Evidence:
    """One observation: ``key`` (see module docstring), ``strength`` 0..1, ``text``."""

    key: str
    strength: float
    text: str

    def to_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass(frozen=True)
class Features:
    """Per-measurement numbers behind the evidence (arrays of shape (N,))."""

    residual: np.ndarray
    noise: np.ndarray
    dq_ref_mm: np.ndarray  # mean |q - q_ref|
    q_mean_mm: np.ndarray  # mean (q - q_ref), signed
    spread_mm: np.ndarray  # max q - min q
    tau_ms: np.ndarray  # phase-slope delay of H_meas/H_pred
    tau_r2: np.ndarray  # linear-fit R^2 of that phase
    top_gain: np.ndarray  # |H_meas/H_pred| at the top of the band
    low_gain: np.ndarray  # |H_meas/H_pred| at the bottom of the band
    peak_shift: np.ndarray  # f_peak,meas / f_peak,pred - 1 (NaN without a clear peak)
    axis: tuple  # "x->x", ...
    ident: np.ndarray  # bool: identification sweep


def _peak(f, H):
    a = np.abs(H)
    if len(a) < 5:
        return np.nan
    i = int(np.argmax(a[1:-1])) + 1
    if a[i] < 1.15 * max(a[0], a[-1]) and a[i] < 1.15 * np.median(a):
        return np.nan
    y0, y1, y2 = np.log(a[i - 1:i + 2])
    x = np.log(f[i - 1:i + 2])
    d = y0 - 2 * y1 + y2
    if d == 0:
        return float(f[i])
    t = 0.5 * (y0 - y2) / d  # vertex offset in samples (log grid)
    return float(np.exp(x[1] + t * (x[2] - x[0]) / 2))


def _tau(f, Hm, Hp, w):
    sel = (np.abs(Hp) > 0.1 * np.max(np.abs(Hp))) & (w > 0.2)
    if sel.sum() < 8:
        return np.nan, 0.0
    om = 2 * np.pi * f[sel]
    ph = np.unwrap(np.angle(Hm[sel] / Hp[sel]))
    ww = w[sel]
    A = np.column_stack([np.ones_like(om), om]) * np.sqrt(ww)[:, None]
    coef, *_ = np.linalg.lstsq(A, ph * np.sqrt(ww), rcond=None)
    fit = coef[0] + coef[1] * om
    ss = np.sum(ww * (ph - np.average(ph, weights=ww)) ** 2)
    r2 = 1 - np.sum(ww * (ph - fit) ** 2) / ss if ss > 0 else 0.0
    return float(-coef[1] * 1e3), float(max(r2, 0.0))


def features(model, measurements, predictions, residual, noise) -> Features:
    """Compute :class:`Features` for measurements with base-model ``predictions``."""
    ident = np.array([m.kind == "carriage" or (m.input == "z" and m.output.startswith("q")
                                                and np.hypot(*m.position_mm[:2]) < 1.0) for m in measurements])
    z_id = [m.position_mm[2] for m, i in zip(measurements, ident) if i]
    z_ref = float(np.median(z_id)) if z_id else float(np.clip(30.0, model.geometry.z_min_m * 1e3,
                                                               model.geometry.z_max_m * 1e3))
    q_ref = inverse(model.geometry, np.array([0.0, 0.0, z_ref * 1e-3])) * 1e3
    pos = np.array([m.position_mm for m in measurements], float)
    q = inverse(model.geometry, pos * 1e-3) * 1e3
    cp = model.carriage
    d0, d1, d2 = float(np.mean(cp.d0)), float(np.mean(cp.d1)), float(np.mean(cp.d2))
    tau, r2, top, low, shift = [], [], [], [], []
    for m, Hp in zip(measurements, predictions):
        t, r = _tau(m.freq_hz, m.H, Hp, m.weights)
        tau.append(t)
        r2.append(r)
        ratio = np.abs(m.H / Hp)
        n = max(3, len(ratio) // 10)
        top.append(float(np.median(ratio[-n:])))
        low.append(float(np.median(ratio[:n])))
        if m.input == m.output or m.kind == "carriage" or m.output.startswith("q"):
            s_ = 2j * np.pi * m.freq_hz
            drive = (d1 * s_ + d0) / (s_**2 + d2 * s_ + d0)  # divide out the drive: the mechanical peak
            fm, fp = _peak(m.freq_hz, m.H / drive), _peak(m.freq_hz, Hp / drive)
            shift.append(fm / fp - 1 if np.isfinite(fm) and np.isfinite(fp) else np.nan)
        else:
            shift.append(np.nan)
    return Features(np.asarray(residual), np.asarray(noise), np.mean(np.abs(q - q_ref), 1), np.mean(q - q_ref, 1),
                    np.ptp(q, 1), np.array(tau), np.array(r2), np.array(top), np.array(low), np.array(shift),
                    tuple(f"{m.input}->{m.output}" for m in measurements), ident)


def _rank_corr(a, b) -> float:
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 5 or np.ptp(a[ok]) == 0 or np.ptp(b[ok]) == 0:
        return 0.0
    return float(spearmanr(a[ok], b[ok]).statistic)


def evidence(ft: Features) -> list[Evidence]:
    """Evidence items, strongest first (only those with something to say)."""
    out: list[Evidence] = []
    nu = float(np.sqrt(np.mean(ft.noise**2)))
    excess = ft.residual**2 - ft.noise**2
    if np.mean(excess) <= 0.1 * nu**2:
        return out
    # delay: linear phase, consistent across measurements
    ok = np.isfinite(ft.tau_ms)
    if ok.sum() >= 3:
        med, r2 = float(np.median(ft.tau_ms[ok])), float(np.median(ft.tau_r2[ok]))
        iqr = float(np.subtract(*np.percentile(ft.tau_ms[ok], [75, 25])))
        if abs(med) > 0.02 and r2 > 0.5 and iqr < 0.5 * abs(med):
            out.append(Evidence("delay", min(1.0, r2), (
                f"phase lag grows linearly with frequency on {ok.sum()} measurements alike (slope = {med:.3f} ms, "
                f"spread {iqr:.3f} ms, linear-fit R^2 {r2:.2f}): a {'delay' if med > 0 else 'lead'}")))
    # lag: magnitude ratio at the top of the band, same everywhere
    tg = float(np.median(ft.top_gain))
    if abs(tg - 1) > max(3 * nu, 0.03) and np.std(ft.top_gain) < 0.5 * abs(tg - 1):
        out.append(Evidence("lag", min(1.0, abs(tg - 1) / 0.1), (
            f"magnitude at the top of the band is {tg:.3f}x the prediction on every axis and pose: "
            f"{'a first-order lag' if tg < 1 else 'less drive filtering than modelled'}")))
    # height
    c = _rank_corr(ft.dq_ref_mm, excess)
    if c > 0.5 and np.ptp(ft.dq_ref_mm) > 5:
        near = ft.dq_ref_mm <= np.median(ft.dq_ref_mm)
        out.append(Evidence("height", c, (
            f"error grows with the carriages' distance from the identification height (rank correlation {c:.2f}; "
            f"mean residual {np.mean(ft.residual[near]):.3f} near, {np.mean(ft.residual[~near]):.3f} far)")))
    cs = _rank_corr(ft.q_mean_mm, ft.peak_shift)
    if abs(cs) > 0.6:
        out.append(Evidence("height_shift", abs(cs), (
            f"the measured resonance moves {'up' if cs > 0 else 'down'} relative to the prediction as the carriages "
            f"climb (rank correlation {cs:.2f} between peak shift and carriage height)")))
    # lateral
    c = _rank_corr(ft.spread_mm, excess)
    if c > 0.5:
        out.append(Evidence("lateral", c, (
            f"error grows with the difference in carriage heights, i.e. away from the bed centre "
            f"(rank correlation {c:.2f})")))
    # common mode vs lateral
    zsel = np.array([a in ("z->z",) for a in ft.axis])
    xsel = np.array([a in ("x->x", "y->y") for a in ft.axis])
    if zsel.any() and xsel.any():
        ez, ex = float(np.mean(excess[zsel])), float(np.mean(excess[xsel]))
        if ex > 0.5 * nu**2 and ez < 0.25 * ex:
            out.append(Evidence("common_vs_lateral", min(1.0, 1 - ez / ex), (
                f"vertical responses (z->z: all carriages in phase) fit better than lateral ones (mean residual "
                f"{np.mean(ft.residual[zsel]):.3f} vs {np.mean(ft.residual[xsel]):.3f} for x->x, y->y): "
                "what is missing acts on the differential (lateral) modes")))
        lx, lz = float(np.median(ft.low_gain[xsel])), float(np.median(ft.low_gain[zsel]))
        if abs(lx - 1) > max(3 * nu / np.sqrt(10), 0.01) and abs(lz - 1) < 0.5 * abs(lx - 1):
            out.append(Evidence("lateral_gain", min(1.0, abs(lx - 1) / 0.05), (
                f"low-frequency gain of lateral moves is {lx:.3f}x the prediction, vertical {lz:.3f}x: the "
                "carriages pull on each other (a stiffness between them)")))
    # uniform peak shift
    ok = np.isfinite(ft.peak_shift) & ~ft.ident & (np.abs(np.nan_to_num(ft.peak_shift)) > 0.005)
    if ok.sum() >= 3:
        s = ft.peak_shift[ok]
        med = float(np.median(s))
        frac = float(np.mean(np.sign(s) == np.sign(med)))
        if abs(med) > 0.01 and frac > 0.85:
            out.append(Evidence("peak_shift", min(1.0, abs(med) / 0.03), (
                f"the measured mechanical resonance peaks are {'above' if med > 0 else 'below'} the prediction in "
                f"{frac:.0%} of the sweeps where they move (median {med:+.1%})")))

    if ft.ident.any():
        ri = float(np.mean(ft.residual[ft.ident]))
        ni = float(np.mean(ft.noise[ft.ident]))
        if ri > 1.5 * ni + 0.005:
            out.append(Evidence("identification", 0.5, (
                f"the identification sweeps at the centre deviate too (residual {ri:.3f}, noise {ni:.3f}): the "
                "missing effect acts at the identification pose (a delay, a coupling between carriages), or "
                "the base dynamics are off (re-run `ffcomp identify`)")))
        else:
            out.append(Evidence("identification", 0.3, (
                f"the identification sweeps at the centre still fit (residual {ri:.3f}, noise {ni:.3f}): "
                "the model is right where it was identified and wrong elsewhere")))
    out.sort(key=lambda e: -e.strength)
    return out


def fixed_band(measurements, predictions, noise, *, per_octave: float = 3.0, min_share: float = 0.8,
               min_excess: float = 5.0, min_contrast: float = 1.5) -> Evidence | None:
    """A misfit concentrated in one frequency band, the same at every pose and in the carriage sweep.

    Each sweep's relative complex residual is taken in 1/``per_octave``-octave bands on a common
    grid.  The signature is found when the worst band of at least ``min_share`` of the sweeps is
    one band (or its neighbour), not one of the two bands at either end of the grid (a misfit
    growing towards an end is a trend: a delay, a lag), every carriage sweep among them, its
    residual is ``min_excess`` times the noise and ``min_contrast`` times the residual outside it
    (medians).  No effect of
    the library does that: they all move with pose or act on the effector.  Returns None if absent.
    """
    from .metrics import complex_residual

    ms = list(measurements)
    if len(ms) < 3:
        return None
    f_lo = min(float(m.freq_hz[0]) for m in ms)
    f_hi = max(float(m.freq_hz[-1]) for m in ms)
    k0, k1 = int(np.floor(np.log2(f_lo) * per_octave)), int(np.ceil(np.log2(f_hi) * per_octave))
    edges = 2.0 ** (np.arange(k0, k1 + 1) / per_octave)
    nb = len(edges) - 1
    bands = np.full((len(ms), nb), np.nan)
    rest = np.full((len(ms), nb), np.nan)
    for i, (m, Hp) in enumerate(zip(ms, predictions)):
        for j in range(nb):
            sel = (m.freq_hz >= edges[j]) & (m.freq_hz < edges[j + 1])
            if sel.sum() < 3:
                continue
            bands[i, j] = complex_residual(m.H[sel], Hp[sel], m.weights[sel])
            if (~sel).sum() >= 3:
                rest[i, j] = complex_residual(m.H[~sel], Hp[~sel], m.weights[~sel])
    ok = np.isfinite(bands).any(axis=1)
    worst = np.where(ok, np.argmax(np.where(np.isfinite(bands), bands, -np.inf), axis=1), -1)
    vals, counts = np.unique(worst[worst >= 0], return_counts=True)
    if not len(vals):
        return None
    j = int(vals[np.argmax(counts)])
    if j < 2 or j > nb - 3:
        return None  # at an end of the band: a trend (a delay, a lag), not a resonance
    hit = np.abs(worst - j) <= 1
    share = float(hit.mean())
    carriage = np.array([m.kind == "carriage" for m in ms])
    nu = np.maximum(np.asarray(noise, float), 1e-12)
    peak = bands[np.arange(len(ms)), np.clip(worst, 0, nb - 1)]
    exc = float(np.median((peak / nu)[hit]))
    con = float(np.nanmedian((peak / rest[np.arange(len(ms)), np.clip(worst, 0, nb - 1)])[hit]))
    if (share < min_share or exc < min_excess or con < min_contrast
            or (carriage.any() and not hit[carriage].all())):
        return None
    poses = {tuple(np.round(np.asarray(m.position_mm, float), 0)) for m in ms}
    hit_poses = {tuple(np.round(np.asarray(m.position_mm, float), 0)) for m, h in zip(ms, hit) if h}
    lo, hi = float(edges[j]), float(edges[j + 1])
    car = (" and in the carriage sweep (effector detached) too" if carriage.any() else "")
    text = (f"a misfit at a fixed frequency, {lo:.0f}-{hi:.0f} Hz, is the worst band of {int(hit.sum())} of {len(ms)} "
            f"sweeps, at {len(hit_poses)} of {len(poses)} poses{car} ({exc:.0f}x the noise there, {con:.1f}x the "
            "residual elsewhere): a resonance that does not move with the pose, which no effect of the library "
            "produces (a compliant motor mount, a frame or pulley mode); describe it as an effect plug-in "
            "(docs/effects_example_motor_mount.py) and fit it with `ffcomp fit --plugin FILE --add NAME`")
    return Evidence("fixed_band", min(1.0, share), text)
