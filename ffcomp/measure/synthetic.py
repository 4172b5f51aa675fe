"""Synthetic measurements from a model with known parameters (ground truth for tests and demos)."""

from __future__ import annotations

import numpy as np

from ..model.lpv import LpvModel, frequency_response
from ..model.submodels import g_qd
from .frf_file import FrfMeasurement

__all__ = ["add_complex_noise", "identification_sweeps", "default_sweep_freqs"]


def default_sweep_freqs(f_lo_hz: float = 3.0, f_hi_hz: float = 500.0, n: int = 800) -> np.ndarray:
    """Log-spaced sweep frequencies, Hz."""
    return np.geomspace(f_lo_hz, f_hi_hz, n)


def add_complex_noise(H, rel: float, rng: np.random.Generator):
    """Multiply by ``1 + rel * n``, ``n`` circular complex Gaussian of unit variance; coherence model
    ``1 / (1 + rel^2)`` (signal-to-noise power ratio ``1 / rel^2``)."""
    n = (rng.standard_normal(np.shape(H)) + 1j * rng.standard_normal(np.shape(H))) / np.sqrt(2.0)
    coh = np.full(np.shape(H), 1.0 / (1.0 + rel**2))
    return np.asarray(H) * (1.0 + rel * n), coh


def identification_sweeps(profile, freq_hz=None, *, noise: float = 0.02, seed: int = 0, z_mm: float = 30.0):
    """The paper's two identification sweeps, computed from ``profile`` with relative noise.

    Returns
    -------
    carriage, assembled : FrfMeasurement
        ``G_qd`` of carriage A (effector detached) and ``z -> qA`` at ``(0, 0, z_mm)``.
    """
    f = default_sweep_freqs() if freq_hz is None else np.asarray(freq_hz, float)
    rng = np.random.default_rng(seed)
    d = profile.dynamics
    s = 2j * np.pi * f
    Hc = g_qd(s, d.m[0], d.c[0], d.b[0], d.k[0], d.d0[0], d.d1[0], d.d2[0])
    model = LpvModel.from_profile(profile)
    pos = np.array([0.0, 0.0, z_mm])
    Ha = frequency_response(model, pos[None] * 1e-3, f, frame="task_to_joint")[0, 0, 2]
    Hc, cc = add_complex_noise(Hc, noise, rng)
    Ha, ca = add_complex_noise(Ha, noise, rng)
    src = f"synthetic from profile {profile.name!r}, {noise * 100:g}% complex noise, seed {seed}"
    carriage = FrfMeasurement(f, Hc, cc, "carriage", pos, "qA", "qA", src)
    assembled = FrfMeasurement(f, Ha, ca, "assembled", pos, "z", "qA", src)
    return carriage, assembled
