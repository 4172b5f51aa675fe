"""Virtual FRF measurements: a small periodic chirp through the nonlinear simulator, H1 estimate.

The excitation is a *periodic* linear chirp around a pose: one period sweeps ``f_lo -> f_hi`` in
``period_s`` and ends in phase (the end frequency is nudged so that the phase closes on a whole
number of turns), and the period is repeated.  After the first period (discarded: start
transient) the response is periodic, so Welch segments of exactly one period with a rectangular
window see no leakage and the H1 estimate ``S_xy / S_xx`` (``scipy.signal.csd`` / ``welch``) is
exact at the bins ``k / period_s`` for a linear plant; coherence (``scipy.signal.coherence``)
drops below 1 only through nonlinearity or the optional output noise.

The commands are linearly interpolated between samples (``hold="linear"``) and the estimate is
divided by that interpolator's response ``sinc^2(f / fs)``, so it estimates the continuous plant
(with ``hold="zoh"`` the zero-order hold's ``sinc(f / fs) exp(-j pi f / fs)`` is removed instead).

Kinds (``shared/FRF_FORMAT.md``):

* ``assembled``: the complete printer; input ``x|y|z`` (nozzle command, carriages follow by exact
  inverse kinematics) or ``qA|qB|qC`` (one carriage), output any coordinate (nozzle coordinates
  are ``forward(q)``);
* ``carriage``: forearms and effector detached (:meth:`DeltaPlant.carriage_only`: ``m_nt = b_nt
  = 0``, carriage mass ``m`` = carriage + half a forearm pair as in Eq. 21, the paper's first
  sweep); input and output must be carriages.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import signal

from ..kinematics import check_reachable, inverse
from ..measure.frf_file import FrfMeasurement
from .plant import DeltaPlant

__all__ = ["SweepSpec", "periodic_chirp", "virtual_frf", "h1_estimate"]

_TASK = ("x", "y", "z")
_JOINT = ("qA", "qB", "qC")


@dataclass(frozen=True)
class SweepSpec:
    """Excitation and analysis settings of a virtual measurement.

    Attributes
    ----------
    f_lo_hz, f_hi_hz : float
        Swept band, Hz (the file keeps the bins inside it).
    period_s : float
        Chirp period, s; the frequency resolution is ``1 / period_s``.
    periods : int
        Periods averaged (one more is run first and discarded).
    amplitude_mm : float
        Chirp amplitude, mm.  The plant is nonlinear: quadratic distortion (pose-dependent
        ``J^T J``, ``J' q'``, forward kinematics) grows with it; at 0.02 mm it stays below ~2 % of
        the response even in the chirp's weakest bins, and below 1e-4 near the resonances.
    rate_hz : float
        Command and output sample rate, Hz.
    substeps : int
        Integration steps per sample.
    pose_every : int
        Integration steps between pose-matrix evaluations (the pose hardly moves in a sweep).
    hold : {"linear", "zoh"}
        Command interpolation (see the module notes).
    noise_um : float
        RMS of white noise added to the measured output, um (0: none).
    seed : int
        Noise seed.
    """

    f_lo_hz: float = 5.0
    f_hi_hz: float = 300.0
    period_s: float = 1.0
    periods: int = 3
    amplitude_mm: float = 0.02
    rate_hz: float = 2000.0
    substeps: int = 5
    pose_every: int = 10
    hold: str = "linear"
    noise_um: float = 0.0
    seed: int = 0

    def validate(self) -> None:
        if not (0 < self.f_lo_hz < self.f_hi_hz < 0.5 * self.rate_hz):
            raise ValueError(f"need 0 < f_lo < f_hi < rate/2, got {self.f_lo_hz}, {self.f_hi_hz}, "
                             f"{self.rate_hz}")
        if self.period_s * self.f_lo_hz < 1 or self.periods < 1 or self.amplitude_mm <= 0:
            raise ValueError("need period_s >= 1 / f_lo_hz, periods >= 1 and amplitude_mm > 0")


def periodic_chirp(spec: SweepSpec) -> tuple[np.ndarray, np.ndarray]:
    """Unit-amplitude periodic linear chirp, ``periods + 1`` periods.

    Returns
    -------
    t_s : ndarray, shape (N,)
    x : ndarray, shape (N,)
        Starts at 0; one period sweeps ``f_lo`` to (about) ``f_hi`` and closes its phase.
    """
    T = spec.period_s
    f0 = spec.f_lo_hz
    # phase over one period 2 pi T (f0 + f1) / 2 must be a whole number of turns
    turns = math.floor(T * (f0 + spec.f_hi_hz) / 2.0)
    f1 = 2.0 * turns / T - f0
    n_per = int(round(T * spec.rate_hz))
    t = np.arange((spec.periods + 1) * n_per + 1) / spec.rate_hz
    tau = np.mod(t, T)
    phase = 2 * np.pi * (f0 * tau + 0.5 * (f1 - f0) * tau**2 / T)
    return t, np.sin(phase)


def h1_estimate(x: np.ndarray, y: np.ndarray, fs_hz: float, nperseg: int):
    """H1 = S_xy / S_xx and coherence over rectangular, non-overlapping segments of ``nperseg``.

    Returns ``freq_hz`` (F,), ``H`` (F,) complex, ``coherence`` (F,).
    """
    kw = dict(fs=fs_hz, window="boxcar", nperseg=nperseg, noverlap=0, detrend=False)
    f, Sxy = signal.csd(x, y, **kw)
    _, Sxx = signal.welch(x, **kw)
    _, coh = signal.coherence(x, y, **kw)
    with np.errstate(invalid="ignore", divide="ignore"):
        H = Sxy / Sxx
    return f, H, coh


def _hold_response(f_hz: np.ndarray, fs_hz: float, hold: str) -> np.ndarray:
    r = f_hz / fs_hz
    return np.sinc(r) ** 2 if hold == "linear" else np.sinc(r) * np.exp(-1j * np.pi * r)


def virtual_frf(plant: DeltaPlant, at_mm, input_: str = "z", output: str = "qA", *, kind: str = "assembled",
                spec: SweepSpec | None = None, source: str | None = None) -> FrfMeasurement:
    """Measure one FRF on the nonlinear simulator around ``at_mm``.

    Parameters
    ----------
    plant : DeltaPlant
        The assembled printer (for ``kind="carriage"`` its :meth:`~DeltaPlant.carriage_only` is used).
    at_mm : (x, y, z)
        Nozzle position of the sweep, mm (for ``carriage``: the point whose carriage heights are used).
    input_, output : str
        ``x, y, z, qA, qB, qC`` (see the module notes for what each kind allows).
    kind : {"assembled", "carriage"}
    spec : SweepSpec, optional
    source : str, optional
        Free text for the file header.

    Returns
    -------
    FrfMeasurement
        Bins inside ``[f_lo_hz, f_hi_hz]``, with coherence.
    """
    spec = spec or SweepSpec()
    spec.validate()
    if kind not in ("assembled", "carriage"):
        raise ValueError(f"kind must be 'assembled' or 'carriage', got {kind!r}")
    for name, v in (("input", input_), ("output", output)):
        if v not in _TASK + _JOINT:
            raise ValueError(f"{name} must be one of {', '.join(_TASK + _JOINT)}, got {v!r}")
    if kind == "carriage":
        if input_ not in _JOINT or output not in _JOINT:
            raise ValueError("kind 'carriage' (effector detached) needs carriage input and output "
                             "(qA, qB, qC)")
        plant = plant.carriage_only()
    geom = plant.geometry
    X0 = np.asarray(at_mm, float) * 1e-3
    check_reachable(geom, X0[None], what="sweep position")
    q0 = inverse(geom, X0)
    t, x_unit = periodic_chirp(spec)
    x = spec.amplitude_mm * 1e-3 * x_unit
    if input_ in _TASK:
        Xc = np.repeat(X0[None], t.shape[0], axis=0)
        Xc[:, _TASK.index(input_)] += x
        q_cmd = inverse(geom, Xc)
    else:
        q_cmd = np.repeat(q0[None], t.shape[0], axis=0)
        q_cmd[:, _JOINT.index(input_)] += x
    res = plant.simulate(t, q_cmd, substeps=spec.substeps, hold=spec.hold, pose_every=spec.pose_every)
    if output in _TASK:
        y = res.xyz_m[0, :, _TASK.index(output)] - X0[_TASK.index(output)]
    else:
        y = res.q_m[0, :, _JOINT.index(output)] - q0[_JOINT.index(output)]
    if spec.noise_um > 0:
        y = y + np.random.default_rng(spec.seed).normal(0.0, spec.noise_um * 1e-6, y.shape)
    n_per = int(round(spec.period_s * spec.rate_hz))
    keep = slice(n_per, n_per * (spec.periods + 1))  # drop the first (transient) period
    f, H, coh = h1_estimate(x[keep], y[keep], spec.rate_hz, n_per)
    H = H / _hold_response(f, spec.rate_hz, spec.hold)
    band = (f >= spec.f_lo_hz) & (f <= spec.f_hi_hz)
    src = source or (f"ffcomp virtual measurement: nonlinear simulator, periodic chirp {spec.f_lo_hz:g}-"
                     f"{spec.f_hi_hz:g} Hz, {spec.amplitude_mm:g} mm, {spec.periods} x {spec.period_s:g} s, "
                     f"noise {spec.noise_um:g} um")
    return FrfMeasurement(f[band], H[band], np.clip(coh[band], 0.0, 1.0), kind, np.asarray(at_mm, float),
                          input_, output, src)
