"""Klipper's input shapers, as Klipper defines them, and their application to trajectories.

The shaper definitions follow Klipper's ``klippy/extras/shaper_defs.py`` (ZV, MZV, ZVD, EI,
2HUMP_EI, 3HUMP_EI; default damping ratio 0.1; EI vibration tolerance 0.05 = 1/20).  The
figures of merit follow ``klippy/extras/shaper_calibrate.py``: :func:`residual_vibration` is
``_estimate_shaper`` and :func:`shaper_smoothing` is ``_get_shaper_smoothing``.

Klipper normalises the amplitudes to sum one and shifts the pulse times by their amplitude-
weighted mean (``kin_shaper.c``), so that shaping is the identity for constant-velocity motion.
It then evaluates ``sum_i A_i x(t - T_i)`` on the Cartesian X and Y (optionally Z) coordinates
*before* the kinematics, which on a delta printer means before the inverse kinematics to the
carriages; :func:`shape_cartesian` does the same on sampled trajectories.

Units: times in s, frequencies in Hz (the user-facing unit of a shaper), positions in whatever
unit the caller uses (shaping is linear); :func:`shaper_smoothing` uses Klipper's mm, mm/s and
mm/s^2 because its result is compared against Klipper's numbers.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from ffcomp.errors import FfcompError

DEFAULT_DAMPING_RATIO = 0.1
"""Klipper's ``DEFAULT_DAMPING_RATIO``."""

SHAPER_VIBRATION_REDUCTION = 20.0
"""Klipper's ``SHAPER_VIBRATION_REDUCTION``; the EI tolerance is its reciprocal."""

EI_VIBRATION_TOLERANCE = 1.0 / SHAPER_VIBRATION_REDUCTION
"""Vibration tolerance (0.05) the EI shaper is designed for."""


class ShaperError(FfcompError, ValueError):
    """A shaper name, frequency, damping ratio or spec string is not usable."""

    exit_code = 2


ShaperFn = Callable[[float, float], "tuple[np.ndarray, np.ndarray]"]


def _damped_period_s(freq_hz: float, damping_ratio: float) -> float:
    """Damped period ``t_d = 1 / (f sqrt(1 - zeta^2))`` of the shaper's design oscillator."""
    return 1.0 / (freq_hz * math.sqrt(1.0 - damping_ratio**2))


def _zv_k(damping_ratio: float) -> float:
    """Per-half-period amplitude decay ``K = exp(-zeta pi / sqrt(1 - zeta^2))``."""
    return math.exp(-damping_ratio * math.pi / math.sqrt(1.0 - damping_ratio**2))


def _zv(freq_hz: float, damping_ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """ZV: two pulses half a damped period apart, ratio ``K``."""
    k, t_d = _zv_k(damping_ratio), _damped_period_s(freq_hz, damping_ratio)
    return np.array([1.0, k]), np.array([0.0, 0.5 * t_d])


def _zvd(freq_hz: float, damping_ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """ZVD: ZV convolved with itself, pulses ``1, 2K, K^2`` over one damped period."""
    k, t_d = _zv_k(damping_ratio), _damped_period_s(freq_hz, damping_ratio)
    return np.array([1.0, 2.0 * k, k * k]), np.array([0.0, 0.5 * t_d, t_d])


def _mzv(freq_hz: float, damping_ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """MZV: three pulses over 0.75 damped period.

    Undamped amplitudes ``(1 - 1/sqrt2, sqrt2 - 1, 1 - 1/sqrt2)`` place zeros at ``f`` and
    ``5f/3``; each later pulse is scaled by ``K = exp(-0.75 zeta pi / sqrt(1 - zeta^2))``.  This
    is the closed form of Klipper's generalised ``get_mzv_coeffs(n=3, t=0.75)`` default.
    """
    df = math.sqrt(1.0 - damping_ratio**2)
    k = math.exp(-0.75 * damping_ratio * math.pi / df)
    t_d = _damped_period_s(freq_hz, damping_ratio)
    a_end = 1.0 - 1.0 / math.sqrt(2.0)
    a = np.array([a_end, (math.sqrt(2.0) - 1.0) * k, a_end * k * k])
    return a, np.array([0.0, 0.375 * t_d, 0.75 * t_d])


def _ei(freq_hz: float, damping_ratio: float,
        v_tol: float = EI_VIBRATION_TOLERANCE) -> tuple[np.ndarray, np.ndarray]:
    """EI (extra-insensitive), Singer's polynomial fit in damping ratio and tolerance."""
    z, v = damping_ratio, v_tol
    a1 = (0.24968 + 0.24961 * v) + ((0.80008 + 1.23328 * v) + (0.49599 + 3.17316 * v) * z) * z
    a3 = (0.25149 + 0.21474 * v) + ((-0.83249 + 1.41498 * v) + (0.85181 - 4.90094 * v) * z) * z
    t2 = 0.4999 + (
        (0.46159 + 8.57843 * v) * v
        + ((4.26169 - 108.644 * v) * v + (1.75601 + 336.989 * v) * v * z) * z
    ) * z
    t_d = _damped_period_s(freq_hz, damping_ratio)
    return np.array([a1, 1.0 - a1 - a3, a3]), np.array([0.0, t2 * t_d, t_d])


# Singer's multi-hump EI fits: row i holds the cubic-in-damping-ratio coefficients
# (ascending powers) of pulse i's time (in units of 1/freq) and amplitude.
_HUMP_COEFFS = {
    "2hump_ei": (
        np.array([[0.0, 0.0, 0.0, 0.0],
                  [0.49890, 0.16270, -0.54262, 6.16180],
                  [0.99748, 0.18382, -1.58270, 8.17120],
                  [1.49920, -0.09297, -0.28338, 1.85710]]),
        np.array([[0.16054, 0.76699, 2.26560, -1.22750],
                  [0.33911, 0.45081, -2.58080, 1.73650],
                  [0.34089, -0.61533, -0.68765, 0.42261],
                  [0.15997, -0.60246, 1.00280, -0.93145]]),
    ),
    "3hump_ei": (
        np.array([[0.0, 0.0, 0.0, 0.0],
                  [0.49974, 0.23834, 0.44559, 12.4720],
                  [0.99849, 0.29808, -2.36460, 23.3990],
                  [1.49870, 0.10306, -2.01390, 17.0320],
                  [1.99960, -0.28231, 0.61536, 5.40450]]),
        np.array([[0.11275, 0.76632, 3.29160, -1.44380],
                  [0.23698, 0.61164, -2.57850, 4.85220],
                  [0.30008, -0.19062, -2.14560, 0.13744],
                  [0.23775, -0.73297, 0.46885, -2.08650],
                  [0.11244, -0.45439, 0.96382, -1.46000]]),
    ),
}


def _hump(name: str) -> ShaperFn:
    """Definition function for a multi-hump EI shaper from its expansion coefficients."""
    t_coeffs, a_coeffs = _HUMP_COEFFS[name]

    def definition(freq_hz: float, damping_ratio: float) -> tuple[np.ndarray, np.ndarray]:
        t_s = np.polynomial.polynomial.polyval(damping_ratio, t_coeffs.T) / freq_hz
        a = np.polynomial.polynomial.polyval(damping_ratio, a_coeffs.T)
        return a, t_s

    definition.__doc__ = f"{name.upper()}: Singer's fit, pulses about half a period apart."
    return definition


SHAPERS: dict[str, ShaperFn] = {
    "zv": _zv,
    "mzv": _mzv,
    "zvd": _zvd,
    "ei": _ei,
    "2hump_ei": _hump("2hump_ei"),
    "3hump_ei": _hump("3hump_ei"),
}
"""Klipper shaper name -> ``f(freq_hz, damping_ratio) -> (A, T_s)`` in Klipper's raw form
(amplitudes not normalised, first pulse at t = 0)."""

MIN_FREQ_HZ: dict[str, float] = {
    "zv": 21.0, "mzv": 23.0, "zvd": 29.0, "ei": 29.0, "2hump_ei": 39.0, "3hump_ei": 48.0,
}
"""Klipper's auto-tuning lower frequency bound per shaper (projected max_accel ~ 1500)."""

MAX_DAMPING_RATIO: dict[str, float] = {
    "zv": 0.99, "mzv": 0.99, "zvd": 0.99, "ei": 0.4, "2hump_ei": 0.3, "3hump_ei": 0.2,
}
"""Klipper's largest damping ratio per shaper (the EI fits are not valid beyond it)."""


def _lookup(name: str) -> ShaperFn:
    key = str(name).strip().lower()
    if key not in SHAPERS:
        raise ShaperError(f"unknown shaper {name!r}; known: {', '.join(SHAPERS)}")
    return SHAPERS[key]


def shaper_impulses(name: str, freq_hz: float,
                    damping_ratio: float = DEFAULT_DAMPING_RATIO) -> tuple[np.ndarray, np.ndarray]:
    """Impulses of a Klipper shaper, normalised and centred as Klipper applies them.

    Parameters
    ----------
    name : str
        Shaper name, case-insensitive: one of :data:`SHAPERS` (``"zv"``, ``"mzv"``, ``"zvd"``,
        ``"ei"``, ``"2hump_ei"``, ``"3hump_ei"``).
    freq_hz : float
        Shaper (design) frequency in Hz, > 0.
    damping_ratio : float, optional
        Design damping ratio, ``0 <= zeta <=`` :data:`MAX_DAMPING_RATIO`; Klipper's default 0.1.

    Returns
    -------
    A : ndarray, shape (n,)
        Amplitudes, summing to 1.
    T_s : ndarray, shape (n,)
        Pulse times in s, increasing, shifted so that ``sum(A * T_s) == 0``.
    """
    fn = _lookup(name)
    if not (np.isfinite(freq_hz) and freq_hz > 0.0):
        raise ShaperError(f"shaper frequency must be a positive number of Hz, got {freq_hz!r}")
    max_zeta = MAX_DAMPING_RATIO[str(name).strip().lower()]
    if not (0.0 <= damping_ratio <= max_zeta):
        raise ShaperError(f"damping ratio for {name!r} must be in [0, {max_zeta}], got {damping_ratio!r}")
    a, t_s = fn(float(freq_hz), float(damping_ratio))
    a = np.asarray(a, dtype=float)
    a = a / a.sum()
    t_s = np.asarray(t_s, dtype=float)
    return a, t_s - np.dot(a, t_s)


def parse_shaper_spec(spec: str) -> tuple[str, float]:
    """Parse ``"name@freq"`` (e.g. ``"mzv@42.5"``) into ``(name, freq_hz)``.

    The name is lower-cased and must be in :data:`SHAPERS`; the frequency must be a finite
    positive number of Hz.  Errors (:class:`ShaperError`, a ``ValueError``) name the bad part.
    """
    text = str(spec).strip()
    name, sep, freq_text = text.partition("@")
    if not sep:
        raise ShaperError(f"shaper spec {spec!r} has no '@': expected 'name@freq_hz', e.g. 'mzv@42.5'")
    name = name.strip().lower()
    if not name:
        raise ShaperError(f"shaper spec {spec!r}: missing shaper name before '@'")
    _lookup(name)
    freq_text = freq_text.strip()
    try:
        freq_hz = float(freq_text)
    except ValueError:
        raise ShaperError(f"shaper spec {spec!r}: frequency {freq_text!r} is not a number") from None
    if not (math.isfinite(freq_hz) and freq_hz > 0.0):
        raise ShaperError(f"shaper spec {spec!r}: frequency {freq_text!r} must be a positive number of Hz")
    return name, freq_hz


def _uniform_step_s(t_s: np.ndarray) -> float:
    """Sample step of a uniform time grid; raises ``ValueError`` if it is not uniform."""
    t_s = np.asarray(t_s, dtype=float)
    if t_s.ndim != 1 or t_s.size < 2:
        raise ValueError("t_s must be a 1-D grid of at least two samples")
    dt_s = (t_s[-1] - t_s[0]) / (t_s.size - 1)
    if not dt_s > 0.0 or not np.allclose(np.diff(t_s), dt_s, rtol=1e-6, atol=0.0):
        raise ValueError("t_s must be increasing and uniformly spaced")
    return float(dt_s)


def _delayed(x: np.ndarray, delay_samples: float) -> np.ndarray:
    """``x`` at fractional index ``j - delay_samples`` (linear interpolation, edges held)."""
    n = x.shape[0]
    pos = np.clip(np.arange(n) - delay_samples, 0.0, n - 1.0)
    i0 = np.minimum(pos.astype(np.intp), n - 2)
    w = (pos - i0).reshape((n,) + (1,) * (x.ndim - 1))
    return x[i0] * (1.0 - w) + x[i0 + 1] * w


def apply_shaper(t_s: np.ndarray, x: np.ndarray, A: np.ndarray, T_s: np.ndarray) -> np.ndarray:
    """Shape a uniformly sampled trajectory: ``y(t) = sum_i A_i x(t - T_i)``.

    Parameters
    ----------
    t_s : ndarray, shape (N,)
        Uniform sample times in s.
    x : ndarray, shape (N,) or (N, k)
        Trajectory samples (any length unit).
    A, T_s : ndarray, shape (n,)
        Pulse amplitudes and times in s, as from :func:`shaper_impulses` (use them as given: no
        normalisation or centring is applied here).

    Returns
    -------
    ndarray, same shape as ``x``
        Shaped trajectory. Fractional delays use linear interpolation between samples; times
        before the first or after the last sample take the first or last value.
    """
    dt_s = _uniform_step_s(t_s)
    x = np.asarray(x, dtype=float)
    if x.shape[:1] != (np.size(t_s),) or x.ndim not in (1, 2):
        raise ValueError(f"x must have shape (N,) or (N, k) with N = {np.size(t_s)}, got {x.shape}")
    A, T_s = np.asarray(A, dtype=float), np.asarray(T_s, dtype=float)
    if A.shape != T_s.shape or A.ndim != 1 or A.size == 0:
        raise ValueError("A and T_s must be non-empty 1-D arrays of equal length")
    out = np.zeros_like(x)
    for a, tau_s in zip(A, T_s, strict=True):
        out += a * _delayed(x, tau_s / dt_s)
    return out


def shape_cartesian(t_s: np.ndarray, xyz: np.ndarray,
                    shaper_x: tuple[np.ndarray, np.ndarray] | None,
                    shaper_y: tuple[np.ndarray, np.ndarray] | None,
                    shaper_z: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Shape the Cartesian axes of a trajectory independently, as Klipper does before kinematics.

    Parameters
    ----------
    t_s : ndarray, shape (N,)
        Uniform sample times in s.
    xyz : ndarray, shape (N, 3)
        Effector trajectory (any length unit).
    shaper_x, shaper_y, shaper_z : (A, T_s) or None
        Impulses per axis (from :func:`shaper_impulses`); ``None`` leaves that axis unshaped.
        Klipper shapes X and Y; Z only when ``shaper_type_z``/``shaper_freq_z`` are set.

    Returns
    -------
    ndarray, shape (N, 3)
        Shaped trajectory, to be passed through the inverse kinematics afterwards.
    """
    xyz = np.asarray(xyz, dtype=float)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"xyz must have shape (N, 3), got {xyz.shape}")
    out = xyz.copy()
    for axis, shaper in enumerate((shaper_x, shaper_y, shaper_z)):
        if shaper is not None:
            out[:, axis] = apply_shaper(t_s, xyz[:, axis], *shaper)
    return out


def shaper_smoothing(A: np.ndarray, T_s: np.ndarray, accel_mm_s2: float = 5000.0,
                     scv_mm_s: float = 5.0) -> float:
    """Klipper's smoothing estimate ``_get_shaper_smoothing`` in mm.

    The larger of two offsets of the shaped path from the commanded one: at a 90 degree corner
    taken at square-corner velocity ``scv`` then accelerating at ``accel`` (pulses after the
    weighted-mean time ``ts`` only, times sqrt 2 for two axes),
    ``sqrt2 * sum_{T_i >= ts} A_i (scv + accel/2 (T_i - ts)) (T_i - ts)``, and at a 180 degree
    reversal, ``sum_i A_i accel/2 (T_i - ts)^2``; amplitudes normalised by ``sum(A)``.

    Parameters
    ----------
    A, T_s : ndarray, shape (n,)
        Pulse amplitudes and times in s (centred or not; ``ts`` is computed here).
    accel_mm_s2 : float, optional
        Acceleration in mm/s^2 (Klipper's default 5000).
    scv_mm_s : float, optional
        Square corner velocity in mm/s (Klipper's default 5).

    Returns
    -------
    float
        Smoothing in mm.
    """
    A, T_s = np.asarray(A, dtype=float), np.asarray(T_s, dtype=float)
    a = A / A.sum()
    dt = T_s - np.dot(a, T_s)
    half_accel = 0.5 * accel_mm_s2
    after = dt >= 0.0
    offset_90 = math.sqrt(2.0) * np.sum(a[after] * (scv_mm_s + half_accel * dt[after]) * dt[after])
    offset_180 = np.sum(a * half_accel * dt**2)
    return float(max(offset_90, offset_180))


def residual_vibration(A: np.ndarray, T_s: np.ndarray, freq_hz: np.ndarray | float,
                       damping_ratio: float = DEFAULT_DAMPING_RATIO) -> np.ndarray:
    """Remaining vibration ratio of a damped oscillator after the shaper (Klipper ``_estimate_shaper``).

    ``|sum_i A_i exp(-zeta w (T_n - T_i)) exp(j w_d T_i)| / sum_i A_i`` with ``w = 2 pi f`` and
    ``w_d = w sqrt(1 - zeta^2)``: the amplitude of ringing left after the last pulse, relative
    to a single unit pulse at ``T_n``. 1 means no reduction, 0 full cancellation.

    Parameters
    ----------
    A, T_s : ndarray, shape (n,)
        Pulse amplitudes and increasing times in s (a time shift does not change the result).
    freq_hz : float or ndarray, any shape
        Natural frequencies of the oscillator in Hz.
    damping_ratio : float, optional
        Damping ratio of the oscillator (not necessarily the shaper's design value).

    Returns
    -------
    ndarray, shape of ``freq_hz``
        Residual vibration ratio.
    """
    A, T_s = np.asarray(A, dtype=float), np.asarray(T_s, dtype=float)
    freq_hz = np.asarray(freq_hz, dtype=float)
    omega_rad_s = 2.0 * np.pi * freq_hz[..., None]
    omega_d_rad_s = omega_rad_s * math.sqrt(1.0 - damping_ratio**2)
    w = A * np.exp(-damping_ratio * omega_rad_s * (T_s[-1] - T_s))
    s = np.sum(w * np.sin(omega_d_rad_s * T_s), axis=-1)
    c = np.sum(w * np.cos(omega_d_rad_s * T_s), axis=-1)
    return np.hypot(s, c) / A.sum()
