"""The paper's two-sweep identification (Section IV-A).

1. Each sweep (carriage alone, effector detached; assembled printer, vertical sweep at the bed
   centre) is fitted with the 4th-order form of Eq. 22,
   ``G(s) = w^2 (1 + tau s) / (s^2 + 2 zeta w s + w^2) * (d1 s + d0) / (s^2 + d2 s + d0)``,
   ``tau = c/k``.  Starting values come from a Sanathanan-Koerner linear least-squares fit of a
   rational function with unit DC gain; the electrical pole pair is the one both sweeps share.
2. A joint coherence-weighted complex least-squares fit refines both sweeps together: the drive
   (``d0, d1, d2``) and ``tau = c/k`` are common to both, each sweep has its own ``w, zeta``.
3. The physical parameters follow from Eqs. 26-34 with the measured ``m_n``, ``m_f``; Eq. 33 with
   its sign fixed: ``m = m_nt w'^2 / (3 (w^2 - w'^2))``.

The joint fit is parametrised so that every result is physical: ``c, b, b_nt >= 0`` and ``m > 0``
(``w' < w``) are bounds of the fit (trust-region reflective), not checks after it.  When the sweeps
ask for more (a mode the model does not have), the best physical profile is still returned, with
:attr:`Identification.warnings` saying which sweep fails, in which band, by how much against its
noise floor, and which bounds were hit.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import least_squares

from ..errors import MeasurementError, SolverError
from ..measure.frf_file import FrfMeasurement
from .metrics import complex_residual, r2_magnitude, r2_phase

__all__ = ["Eq22Fit", "Identification", "fit_eq22", "sk_fit", "identify", "eq22_response", "quality_warnings",
           "worst_band"]


def eq22_response(s, wn, zeta, tau, d0, d1, d2):
    """Eq. 22 with the mechanical part written through ``w_n, zeta, tau = c/k`` (unit DC gain)."""
    mech = wn**2 * (1.0 + tau * s) / (s**2 + 2.0 * zeta * wn * s + wn**2)
    elec = (d1 * s + d0) / (s**2 + d2 * s + d0)
    return mech * elec


@dataclass(frozen=True)
class Eq22Fit:
    """A fitted Eq. 22 and its quality against the data it was fitted to.

    ``wn`` (rad/s), ``zeta``, ``tau`` (= c/k, s), ``d0`` (1/s^2), ``d1`` (1/s), ``d2`` (1/s);
    ``residual`` is the normalised complex residual, ``r2_mag`` / ``r2_phase`` the paper's Eq. 36.
    """

    wn: float
    zeta: float
    tau: float
    d0: float
    d1: float
    d2: float
    residual: float
    r2_mag: float
    r2_mag_db: float
    r2_phase: float
    n_points: int

    def response(self, freq_hz) -> np.ndarray:
        s = 2j * np.pi * np.asarray(freq_hz, float)
        return eq22_response(s, self.wn, self.zeta, self.tau, self.d0, self.d1, self.d2)

    def to_dict(self) -> dict:
        return {k: float(v) if not isinstance(v, int) else v for k, v in self.__dict__.items()}


@dataclass(frozen=True)
class Identification:
    """Result of :func:`identify`: the physical parameters and both fits."""

    m: float
    c: float
    b: float
    k: float
    b_nt: float
    d0: float
    d1: float
    d2: float
    m_n: float
    m_f: float
    carriage_fit: Eq22Fit
    assembled_fit: Eq22Fit
    #: physical bounds the fit ended on, and warnings on its quality (see :func:`quality_warnings`)
    at_bound: tuple = ()
    warnings: tuple = ()

    @property
    def m_nt(self) -> float:
        return self.m_n + 1.5 * self.m_f

    def to_dict(self) -> dict:
        d = {k: getattr(self, k) for k in ("m", "c", "b", "k", "b_nt", "d0", "d1", "d2", "m_n", "m_f")}
        d["m_nt"] = self.m_nt
        d["carriage_fit"] = self.carriage_fit.to_dict()
        d["assembled_fit"] = self.assembled_fit.to_dict()
        d["at_bound"] = list(self.at_bound)
        d["warnings"] = list(self.warnings)
        return d

    def apply_to(self, profile):
        """A copy of ``profile`` with these dynamics (same for all three towers)."""
        dyn = replace(
            profile.dynamics,
            **{k: (float(getattr(self, k)),) * 3 for k in ("m", "c", "b", "k", "d0", "d1", "d2")},
            m_n=float(self.m_n), m_f=float(self.m_f), b_nt=float(self.b_nt),
        )
        return replace(profile, dynamics=dyn, effects=(), source=None)


# --------------------------------------------------------------------------- linear start

def sk_fit(freq_hz, H, w=None, *, n_iter: int = 12):
    """Sanathanan-Koerner fit of ``(b2 s^2 + b1 s + a0) / (s^4 + a3 s^3 + a2 s^2 + a1 s + a0)``.

    The numerator's constant equals the denominator's (unit DC gain).  Frequencies are scaled by
    their geometric mean for conditioning.  Returns ``(num, den)`` polynomial coefficients in ``s``
    (highest power first, rad/s).
    """
    f = np.asarray(freq_hz, float)
    H = np.asarray(H, complex)
    w = np.ones_like(f) if w is None else np.asarray(w, float)
    w0 = 2 * np.pi * np.exp(np.mean(np.log(f)))
    s = 2j * np.pi * f / w0
    wt = np.sqrt(w)
    Aprev = np.ones_like(s)
    for _ in range(n_iter):
        # unknowns: a3, a2, a1, a0, b2, b1
        cols = np.stack([H * s**3, H * s**2, H * s, H - 1.0, -s**2, -s], axis=1)
        rhs = -H * s**4
        scale = wt / np.abs(Aprev)
        Am = cols * scale[:, None]
        bm = rhs * scale
        Ar = np.vstack([Am.real, Am.imag])
        br = np.concatenate([bm.real, bm.imag])
        x, *_ = np.linalg.lstsq(Ar, br, rcond=None)
        a3, a2, a1, a0, b2, b1 = x
        Aprev = s**4 + a3 * s**3 + a2 * s**2 + a1 * s + a0
    # unscale: s_true = w0 * s
    den = np.array([1.0, a3 * w0, a2 * w0**2, a1 * w0**3, a0 * w0**4])
    num = np.array([b2 * w0**2, b1 * w0**3, a0 * w0**4])
    return num, den


def _pole_pairs(den) -> list[tuple[float, float]]:
    """(w_n, zeta) of each complex pole pair of a 4th-order denominator, sorted by w_n."""
    r = np.roots(den)
    pairs = []
    used = np.zeros(len(r), bool)
    for i in np.argsort(-r.imag):
        if used[i]:
            continue
        j = int(np.argmin(np.where(used | (np.arange(len(r)) == i), np.inf, np.abs(r - np.conj(r[i])))))
        used[i] = used[j] = True
        # quadratic (s - r_i)(s - r_j) = s^2 - (r_i + r_j) s + r_i r_j
        wn2 = float((r[i] * r[j]).real)
        two_zw = float(-(r[i] + r[j]).real)
        wn = np.sqrt(abs(wn2))
        pairs.append((wn, two_zw / (2 * wn) if wn > 0 else 1.0))
    return sorted(pairs)


# --------------------------------------------------------------------------- nonlinear fits

def _quality(meas: FrfMeasurement, Hfit) -> dict:
    w = meas.weights
    return {
        "residual": complex_residual(meas.H, Hfit, w),
        "r2_mag": r2_magnitude(meas.H, Hfit),
        "r2_mag_db": r2_magnitude(meas.H, Hfit, db=True),
        "r2_phase": r2_phase(meas.H, Hfit),
        "n_points": int(len(meas.freq_hz)),
    }


def log_density_weights(freq_hz) -> np.ndarray:
    """Weights proportional to each point's share of log frequency (mean 1): every decade counts the
    same whatever the grid, so a linear grid does not let the top of the band dominate the fit."""
    x = np.log(np.asarray(freq_hz, float))
    if len(x) < 3:
        return np.ones_like(x)
    d = np.empty_like(x)
    d[1:-1] = 0.5 * (x[2:] - x[:-2])
    d[0], d[-1] = x[1] - x[0], x[-1] - x[-2]
    return d / np.mean(d)


def _rel_residual(meas: FrfMeasurement, Hmod):
    w = meas.weights * log_density_weights(meas.freq_hz)
    r = (Hmod - meas.H) / np.maximum(np.abs(meas.H), 1e-12) * np.sqrt(w)
    return np.concatenate([r.real, r.imag])


def _check_sweep(meas: FrfMeasurement, what: str) -> None:
    if len(meas.freq_hz) < 12:
        raise MeasurementError(meas.path or what, None, f"{what}: need at least 12 frequency points to fit "
                               f"Eq. 22, got {len(meas.freq_hz)}")


def fit_eq22(meas: FrfMeasurement) -> Eq22Fit:
    """Fit Eq. 22 to one sweep on its own.

    From a single FRF the two pole pairs cannot be told apart (their product is the same); the more
    lightly damped pair is taken as the drive's.  :func:`identify` resolves this properly from two
    sweeps (the drive pair is the one they share).
    """
    _check_sweep(meas, "sweep")
    s = 2j * np.pi * meas.freq_hz
    num, den = sk_fit(meas.freq_hz, meas.H, meas.weights)
    (w1, z1), (w2, z2) = _pole_pairs(den)
    (we, ze), (wm, zm) = ((w1, z1), (w2, z2)) if z1 <= z2 else ((w2, z2), (w1, z1))
    d0, d2 = we**2, 2 * ze * we
    d1 = _start_d1(num, wm, d0)
    x0 = np.array([np.log(wm), zm, 0.0, np.log(d0), d1 / np.sqrt(d0), d2 / np.sqrt(d0)])

    def fun(x):
        wn, zeta, tau = np.exp(x[0]), x[1], x[2] * 1e-4
        d0_ = np.exp(x[3])
        sq = np.sqrt(d0_)
        return _rel_residual(meas, eq22_response(s, wn, zeta, tau, d0_, x[4] * sq, x[5] * sq))

    res = _best_lsq(fun, x0, 2)
    x = res.x
    d0 = float(np.exp(x[3]))
    sq = np.sqrt(d0)
    wn, zeta, tau, d1, d2 = float(np.exp(x[0])), float(x[1]), float(x[2] * 1e-4), float(x[4] * sq), float(x[5] * sq)
    H = eq22_response(s, wn, zeta, tau, d0, d1, d2)
    return Eq22Fit(wn, zeta, tau, d0, d1, d2, **_quality(meas, H))


def _start_d1(num, wm, d0) -> float:
    """Starting ``d1`` from the linear fit's numerator ``n1 s`` term with ``tau = 0``: n1 = wm^2 d1."""
    return float(num[1] / wm**2) if wm > 0 else 0.0


def _best_lsq(fun, x0, i_tau: int, starts=(0.0, 0.5, -0.5), max_nfev: int = 4000,
              what: str = "Eq. 22 fit"):
    """Levenberg-Marquardt from several starting values of the scaled ``tau`` (index ``i_tau``) --
    the belt-damping zero is weakly determined -- keeping the lowest cost."""
    best = None
    for tau0 in starts:
        x = x0.copy()
        x[i_tau] = tau0
        try:
            r = least_squares(fun, x, method="lm", x_scale="jac", max_nfev=max_nfev)
        except (ValueError, np.linalg.LinAlgError):
            continue
        if best is None or r.cost < best.cost:
            best = r
    if best is None or not np.all(np.isfinite(best.x)):
        raise SolverError(f"{what} failed to converge (check the sweeps' frequency range and coherence)")
    return best


def identify(carriage: FrfMeasurement, assembled: FrfMeasurement, m_n: float, m_f: float) -> Identification:
    """Two-sweep identification of the paper's model (Section IV-A).

    Parameters
    ----------
    carriage : FrfMeasurement
        ``G_qd``: one carriage, effector and forearms detached (``kind: carriage``).
    assembled : FrfMeasurement
        ``G'_qd``: the same carriage with the effector attached, vertical sweep at the bed centre.
    m_n, m_f : float
        Measured masses of the effector and of one forearm pair, kg.

    Returns
    -------
    Identification
    """
    for name, v in (("m_n", m_n), ("m_f", m_f)):
        if not (np.isfinite(v) and v >= 0) or (name == "m_n" and v <= 0):
            raise ValueError(f"{name} must be a positive mass in kg, got {v!r}")
    _check_sweep(carriage, "carriage sweep")
    _check_sweep(assembled, "assembled sweep")
    if np.hypot(*assembled.position_mm[:2]) > 1.0:
        raise MeasurementError(assembled.path or "assembled", None,
                               f"the assembled sweep must be at the bed centre (x = y = 0); file says "
                               f"position_mm = {assembled.position_mm.tolist()}")
    # linear starts; the electrical pair is the one both sweeps share
    sk_c, sk_a = (sk_fit(m.freq_hz, m.H, m.weights) for m in (carriage, assembled))
    pc, pa = _pole_pairs(sk_c[1]), _pole_pairs(sk_a[1])
    best = None
    for i in range(2):
        for j in range(2):
            d = abs(np.log(pc[i][0] / pa[j][0])) + abs(pc[i][1] - pa[j][1])
            if best is None or d < best[0]:
                best = (d, i, j)
    _, ie, ja = best
    we = 0.5 * (pc[ie][0] + pa[ja][0])
    ze = 0.5 * (pc[ie][1] + pa[ja][1])
    wc, zc = pc[1 - ie]
    wa, za = pa[1 - ja]
    if not wa < wc:
        raise SolverError(
            f"the assembled sweep's mechanical resonance ({wa / 2 / np.pi:.2f} Hz) is not below the carriage "
            f"sweep's ({wc / 2 / np.pi:.2f} Hz): the effector mass cannot be separated (swapped files?)")
    d0 = we**2
    d1 = _start_d1(sk_c[0], wc, d0)
    sc, sa = 2j * np.pi * carriage.freq_hz, 2j * np.pi * assembled.freq_hz
    lo, hi = _BOUNDS_LO, _BOUNDS_HI
    r0 = wa / wc
    x0 = np.clip(np.array([np.log(wc), max(zc, 1e-3), r0, max(za - abs(zc) * r0, 1e-3), 0.0, np.log(d0),
                           d1 / we, max(2 * ze, 1e-3)]), lo + 1e-9, hi - 1e-9)

    def fun(x):
        wc_, zc_, wa_, za_, tau, d0_, d1_, d2_ = _unpack(x)
        return np.concatenate([
            _rel_residual(carriage, eq22_response(sc, wc_, zc_, tau, d0_, d1_, d2_)),
            _rel_residual(assembled, eq22_response(sa, wa_, za_, tau, d0_, d1_, d2_)),
        ])

    res = _best_lsq_bounded(fun, x0, 4, (0.0, 0.6, 1.5), (lo, hi))
    snap = np.isfinite(lo) & (np.abs(res.x - lo) <= 1e-7 * np.maximum(1.0, np.abs(lo)))
    res.x = np.where(snap, lo, res.x)  # a value on its bound is the bound (c = 0, not 6e-24)
    wc, zc, wa, za, tau, d0, d1, d2 = (float(v) for v in _unpack(res.x))
    m_nt = m_n + 1.5 * m_f
    m = m_nt * wa**2 / (3.0 * (wc**2 - wa**2))  # Eq. 33, sign fixed
    k = m * wc**2  # Eq. 27
    c = tau * k
    b = max(2.0 * zc * wc * m - c, 0.0)  # Eq. 26 (>= 0 by construction; rounding)
    m_p = m + m_nt / 3.0
    b_p = 2.0 * za * wa * m_p  # Eq. 31
    b_nt = max(3.0 * (b_p - c - b), 0.0)
    fit_c = Eq22Fit(wc, zc, tau, d0, d1, d2, **_quality(carriage, eq22_response(sc, wc, zc, tau, d0, d1, d2)))
    fit_a = Eq22Fit(wa, za, tau, d0, d1, d2, **_quality(assembled, eq22_response(sa, wa, za, tau, d0, d1, d2)))
    at_bound = tuple(name for name, i, side in _BOUND_NAMES
                     if abs(res.x[i] - (lo if side == "lo" else hi)[i]) <= 1e-6 * max(1.0, abs(res.x[i])))
    ident = Identification(m, c, b, k, b_nt, d0, d1, d2, float(m_n), float(m_f), fit_c, fit_a, at_bound)
    return replace(ident, warnings=tuple(quality_warnings(ident, carriage, assembled)))


# scaled parameters of the joint fit: log wc, zeta_c, wa/wc, za - zeta_c wa/wc, tau * 1e4, log d0,
# d1/sqrt(d0), d2/sqrt(d0).  b >= 0 <=> zeta_c >= tau wc / 2 and b_nt >= 0 <=> za >= zeta_c wa/wc
# (Eqs. 26, 31, 33); c >= 0 <=> tau >= 0; m > 0 <=> wa < wc.  zeta_c is written tau wc/2 + e_b.
_BOUNDS_LO = np.array([-np.inf, 0.0, 0.05, 0.0, 0.0, -np.inf, -5.0, 0.0])
_BOUNDS_HI = np.array([np.inf, 2.0, 0.995, 2.0, 50.0, np.inf, 5.0, 4.0])
_BOUND_NAMES = (("b = 0 (guide damping)", 1, "lo"), ("b_nt = 0 (effector damping)", 3, "lo"),
                ("c = 0 (belt damping)", 4, "lo"), ("m at its largest (assembled mode almost at the carriage "
                                                   "mode)", 2, "hi"), ("m at its smallest", 2, "lo"))


def _unpack(x):
    wc = np.exp(x[0])
    tau = x[4] * 1e-4
    zc = tau * wc / 2.0 + x[1]
    wa = x[2] * wc
    za = zc * x[2] + x[3]
    d0 = np.exp(x[5])
    sq = np.sqrt(d0)
    return wc, zc, wa, za, tau, d0, x[6] * sq, x[7] * sq


def _best_lsq_bounded(fun, x0, i_tau, starts, bounds, max_nfev: int = 4000):
    """Trust-region reflective fit within physical bounds from several starts of ``tau``."""
    best = None
    for tau0 in starts:
        x = x0.copy()
        x[i_tau] = tau0
        try:
            r = least_squares(fun, x, bounds=bounds, method="trf", x_scale="jac", max_nfev=max_nfev)
        except (ValueError, np.linalg.LinAlgError):
            continue
        if best is None or r.cost < best.cost:
            best = r
    if best is None or not np.all(np.isfinite(best.x)):
        raise SolverError("joint identification fit failed to converge (check the sweeps' frequency range and "
                          "coherence)")
    return best


def worst_band(meas: FrfMeasurement, Hfit, per_octave: float = 3.0) -> tuple[float, float, float]:
    """``(lo_hz, hi_hz, residual)`` of the 1/``per_octave``-octave band where the fit is worst."""
    f = meas.freq_hz
    edges = 2.0 ** np.arange(np.floor(np.log2(f[0]) * per_octave), np.ceil(np.log2(f[-1]) * per_octave) + 1)
    edges = edges ** (1.0 / per_octave)
    best = (float(f[0]), float(f[-1]), float("nan"))
    for a, b in zip(edges[:-1], edges[1:]):
        sel = (f >= a) & (f < b)
        if sel.sum() < 3:
            continue
        r = complex_residual(meas.H[sel], Hfit[sel], meas.weights[sel])
        if not np.isfinite(best[2]) or r > best[2]:
            best = (float(a), float(b), float(r))
    return best


def quality_warnings(ident: "Identification", carriage: FrfMeasurement, assembled: FrfMeasurement,
                     noise_floor: float | None = None, factor: float = 1.3) -> list[str]:
    """Warnings on an identification: fit residuals above the noise (where, and what to do), bounds hit."""
    from ..measure.noise import noise_floors

    nfs = noise_floors([carriage, assembled], override=noise_floor,
                       predictions=[ident.carriage_fit.response(carriage.freq_hz),
                                    ident.assembled_fit.response(assembled.freq_hz)])
    out = []
    bad = []
    for (name, meas, fit), nu in zip((("carriage", carriage, ident.carriage_fit),
                                      ("assembled", assembled, ident.assembled_fit)), nfs.values):
        if nu > 0 and fit.residual > factor * nu:
            lo, hi, r = worst_band(meas, fit.response(meas.freq_hz))
            bad.append((name, meas, fit, nu, lo, hi, r))
    for name, meas, fit, nu, lo, hi, r in bad:
        where = meas.path or meas.label
        out.append(f"the 4th-order model (Eq. 22) does not fit the {name} sweep ({where}): residual "
                   f"{fit.residual:.4f}, {fit.residual / nu:.1f}x its noise floor {nu:.4f}; worst in "
                   f"{lo:.0f}-{hi:.0f} Hz (residual {r:.3f} there)")
    if bad:
        strong = max(b[2].residual / b[3] for b in bad)
        if strong > 5:
            out.append("a misfit this large and this local is a mode or lag the paper's model does not have (a "
                       "compliant motor mount, a frame mode): the profile written is the best physical fit; measure "
                       "sweeps at several poses and run `ffcomp diagnose`, then describe the missing part as an "
                       "effect plug-in (docs/effects_example_motor_mount.py)")
        else:
            out.append("the two-sweep identification assumes three equal towers and no effect at the centre, and its "
                       "result is biased if not: add the carriage sweeps of towers B and C (kind: carriage, input and "
                       "output qB, qC) with --sweep and identify uses them; or refit the base with the effects from "
                       "sweeps at several poses (`ffcomp fit DATA --profile OUT`, which refits the base dynamics)")
    if ident.at_bound:
        out.append("at a physical bound: " + ", ".join(ident.at_bound) + " -- the sweeps ask for a value beyond it "
                   "(a sign the model structure does not fit them)")
    return out

